//! Exact (erf) GELU with an exact gradient (network.md §5.1, §11.1).
//!
//! Burn 0.22.1's built-in GELU back-propagates the tanh approximation's derivative on ndarray
//! and wgpu. Composing the activation from `erf` (whose autodiff backward is the exact
//! `2/sqrt(pi) exp(-x^2)`) gives PyTorch's exact forward and backward.

use burn::tensor::{Tensor, TensorData};

use crate::host_dense::read_values;
use crate::host_mlp::gelu_in_place;
use crate::ops::is_cpu_device;

/// `GELU(x) = 0.5 x (1 + erf(x / sqrt(2)))`, element-wise, any shape.
///
/// Gradient (through autodiff of the composition):
/// `0.5 (1 + erf(x/sqrt 2)) + x exp(-x^2/2) / sqrt(2 pi)`.
///
/// An untracked tensor on a CPU device is computed on the host over the rayon pool
/// ([`crate::host_mlp::gelu_in_place`], the same f32 operations): Burn's element-wise ops run
/// on one thread there.
pub fn gelu<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    if let Some(y) = host_gelu(&x) {
        return y;
    }
    let cdf = x
        .clone()
        .mul_scalar(std::f64::consts::FRAC_1_SQRT_2)
        .erf()
        .add_scalar(1.0)
        .mul_scalar(0.5);
    x * cdf
}

/// `GELU(x)` on the host for an untracked `x` on a CPU device; `None` otherwise (or when the
/// readback fails).
fn host_gelu<const D: usize>(x: &Tensor<D>) -> Option<Tensor<D>> {
    let device = x.device();
    if !is_cpu_device(&device) || x.is_tracked() {
        return None;
    }
    let mut values = read_values(x.clone())?;
    gelu_in_place(&mut values);
    Some(Tensor::from_data(
        TensorData::new(values, x.dims()),
        &device,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::Device;

    /// erf in f64 (Abramowitz-Stegun 7.1.26 is too coarse; use a series / continued fraction).
    fn erf64(x: f64) -> f64 {
        // Taylor series converges well for |x| < 3; beyond, 1 - erfc asymptotics are ~1.
        if x.abs() > 5.0 {
            return x.signum();
        }
        let mut sum: f64 = 0.0;
        let mut term = x;
        let mut n = 0.0;
        while term.abs() > 1e-17 * sum.abs().max(1e-300) || n < 5.0 {
            sum += term / (2.0 * n + 1.0);
            n += 1.0;
            term *= -x * x / n;
            if n > 200.0 {
                break;
            }
        }
        sum * 2.0 / std::f64::consts::PI.sqrt()
    }

    #[allow(deprecated)]
    #[test]
    fn forward_and_gradient_are_exact() {
        let device = Device::ndarray().autodiff();
        let xs: Vec<f32> = (-40..=40).map(|i| i as f32 * 0.1).collect();
        let n = xs.len();
        let x = Tensor::<1>::from_data(TensorData::new(xs.clone(), [n]), &device).require_grad();
        let y = gelu(x.clone());
        let grads = y.clone().sum().backward();
        let gx: Vec<f32> = x
            .grad(&grads)
            .expect("grad")
            .into_data()
            .to_vec()
            .expect("f32");
        let yv: Vec<f32> = y.into_data().to_vec().expect("f32");
        for (i, &xi) in xs.iter().enumerate() {
            let x64 = xi as f64;
            let want = 0.5 * x64 * (1.0 + erf64(x64 / 2f64.sqrt()));
            let dwant = 0.5 * (1.0 + erf64(x64 / 2f64.sqrt()))
                + x64 * (-x64 * x64 / 2.0).exp() / (2.0 * std::f64::consts::PI).sqrt();
            assert!(
                (yv[i] as f64 - want).abs() < 2e-6,
                "gelu({xi}) = {} want {want}",
                yv[i]
            );
            assert!(
                (gx[i] as f64 - dwant).abs() < 2e-6,
                "gelu'({xi}) = {} want {dwant}",
                gx[i]
            );
        }
    }
}
