//! Row gathers on the CubeCL backends.

use burn::backend::Backend;
use burn::backend::TensorMetadata;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::tensor::IndexingUpdateOp;

/// `grad [M, C]` summed into `[rows, C]` at the rows `idx [M]`, as a `scatter` along axis 0
/// with the index expanded to `[M, C]`: one atomic add per element, parallel over all of them.
#[cfg_attr(not(any(feature = "wgpu", feature = "cuda")), allow(dead_code))]
pub(super) fn scatter_add_rows_atomic<B: Backend>(
    grad: FloatTensor<B>,
    idx: IntTensor<B>,
    rows: usize,
) -> FloatTensor<B> {
    let shape = grad.shape();
    let (m, c) = (shape[0], shape[1]);
    let idx = B::int_expand(B::int_reshape(idx, [m, 1].into()), [m, c].into());
    let zeros = B::float_zeros([rows, c].into(), &grad.device(), grad.dtype().into());
    B::float_scatter(0, zeros, idx, grad, IndexingUpdateOp::Add)
}
