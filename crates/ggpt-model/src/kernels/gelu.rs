//! The exact-erf GELU on the host, over the rayon pool (network.md §5.1): the same f32
//! operations, in the same order, as [`super::composed::gelu`]. Burn 0.22.1's flex and ndarray
//! backends run element-wise ops on one thread; here every pass is split over the pool.

use rayon::prelude::*;

use crate::host_dense::ROWS_PER_TASK;

/// Elements per rayon task of the element-wise passes.
const ELEMENTS_PER_TASK: usize = ROWS_PER_TASK * 256;

/// `1 / sqrt(2 pi)` in f32 ([`super::composed::INV_SQRT_2PI`]).
const INV_SQRT_2PI: f32 = super::composed::INV_SQRT_2PI as f32;

/// `GELU(x) = x · ½ (1 + erf(x / √2))`.
#[inline]
pub fn gelu_value(x: f32) -> f32 {
    x * ((libm::erff(x * std::f32::consts::FRAC_1_SQRT_2) + 1.0) * 0.5)
}

/// `GELU'(x) = ½ (1 + erf(x / √2)) + x φ(x)`.
#[inline]
pub fn gelu_derivative(x: f32) -> f32 {
    let cdf = (libm::erff(x * std::f32::consts::FRAC_1_SQRT_2) + 1.0) * 0.5;
    cdf + x * INV_SQRT_2PI * (-0.5 * x * x).exp()
}

/// [`gelu_value`] in place over the rayon pool.
pub fn gelu_in_place(h: &mut [f32]) {
    h.par_chunks_mut(ELEMENTS_PER_TASK).for_each(|c| {
        for v in c {
            *v = gelu_value(*v);
        }
    });
}

/// `GELU(x)` of every element of `x`.
pub(super) fn gelu_slice(x: &[f32]) -> Vec<f32> {
    let mut y = x.to_vec();
    gelu_in_place(&mut y);
    y
}

/// `grad · GELU'(x)` element-wise (`x`, `grad` of one length).
pub(super) fn gelu_backward_slice(x: &[f32], grad: &[f32]) -> Vec<f32> {
    let mut out = grad.to_vec();
    out.par_chunks_mut(ELEMENTS_PER_TASK)
        .zip(x.par_chunks(ELEMENTS_PER_TASK))
        .for_each(|(g, x)| {
            for (g, &x) in g.iter_mut().zip(x) {
                *g *= gelu_derivative(x);
            }
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gelu_matches_the_tensor_composition() {
        let xs: Vec<f32> = (-60..=60).map(|i| i as f32 * 0.1).collect();
        let mut host = xs.clone();
        gelu_in_place(&mut host);
        for (&x, &y) in xs.iter().zip(&host) {
            let want = 0.5 * x as f64 * (1.0 + libm::erf(x as f64 / 2f64.sqrt()));
            assert!(
                (y as f64 - want).abs() < 1e-6,
                "gelu({x}) = {y}, want {want}"
            );
            let dwant = 0.5 * (1.0 + libm::erf(x as f64 / 2f64.sqrt()))
                + x as f64 * (-(x as f64).powi(2) / 2.0).exp()
                    / (2.0 * std::f64::consts::PI).sqrt();
            assert!(
                (gelu_derivative(x) as f64 - dwant).abs() < 1e-6,
                "gelu'({x})"
            );
        }
    }
}
