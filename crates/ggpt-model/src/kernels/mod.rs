//! The kernel layer: GGPT's own operations as a Burn backend extension (`docs/architecture.md`,
//! "Kernel layer").
//!
//! ```text
//! network modules (block, pooling, linear_bn, attention, ...)
//!        │  call the tensor-level wrappers below (gelu, gather_rows, ...)
//!        ▼
//! GgptKernels (#[backend_extension]): routed by the tensor's backend TYPE
//!   ├─ Flex, NdArray   host kernels over the rayon pool (zero-copy input on flex)
//!   ├─ Cube (wgpu/CUDA) the trait's default bodies, composed of Burn primitives
//!   └─ Autodiff<B, C>  one `Backward` per op; its backward calls B's backward op
//!        ▼
//! readback (host vectors), ground (burn)
//! ```
//!
//! Every op has a default body composed of differentiable Burn primitives: it is the
//! definition the host kernels and the `Backward`s are tested against (each op's tests check
//! "the op's `Backward` equals autodiff of the composed default body"), and it is what a
//! backend without a kernel of its own runs. A new backend gets GGPT by an empty
//! `impl GgptKernels for NewBackend {}` plus its selector in the attribute; a new op is a
//! method with a default body, host kernels where they pay, and a `Backward` in
//! [`autodiff`].

// burn-ndarray is deprecated in Burn 0.22.1; it stays the second CPU backend (device.rs), and
// the extension macro names it in generated code that an item attribute does not reach.
#![allow(deprecated)]

pub mod attention;
mod autodiff;
pub mod composed;
pub mod conv;
mod gelu;
mod host;
mod norm;
mod rows;

use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{Backend, Dispatch, backend_extension};
use burn::tensor::{Int, Tensor};

use crate::conv_layout::ConvLayout;
use crate::host_attention::WindowShape;
use crate::prepared::ConvIndex;

pub use attention::SCORE_BUDGET_FLOATS;
pub use gelu::{gelu_derivative, gelu_in_place, gelu_value};

/// GGPT's operations, one implementation per backend type (module docs).
#[backend_extension(
    Flex: cfg(feature = "flex"),
    NdArray: cfg(feature = "ndarray"),
    Cube: cfg(any(feature = "wgpu", feature = "cuda")),
    Autodiff
)]
pub trait GgptKernels: Backend {
    /// Exact (erf) GELU, element-wise, any shape (network.md §5.1, §11.1):
    /// `GELU(x) = x · ½ (1 + erf(x / √2))`.
    fn gelu_exact(x: FloatTensor<Self>) -> FloatTensor<Self> {
        composed::gelu::<Self>(x)
    }

    /// The gradient of [`GgptKernels::gelu_exact`] at `x` times the upstream gradient `grad` (same
    /// shape): `grad · (½ (1 + erf(x / √2)) + x φ(x))`, `φ(x) = exp(-x²/2) / √(2π)`.
    fn gelu_exact_backward(x: FloatTensor<Self>, grad: FloatTensor<Self>) -> FloatTensor<Self> {
        composed::gelu_backward::<Self>(x, grad)
    }

    /// LayerNorm of `x [N, C]` over its last axis with the affine `gamma [C]`, `beta [C]`
    /// (biased variance, epsilon `eps`; network.md §11): `[N, C]`.
    fn layer_norm_rows(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        eps: f64,
    ) -> FloatTensor<Self> {
        composed::layer_norm::<Self>(x, gamma, beta, eps)
    }

    /// The backward of [`GgptKernels::layer_norm_rows`]: `x [N, C]`, `gamma [C]` and the
    /// output gradient `grad [N, C]` -> `(dx [N, C], dγ [C], dβ [C])`.
    fn layer_norm_rows_backward(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        eps: f64,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        composed::layer_norm_backward::<Self>(x, gamma, grad, eps)
    }

    /// The window-attention core (network.md §7, [`attention`]): `rows [W L, 3C]` (the `qkv`
    /// projection of the gathered tokens of `shape.windows` windows) `-> [W L, C]`, every row
    /// `softmax((q s) kᵀ) v` over its own window, `s = d^-1/2`. `rows` must have
    /// `shape.windows · shape.len` rows and `3 shape.channels()` columns.
    fn window_attention(rows: FloatTensor<Self>, shape: WindowShape) -> FloatTensor<Self> {
        attention::window_attention::<Self>(rows, shape, SCORE_BUDGET_FLOATS)
    }

    /// The backward of [`GgptKernels::window_attention`]: `rows [W L, 3C]` and the output
    /// gradient `grad [W L, C]` -> `d rows [W L, 3C]`.
    fn window_attention_backward(
        rows: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        shape: WindowShape,
    ) -> FloatTensor<Self> {
        attention::window_attention_backward::<Self>(rows, grad, shape, SCORE_BUDGET_FLOATS)
    }

