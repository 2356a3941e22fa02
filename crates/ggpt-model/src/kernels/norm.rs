//! The LayerNorm backward on the host ([`crate::host_dense`]'s row kernels over the rayon pool).

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;

use super::host::HostFloat;
use crate::host_dense::NormRows;

/// Three tensors: `(x, gamma, grad)` handed back for the composed fallback, or `(dx, dγ, dβ)`.
type Three<B> = (FloatTensor<B>, FloatTensor<B>, FloatTensor<B>);

/// `(dx, dγ, dβ)` of LayerNorm for `x [N, C]`, `gamma [C]`, `grad [N, C]` on the host;
/// `Err(inputs)` when a tensor is not f32 or the shapes do not fit.
pub(super) fn layer_norm_backward_host<B: HostFloat>(
    x: FloatTensor<B>,
    gamma: FloatTensor<B>,
    grad: FloatTensor<B>,
    eps: f64,
) -> Result<Three<B>, Three<B>> {
    let (xs, gs) = (x.shape(), gamma.shape());
    if xs.num_dims() != 2 || gs.num_dims() != 1 || gs[0] != xs[1] || grad.shape() != xs {
        return Err((x, gamma, grad));
    }
    let c = xs[1];
    let out = B::with_f32(&x, |xv| {
        B::with_f32(&gamma, |gv| {
            B::with_f32(&grad, |dv| {
                let state = NormRows::of(xv, c, eps as f32);
                let (mut d_gamma, mut d_beta) = (vec![0.0f32; c], vec![0.0f32; c]);
                let dx = state.backward(dv, gv, None, &mut d_gamma, &mut d_beta);
                (dx, d_gamma, d_beta)
            })
        })
    })
    .flatten()
    .flatten();
    match out {
        Some((dx, d_gamma, d_beta)) => {
            let dx = B::from_f32(dx, xs, &x);
            let d_gamma = B::from_f32(d_gamma, gs.clone(), &x);
            let d_beta = B::from_f32(d_beta, gs, &x);
            Ok((dx, d_gamma, d_beta))
        }
        None => Err((x, gamma, grad)),
    }
}
