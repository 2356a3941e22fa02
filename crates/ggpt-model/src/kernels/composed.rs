//! The default bodies of [`super::GgptKernels`]: each op composed of Burn primitives, the
//! definition its host kernels and its `Backward` are tested against, and what a backend
//! without a kernel of its own runs.

use burn::backend::Backend;
use burn::backend::TensorMetadata;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::tensor::{IndexingUpdateOp, Slice};

/// `1 / sqrt(2 pi)`, the standard normal density at 0 (GELU', network.md §5.1).
pub const INV_SQRT_2PI: f64 = 0.398_942_280_401_432_7;

/// `½ (1 + erf(x / √2))`, the standard normal CDF.
fn normal_cdf<B: Backend>(x: FloatTensor<B>) -> FloatTensor<B> {
    let erf = B::float_erf(B::float_mul_scalar(
        x,
        std::f64::consts::FRAC_1_SQRT_2.into(),
    ));
    B::float_mul_scalar(B::float_add_scalar(erf, 1.0.into()), 0.5.into())
}

/// `GELU(x) = x · ½ (1 + erf(x / √2))`, any shape. Under autodiff its gradient is the exact
/// `½ (1 + erf(x/√2)) + x φ(x)` (Burn 0.22.1's built-in GELU back-propagates the tanh
/// approximation's derivative on ndarray and wgpu).
pub fn gelu<B: Backend>(x: FloatTensor<B>) -> FloatTensor<B> {
    let cdf = normal_cdf::<B>(x.clone());
    B::float_mul(x, cdf)
}

/// `grad · GELU'(x)`, `GELU'(x) = ½ (1 + erf(x / √2)) + x φ(x)`, `φ(x) = exp(-x²/2) / √(2π)`.
pub fn gelu_backward<B: Backend>(x: FloatTensor<B>, grad: FloatTensor<B>) -> FloatTensor<B> {
    let cdf = normal_cdf::<B>(x.clone());
    let x2 = B::float_mul(x.clone(), x.clone());
    let pdf = B::float_mul_scalar(
        B::float_exp(B::float_mul_scalar(x2, (-0.5).into())),
        INV_SQRT_2PI.into(),
    );
    B::float_mul(grad, B::float_add(cdf, B::float_mul(x, pdf)))
}

/// `grad [M, C]` summed into `[rows, C]` at the rows `idx [M]` (`select_assign` with addition:
/// the backward of `select` in burn-autodiff).
pub fn scatter_add_rows<B: Backend>(
    grad: FloatTensor<B>,
    idx: IntTensor<B>,
    rows: usize,
) -> FloatTensor<B> {
    let shape = grad.shape();
    let zeros = B::float_zeros([rows, shape[1]].into(), &grad.device(), grad.dtype().into());
    B::float_select_assign(zeros, 0, idx, grad, IndexingUpdateOp::Add)
}

/// LayerNorm of `x [N, C]` over the last axis (biased variance): Burn's backend `layer_norm`
/// (flex: one fused multi-threaded pass; elsewhere its composition).
pub fn layer_norm<B: Backend>(
    x: FloatTensor<B>,
    gamma: FloatTensor<B>,
    beta: FloatTensor<B>,
    eps: f64,
) -> FloatTensor<B> {
    B::layer_norm(x, gamma, Some(beta), eps)
}

/// The backward of [`layer_norm`] for `x [N, C]`, `gamma [C]`, `grad [N, C]` (gradient of the
/// output): `(dx [N, C], dγ [C], dβ [C])` with `xhat = (x - mean) rstd`,
/// `dx = rstd (g γ - mean(g γ) - xhat mean(g γ ⊙ xhat))`, `dγ = Σ g ⊙ xhat`, `dβ = Σ g`.
pub fn layer_norm_backward<B: Backend>(
    x: FloatTensor<B>,
    gamma: FloatTensor<B>,
    grad: FloatTensor<B>,
    eps: f64,
) -> (FloatTensor<B>, FloatTensor<B>, FloatTensor<B>) {
    let shape = x.shape();
    let c = shape[1];
    let mean = B::float_mean_dim(x.clone(), 1);
    let centered = B::float_sub(x, mean);
    let var = B::float_mean_dim(B::float_mul(centered.clone(), centered.clone()), 1);
    let rstd = B::float_recip(B::float_sqrt(B::float_add_scalar(var, eps.into())));
    let xhat = B::float_mul(centered, rstd.clone());
    let gamma_row = B::float_reshape(gamma, [1, c].into());
    let g_gamma = B::float_mul(grad.clone(), gamma_row);
    let mean_g = B::float_mean_dim(g_gamma.clone(), 1);
    let mean_gx = B::float_mean_dim(B::float_mul(g_gamma.clone(), xhat.clone()), 1);
    let dx = B::float_mul(
        rstd,
        B::float_sub(
            B::float_sub(g_gamma, mean_g),
            B::float_mul(xhat.clone(), mean_gx),
        ),
    );
    let d_gamma = B::float_reshape(
        B::float_sum_dim(B::float_mul(grad.clone(), xhat), 0),
        [c].into(),
    );
    let d_beta = B::float_reshape(B::float_sum_dim(grad, 0), [c].into());
    (dx, d_gamma, d_beta)
}

/// Rows `start..start + len` of `t` along axis 0 (any rank).
pub fn narrow_rows<B: Backend>(t: FloatTensor<B>, start: usize, len: usize) -> FloatTensor<B> {
    let shape = t.shape();
    let slices: Vec<Slice> = (0..shape.num_dims())
        .map(|i| {
            let (a, b) = if i == 0 {
                (start, start + len)
            } else {
                (0, shape[i])
            };
            Slice::new(a as isize, Some(b as isize), 1)
        })
        .collect();
    B::float_slice(t, &slices)
}