    /// The submanifold sparse convolution, kernel 3 (network.md §6, [`conv`]): `x [N, C_in]`,
    /// `weight [C_out, 3, 3, 3, C_in]` (spconv KRSC), `bias [C_out]`, the packed index `tables`
    /// read by `layout` ([`crate::conv_layout`]) -> `[N, C_out]`. The default is the im2col
    /// GEMM.
    fn subm_conv(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        tables: IntTensor<Self>,
        layout: ConvLayout,
    ) -> FloatTensor<Self> {
        conv::subm_conv_im2col::<Self>(x, weight, bias, &tables, &layout)
    }

    /// The backward of [`GgptKernels::subm_conv`]: `x`, `weight` and the output gradient
    /// `grad [N, C_out]` -> `(d x [N, C_in], d weight [C_out, 3, 3, 3, C_in], d bias [C_out])`.
    fn subm_conv_backward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        tables: IntTensor<Self>,
        layout: ConvLayout,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        conv::subm_conv_backward_composed::<Self>(x, weight, grad, &tables, &layout)
    }

    /// Whether this backend's kernels run on the host (the CPU backends): `true` selects the
    /// host part backwards of [`crate::recompute`] for a segment whose tensors live here.
    /// `probe` is any tensor of the backend (only its type is looked at).
    fn runs_on_host(probe: FloatTensor<Self>) -> bool {
        let _ = probe;
        false
    }

    /// Rows of `x [N, C]` picked by `idx [M]` (values in `0..N`): `[M, C]`.
    fn gather_rows(x: FloatTensor<Self>, idx: IntTensor<Self>) -> FloatTensor<Self> {
        Self::float_select(x, 0, idx)
    }

    /// The adjoint of [`GgptKernels::gather_rows`]: `grad [M, C]` summed into `rows` rows, row
    /// `idx[m]` receiving `grad[m]`: `[rows, C]`. The default is `select_assign` with addition.
    fn scatter_add_rows(
        grad: FloatTensor<Self>,
        idx: IntTensor<Self>,
        rows: usize,
    ) -> FloatTensor<Self> {
        composed::scatter_add_rows::<Self>(grad, idx, rows)
    }
}

/// The CPU backends' implementation: the host kernels (`host.rs` bridges their f32 storage),
/// each falling back to its composed body for another dtype. One body for both backends.
macro_rules! host_kernels {
    ($backend:ty) => {
        impl GgptKernels for $backend {
            fn runs_on_host(_probe: FloatTensor<Self>) -> bool {
                true
            }

            fn gelu_exact(x: FloatTensor<Self>) -> FloatTensor<Self> {
                host::map::<Self>(x, gelu::gelu_slice).unwrap_or_else(composed::gelu::<Self>)
            }

            fn gelu_exact_backward(
                x: FloatTensor<Self>,
                grad: FloatTensor<Self>,
            ) -> FloatTensor<Self> {
                host::zip::<Self>(x, grad, gelu::gelu_backward_slice)
                    .unwrap_or_else(|(x, g)| composed::gelu_backward::<Self>(x, g))
            }

            fn layer_norm_rows_backward(
                x: FloatTensor<Self>,
                gamma: FloatTensor<Self>,
                grad: FloatTensor<Self>,
                eps: f64,
            ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
                norm::layer_norm_backward_host::<Self>(x, gamma, grad, eps)
                    .unwrap_or_else(|(x, g, d)| composed::layer_norm_backward::<Self>(x, g, d, eps))
            }

            /// Tap-wise for sparse neighbourhoods ([`conv::tapwise`]), else im2col.
            fn subm_conv(
                x: FloatTensor<Self>,
                weight: FloatTensor<Self>,
                bias: FloatTensor<Self>,
                tables: IntTensor<Self>,
                layout: ConvLayout,
            ) -> FloatTensor<Self> {
                if conv::tapwise(&layout) {
                    conv::subm_conv_tapwise::<Self>(x, weight, bias, &tables, &layout)
                } else {
                    conv::subm_conv_im2col::<Self>(x, weight, bias, &tables, &layout)
                }
            }

            fn subm_conv_backward(
                x: FloatTensor<Self>,
                weight: FloatTensor<Self>,
                grad: FloatTensor<Self>,
                tables: IntTensor<Self>,
                layout: ConvLayout,
            ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
                conv::subm_conv_backward_host::<Self>(x, weight, grad, &tables, &layout)
                    .unwrap_or_else(|(x, w, g)| {
                        conv::subm_conv_backward_composed::<Self>(x, w, g, &tables, &layout)
                    })
            }

            fn window_attention(rows: FloatTensor<Self>, shape: WindowShape) -> FloatTensor<Self> {
                attention::window_attention_host::<Self>(rows, shape).unwrap_or_else(|rows| {
                    attention::window_attention::<Self>(rows, shape, SCORE_BUDGET_FLOATS)
                })
            }

            fn window_attention_backward(
                rows: FloatTensor<Self>,
                grad: FloatTensor<Self>,
                shape: WindowShape,
            ) -> FloatTensor<Self> {
                attention::window_attention_backward_host::<Self>(rows, grad, shape).unwrap_or_else(
                    |(rows, grad)| {
                        attention::window_attention_backward::<Self>(
                            rows,
                            grad,
                            shape,
                            SCORE_BUDGET_FLOATS,
                        )
                    },
                )
            }
        }
    };
}

