//! Submanifold sparse convolution, kernel 3 (network.md §6), spconv CPU duplicate rule.
//!
//! Weight kept in the checkpoint's spconv "KRSC" layout `[C_out, 3, 3, 3, C_in]` (no adapter
//! touches it); tap `f = 9 r0 + 3 r1 + r2` has matrix `W_f = weight[:, r0, r1, r2, :]`.
//! The forward is an im2col GEMM:
//!
//! ```text
//! X_ext  = [x; group sums; 0]                       [N + G + 1, C_in]
//! cols   = X_ext[im2col] reshaped                   [N, 27 C_in]   (row t, block f = source of tap f)
//! out    = cols @ W_mat + bias                      [N, C_out]
//! W_mat  = weight.reshape([C_out, 27 C_in])^T       [27 C_in, C_out]
//! ```
//!
//! processed in row blocks so the im2col buffer stays below [`IM2COL_BUDGET_FLOATS`].

use burn::module::{Module, Param};
use burn::nn::Initializer;
use burn::tensor::{Device, IndexingUpdateOp, Tensor};

use crate::ops::gather_rows;
use crate::prepared::{ConvIndex, NUM_TAPS};

/// Upper bound on the floats of one im2col block (64 MiB of f32).
pub const IM2COL_BUDGET_FLOATS: usize = 16 * 1024 * 1024;

/// spconv `SubMConv3d(C_in, C_out, kernel 3, bias)`.
#[derive(Module, Debug)]
pub struct SubmConv3d {
    /// `[C_out, 3, 3, 3, C_in]` (KRSC).
    pub weight: Param<Tensor<5>>,
    /// `[C_out]`.
    pub bias: Param<Tensor<1>>,
}

impl SubmConv3d {
    /// Initialised `U(±1/sqrt(27 C_in))` (network.md §11.4).
    pub fn new(c_in: usize, c_out: usize, device: &Device) -> Self {
        let bound = 1.0 / ((NUM_TAPS * c_in) as f64).sqrt();
        let init = Initializer::Uniform { min: -bound, max: bound };
        Self { weight: init.init([c_out, 3, 3, 3, c_in], device), bias: init.init([c_out], device) }
    }

    /// `x [N, C_in] -> [N, C_out]` over the level's neighbour tables.
    pub fn forward(&self, x: Tensor<2>, index: &ConvIndex) -> Tensor<2> {
        let [n, c_in] = x.dims();
        let [c_out, _, _, _, _] = self.weight.dims();
        let device = x.device();
        if n == 0 {
            return Tensor::zeros([0, c_out], &device);
        }
        let w_mat = self.weight.val().reshape([c_out, NUM_TAPS * c_in]).transpose();
        let mut parts = vec![x.clone()];
        if let (Some(members), Some(ids)) = (&index.group_members, &index.group_ids) {
            let sums = Tensor::<2>::zeros([index.num_groups, c_in], &device).select_assign(
                0,
                ids.clone(),
                gather_rows(x.clone(), members.clone()),
                IndexingUpdateOp::Add,
            );
            parts.push(sums);
        }
        parts.push(Tensor::zeros([1, c_in], &device));
        let x_ext = Tensor::cat(parts, 0);
        let rows_per_block = (IM2COL_BUDGET_FLOATS / (NUM_TAPS * c_in)).max(1);
        let bias = self.bias.val().reshape([1, c_out]);
        let mut outs = Vec::with_capacity(n.div_ceil(rows_per_block));
        let mut r0 = 0;
        while r0 < n {
            let rows = rows_per_block.min(n - r0);
            let idx = index.im2col.clone().narrow(0, r0 * NUM_TAPS, rows * NUM_TAPS);
            let cols = gather_rows(x_ext.clone(), idx).reshape([rows, NUM_TAPS * c_in]);
            outs.push(cols.matmul(w_mat.clone()) + bias.clone());
            r0 += rows;
        }
        match outs.len() {
            1 => outs.pop().unwrap_or_else(|| Tensor::zeros([0, c_out], &device)),
            _ => Tensor::cat(outs, 0),
        }
    }
}
