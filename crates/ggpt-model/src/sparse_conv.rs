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

use crate::kernels::gather_rows;
use crate::ops::is_cpu_device;
use crate::prepared::{ConvIndex, NUM_TAPS, TapIndex};

/// Upper bound on the floats of one im2col block (64 MiB of f32).
pub const IM2COL_BUDGET_FLOATS: usize = 16 * 1024 * 1024;

/// Above this occupancy (occupied slots / `27 N`) the dense im2col GEMM is used on CPU too:
/// nearly full neighbourhoods gain nothing from 27 separate products and scatters.
pub const TAPWISE_MAX_OCCUPANCY: f64 = 0.75;

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
        let init = Initializer::Uniform {
            min: -bound,
            max: bound,
        };
        Self {
            weight: init.init([c_out, 3, 3, 3, c_in], device),
            bias: init.init([c_out], device),
        }
    }

    /// `x [N, C_in] -> [N, C_out]` over the level's neighbour tables.
    ///
    /// CPU devices with sparse neighbourhoods ([`ConvIndex::occupancy`] below
    /// [`TAPWISE_MAX_OCCUPANCY`]) use the tap-wise form (only occupied slots are multiplied);
    /// other devices the im2col GEMM. Both compute the same sums (up to f32 rounding order).
    pub fn forward(&self, x: Tensor<2>, index: &ConvIndex) -> Tensor<2> {
        let [n, _] = x.dims();
        let [c_out, _, _, _, _] = self.weight.dims();
        let device = x.device();
        if n == 0 {
            return Tensor::zeros([0, c_out], &device);
        }
        if is_cpu_device(&device)
            && index.occupancy < TAPWISE_MAX_OCCUPANCY
            && !index.taps.is_empty()
        {
            self.forward_tapwise(x, index)
        } else {
            self.forward_im2col(x, index)
        }
    }

    /// `X_ext = [x; group sums; 0]` (network.md §6 duplicate rule).
    fn extended_input(x: Tensor<2>, index: &ConvIndex) -> Tensor<2> {
        let [_, c_in] = x.dims();
        let device = x.device();
        let mut parts = vec![x.clone()];
        if let (Some(members), Some(ids)) = (&index.group_members, &index.group_ids) {
            let sums = Tensor::<2>::zeros([index.num_groups, c_in], &device).select_assign(
                0,
                ids.clone(),
                gather_rows(x, members.clone()),
                IndexingUpdateOp::Add,
            );
            parts.push(sums);
        }
        parts.push(Tensor::zeros([1, c_in], &device));
        Tensor::cat(parts, 0)
    }

    /// The im2col GEMM of the module docs.
    pub fn forward_im2col(&self, x: Tensor<2>, index: &ConvIndex) -> Tensor<2> {
        let [n, c_in] = x.dims();
        let [c_out, _, _, _, _] = self.weight.dims();
        let device = x.device();
        let w_mat = self
            .weight
            .val()
            .reshape([c_out, NUM_TAPS * c_in])
            .transpose();
        let x_ext = Self::extended_input(x, index);
        let rows_per_block = (IM2COL_BUDGET_FLOATS / (NUM_TAPS * c_in)).max(1);
        let bias = self.bias.val().reshape([1, c_out]);
        let mut outs = Vec::with_capacity(n.div_ceil(rows_per_block));
        let mut r0 = 0;
        while r0 < n {
            let rows = rows_per_block.min(n - r0);
            let idx = index
                .im2col
                .clone()
                .narrow(0, r0 * NUM_TAPS, rows * NUM_TAPS);
            let cols = gather_rows(x_ext.clone(), idx).reshape([rows, NUM_TAPS * c_in]);
            outs.push(cols.matmul(w_mat.clone()) + bias.clone());
            r0 += rows;
        }
        match outs.len() {
            1 => outs
                .pop()
                .unwrap_or_else(|| Tensor::zeros([0, c_out], &device)),
            _ => Tensor::cat(outs, 0),
        }
    }

    /// Tap-wise form: `out = bias + sum_f scatter_add(target_f, X_ext[source_f] W_f)`, only
    /// over the occupied `(target, tap)` slots; gathers in row blocks of at most
    /// [`IM2COL_BUDGET_FLOATS`] floats.
    pub fn forward_tapwise(&self, x: Tensor<2>, index: &ConvIndex) -> Tensor<2> {
        let [n, c_in] = x.dims();
        let [c_out, _, _, _, _] = self.weight.dims();
        // [27 C_in, C_out]: rows f C_in .. (f + 1) C_in are W_f^T.
        let w_mat = self
            .weight
            .val()
            .reshape([c_out, NUM_TAPS * c_in])
            .transpose();
        let x_ext = if index.num_groups > 0 {
            Self::extended_input(x.clone(), index)
        } else {
            x.clone()
        };
        let rows_per_block = (IM2COL_BUDGET_FLOATS / c_in.max(c_out)).max(1);
        // A dense, uniquely owned [N, C_out] (scatter-adds then update it in place on flex).
        let mut out =
            Tensor::<2>::zeros([n, c_out], &x.device()) + self.bias.val().reshape([1, c_out]);
        // Full taps first: plain adds build the output before any scatter.
        let mut order: Vec<&TapIndex> = index.taps.iter().collect();
        order.sort_by_key(|t| !t.full);
        for tap in order {
            let w_f = w_mat.clone().narrow(0, tap.tap * c_in, c_in);
            if tap.identity {
                out = out + x.clone().matmul(w_f);
                continue;
            }
            let mut r0 = 0;
            while r0 < tap.len {
                let rows = rows_per_block.min(tap.len - r0);
                let src = tap.source.clone().narrow(0, r0, rows);
                let y = gather_rows(x_ext.clone(), src).matmul(w_f.clone());
                out = if tap.full && rows == tap.len {
                    out + y
                } else {
                    out.select_assign(
                        0,
                        tap.target.clone().narrow(0, r0, rows),
                        y,
                        IndexingUpdateOp::Add,
                    )
                };
                r0 += rows;
            }
        }
        out
    }
}