#[cfg(feature = "flex")]
host_kernels!(burn::backend::Flex);
#[cfg(feature = "ndarray")]
host_kernels!(burn::backend::NdArray);

/// The CubeCL runtimes (wgpu, CUDA): the composed bodies, except the row scatter.
#[cfg(any(feature = "wgpu", feature = "cuda"))]
impl GgptKernels for burn::backend::Cube {
    /// Burn's fused attention where its autotune can pick the flash kernel
    /// ([`attention::FLASH_REACHABLE`]); otherwise the composed body.
    fn window_attention(rows: FloatTensor<Self>, shape: WindowShape) -> FloatTensor<Self> {
        if attention::FLASH_REACHABLE {
            attention::window_attention_fused::<Self>(rows, shape)
        } else {
            attention::window_attention::<Self>(rows, shape, SCORE_BUDGET_FLOATS)
        }
    }

    /// A `scatter` with an expanded index (an atomic add per element): Burn 0.22.1's CubeCL
    /// `select_assign` loops serially per column (burn-notes.md).
    fn scatter_add_rows(
        grad: FloatTensor<Self>,
        idx: IntTensor<Self>,
        rows: usize,
    ) -> FloatTensor<Self> {
        rows::scatter_add_rows_atomic::<Self>(grad, idx, rows)
    }
}

/// Exact GELU of `x`, any shape, on any backend ([`GgptKernels::gelu_exact`]).
pub fn gelu<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    Tensor::from_dispatch(<Dispatch as GgptKernels>::gelu_exact(x.into_dispatch()))
}

/// LayerNorm of `x [N, C]` with the affine `gamma [C]`, `beta [C]` (`None`: zero), epsilon
/// `eps`, on any backend ([`GgptKernels::layer_norm_rows`]; its backward is
/// [`GgptKernels::layer_norm_rows_backward`]).
pub fn layer_norm(x: Tensor<2>, gamma: Tensor<1>, beta: Option<Tensor<1>>, eps: f64) -> Tensor<2> {
    let beta = beta.unwrap_or_else(|| gamma.zeros_like());
    Tensor::from_dispatch(<Dispatch as GgptKernels>::layer_norm_rows(
        x.into_dispatch(),
        gamma.into_dispatch(),
        beta.into_dispatch(),
        eps,
    ))
}

/// The window-attention core of `rows [W L, 3C]` -> `[W L, C]` on any backend
/// ([`GgptKernels::window_attention`]; its backward is
/// [`GgptKernels::window_attention_backward`]). `rows` must be `[shape.windows · shape.len,
/// 3 shape.channels()]` (built by the attention layer from its own sizes).
pub fn window_attention(rows: Tensor<2>, shape: WindowShape) -> Tensor<2> {
    debug_assert_eq!(
        rows.dims(),
        [shape.windows * shape.len, 3 * shape.channels()],
        "window attention rows"
    );
    Tensor::from_dispatch(<Dispatch as GgptKernels>::window_attention(
        rows.into_dispatch(),
        shape,
    ))
}

/// The submanifold conv of `x [N, C_in]` with `weight [C_out, 3, 3, 3, C_in]`, `bias [C_out]`
/// over the neighbour tables of `index`, on any backend ([`GgptKernels::subm_conv`]; its
/// backward is [`GgptKernels::subm_conv_backward`]): `[N, C_out]`.
pub fn subm_conv(x: Tensor<2>, weight: Tensor<5>, bias: Tensor<1>, index: &ConvIndex) -> Tensor<2> {
    Tensor::from_dispatch(<Dispatch as GgptKernels>::subm_conv(
        x.into_dispatch(),
        weight.into_dispatch(),
        bias.into_dispatch(),
        index.tables.clone().into_dispatch(),
        index.layout.clone(),
    ))
}

/// Whether `probe`'s backend runs the kernels on the host ([`GgptKernels::runs_on_host`]):
/// routed by the tensor's backend type, with or without autodiff.
pub fn runs_on_host<const D: usize>(probe: &Tensor<D>) -> bool {
    <Dispatch as GgptKernels>::runs_on_host(probe.clone().into_dispatch())
}

/// `x[idx]` along rows: `x [N, C]`, `idx [M]` -> `[M, C]` ([`GgptKernels::gather_rows`]; its
/// backward is [`GgptKernels::scatter_add_rows`]).
pub fn gather_rows(x: Tensor<2>, idx: Tensor<1, Int>) -> Tensor<2> {
    Tensor::from_dispatch(<Dispatch as GgptKernels>::gather_rows(
        x.into_dispatch(),
        idx.into_dispatch(),
    ))
}

#[cfg(test)]
mod tests;
