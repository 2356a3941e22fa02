//! Small device helpers shared by the building blocks: index uploads and row blocks.

use burn::tensor::{Device, Int, Tensor, TensorData};

/// Uploads host indices as a rank-1 Int tensor (the device's default int dtype).
pub(crate) fn index_tensor(values: &[usize], device: &Device) -> Tensor<1, Int> {
    let data: Vec<i64> = values.iter().map(|&v| v as i64).collect();
    Tensor::from_data(TensorData::new(data, [values.len()]), device)
}

/// Uploads host f32 values as a tensor of the given shape.
pub(crate) fn float_tensor<const D: usize>(
    values: Vec<f32>,
    shape: [usize; D],
    device: &Device,
) -> Tensor<D> {
    Tensor::from_data(TensorData::new(values, shape), device)
}

/// Upper bound on the floats of one row block of a wide intermediate (MLP hidden layer, head
/// input): 64 MiB of f32. Bounds peak memory on large chunks (400k tokens).
pub const ROW_BLOCK_BUDGET_FLOATS: usize = 16 * 1024 * 1024;

/// Applies a row-wise function `f` to `x [N, C]` in row blocks whose widest intermediate
/// (`width` columns) stays below [`ROW_BLOCK_BUDGET_FLOATS`]; concatenates the results.
/// Exact: `f` must act on every row independently.
pub(crate) fn map_row_blocks(
    x: Tensor<2>,
    width: usize,
    f: impl Fn(Tensor<2>) -> Tensor<2>,
) -> Tensor<2> {
    let [n, _] = x.dims();
    let rows = (ROW_BLOCK_BUDGET_FLOATS / width.max(1)).max(1);
    if n <= rows {
        return f(x);
    }
    let mut parts = Vec::with_capacity(n.div_ceil(rows));
    let mut r0 = 0;
    while r0 < n {
        let len = rows.min(n - r0);
        parts.push(f(x.clone().narrow(0, r0, len)));
        r0 += len;
    }
    Tensor::cat(parts, 0)
}
