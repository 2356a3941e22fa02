//! The submanifold sparse convolution, kernel 3 (network.md §6, spconv CPU duplicate rule), as
//! an op of the kernel layer: its composed bodies (the im2col GEMM and its gradient; the
//! tap-wise form of the CPU backends) and the bridge to the host backward of
//! [`crate::host_conv_grad`]. The index tables arrive packed in one list read by a
//! [`ConvLayout`] ([`crate::conv_layout`]).
//!
//! ```text
//! X_ext  = [x; group sums; 0]                       [N + G + 1, C_in]
//! im2col: cols = X_ext[im2col] reshaped             [N, 27 C_in]   (row t, block f = source of tap f)
//!         out  = cols @ W_mat + bias                [N, C_out]
//! W_mat  = weight.reshape([C_out, 27 C_in])ᵀ        [27 C_in, C_out]
//! tap-wise (CPU, sparse neighbourhoods): out = bias + Σ_f scatter_add(target_f, X_ext[source_f] W_f)
//! backward of the im2col form, g = d out [N, C_out]:
//!   d bias = Σ_rows g,  d W_mat = Σ_blocks colsᵀ g,  d X_ext = scatter_add(im2col, g W_matᵀ)
//!   d x    = d X_ext[0..N] + d X_ext[N + group] at each group member
//! ```
//!
//! Gathers are processed in row blocks so that no gathered buffer exceeds
//! [`IM2COL_BUDGET_FLOATS`].

use burn::backend::Backend;
use burn::backend::TensorMetadata;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::tensor::{IndexingUpdateOp, Shape, Slice};

use super::GgptKernels;
use super::composed::narrow_rows;
use super::host::HostFloat;
use crate::conv_layout::{ConvLayout, NUM_TAPS, Span};
use crate::host_conv_grad::{HostConvTables, subm_conv_backward};
use crate::readback::read_indices_primitive;

/// Upper bound on the floats of one gathered block (64 MiB of f32).
pub const IM2COL_BUDGET_FLOATS: usize = 16 * 1024 * 1024;

/// Above this occupancy (occupied slots / `27 N`) the CPU backends use the im2col GEMM too:
/// nearly full neighbourhoods gain nothing from 27 separate products and scatters.
pub const TAPWISE_MAX_OCCUPANCY: f64 = 0.75;

/// Whether a CPU backend takes the tap-wise form for `layout`.
pub fn tapwise(layout: &ConvLayout) -> bool {
    layout.occupancy < TAPWISE_MAX_OCCUPANCY && !layout.taps.is_empty()
}

/// The table at `span` of the packed list.
fn table<B: Backend>(tables: &IntTensor<B>, (start, len): Span) -> IntTensor<B> {
    B::int_slice(
        tables.clone(),
        &[Slice::new(start as isize, Some((start + len) as isize), 1)],
    )
}

/// `W_mat [27 C_in, C_out]` of `weight [C_out, 3, 3, 3, C_in]`.
fn weight_matrix<B: Backend>(weight: FloatTensor<B>) -> FloatTensor<B> {
    let shape = weight.shape();
    let (c_out, c_in) = (shape[0], shape[4]);
    B::float_transpose(B::float_reshape(weight, [c_out, NUM_TAPS * c_in].into()))
}

/// `X_ext = [x; group sums; 0]` `[N + G + 1, C_in]` (network.md §6 duplicate rule).
fn extended_input<B: GgptKernels>(
    x: FloatTensor<B>,
    tables: &IntTensor<B>,
    layout: &ConvLayout,
) -> FloatTensor<B> {
    let c_in = x.shape()[1];
    let (device, dtype) = (x.device(), x.dtype());
    let mut parts = vec![x.clone()];
    if let Some((members, ids)) = layout.groups() {
        let picked = B::gather_rows(x, table::<B>(tables, members));
        let sums = B::scatter_add_rows(picked, table::<B>(tables, ids), layout.num_groups);
        parts.push(sums);
    }
    parts.push(B::float_zeros([1, c_in].into(), &device, dtype.into()));
    B::float_cat(parts, 0)
}

/// Rows per gathered block of `width` floats.
fn rows_per_block(width: usize) -> usize {
    (IM2COL_BUDGET_FLOATS / width.max(1)).max(1)
}

/// The im2col forward (module docs): `x [N, C_in]`, `weight [C_out, 3, 3, 3, C_in]`,
/// `bias [C_out]` -> `[N, C_out]`.
pub fn subm_conv_im2col<B: GgptKernels>(
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    bias: FloatTensor<B>,
    tables: &IntTensor<B>,
    layout: &ConvLayout,
) -> FloatTensor<B> {
    let [n, c_in] = [x.shape()[0], x.shape()[1]];
    let c_out = weight.shape()[0];
    if n == 0 {
        return B::float_zeros([n, c_out].into(), &x.device(), x.dtype().into());
    }
    let w_mat = weight_matrix::<B>(weight);
    let bias = B::float_reshape(bias, [1, c_out].into());
    let im2col = table::<B>(tables, layout.im2col());
    let x_ext = extended_input::<B>(x, tables, layout);
    let block = rows_per_block(NUM_TAPS * c_in);
    let mut outs = Vec::with_capacity(n.div_ceil(block));
    let mut r0 = 0;
    while r0 < n {
        let m = block.min(n - r0);
        let idx = table::<B>(&im2col, (r0 * NUM_TAPS, m * NUM_TAPS));
        let cols = B::float_reshape(
            B::gather_rows(x_ext.clone(), idx),
            [m, NUM_TAPS * c_in].into(),
        );
        outs.push(B::float_add(
            B::float_matmul(cols, w_mat.clone()),
            bias.clone(),
        ));
        r0 += m;
    }
    if outs.len() == 1
        && let Some(out) = outs.pop()
    {
        return out;
    }
    B::float_cat(outs, 0)
}

/// The tap-wise forward (module docs; the CPU backends' form for sparse neighbourhoods): only
/// the occupied `(target, tap)` slots are multiplied.
pub fn subm_conv_tapwise<B: GgptKernels>(
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    bias: FloatTensor<B>,
    tables: &IntTensor<B>,
    layout: &ConvLayout,
) -> FloatTensor<B> {
    let [n, c_in] = [x.shape()[0], x.shape()[1]];
    let c_out = weight.shape()[0];
    let w_mat = weight_matrix::<B>(weight);
    let x_ext = if layout.num_groups > 0 {
        extended_input::<B>(x.clone(), tables, layout)
    } else {
        x.clone()
    };
    let block = rows_per_block(c_in.max(c_out));
    // a dense, uniquely owned [N, C_out] (the scatter-adds then update it in place on flex)
    let zeros = B::float_zeros([n, c_out].into(), &x.device(), x.dtype().into());
    let mut out = B::float_add(zeros, B::float_reshape(bias, [1, c_out].into()));
    // full taps first: plain adds build the output before any scatter
    let mut order: Vec<_> = layout.taps.iter().zip(layout.tap_spans()).collect();
    order.sort_by_key(|(t, _)| !t.full);
    for (tap, (source, target)) in order {
        let (source, target) = (table::<B>(tables, source), table::<B>(tables, target));
        let w_f = narrow_rows::<B>(w_mat.clone(), tap.tap * c_in, c_in);
        if tap.identity {
            out = B::float_add(out, B::float_matmul(x.clone(), w_f));
            continue;
        }
        let len = tap.len;
        let mut r0 = 0;
        while r0 < len {
            let m = block.min(len - r0);
            let src = table::<B>(&source, (r0, m));
            let y = B::float_matmul(B::gather_rows(x_ext.clone(), src), w_f.clone());
            out = if tap.full && m == len {
                B::float_add(out, y)
            } else {
                let tgt = table::<B>(&target, (r0, m));
                B::float_select_assign(out, 0, tgt, y, IndexingUpdateOp::Add)
            };
            r0 += m;
        }
    }
    out
}

/// The composed backward (the gradient of the im2col form, module docs): `x [N, C_in]`,
/// `weight`, `grad [N, C_out]` -> `(d x [N, C_in], d weight [C_out, 3, 3, 3, C_in],
/// d bias [C_out])`.
pub fn subm_conv_backward_composed<B: GgptKernels>(
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    grad: FloatTensor<B>,
    tables: &IntTensor<B>,
    layout: &ConvLayout,
) -> (FloatTensor<B>, FloatTensor<B>, FloatTensor<B>) {
    let [n, c_in] = [x.shape()[0], x.shape()[1]];
    let w_shape = weight.shape();
    let c_out = w_shape[0];
    let (device, dtype) = (x.device(), x.dtype());
    let d_bias = B::float_reshape(B::float_sum_dim(grad.clone(), 0), [c_out].into());
    let w_mat = weight_matrix::<B>(weight);
    let im2col = table::<B>(tables, layout.im2col());
    let rows_ext = n + layout.num_groups + 1;
    let x_ext = extended_input::<B>(x, tables, layout);
    let w_mat_t = B::float_transpose(w_mat);
    let block = rows_per_block(NUM_TAPS * c_in);
    let mut d_w_mat: Option<FloatTensor<B>> = None;
    let mut d_ext: Option<FloatTensor<B>> = None;
    let mut r0 = 0;
    while r0 < n {
        let m = block.min(n - r0);
        let idx = table::<B>(&im2col, (r0 * NUM_TAPS, m * NUM_TAPS));
        let cols = B::float_reshape(
            B::gather_rows(x_ext.clone(), idx.clone()),
            [m, NUM_TAPS * c_in].into(),
        );
        let g = narrow_rows::<B>(grad.clone(), r0, m);
        let dw = B::float_matmul(B::float_transpose(cols), g.clone());
        d_w_mat = Some(match d_w_mat {
            Some(a) => B::float_add(a, dw),
            None => dw,
        });
        let d_cols = B::float_reshape(
            B::float_matmul(g, w_mat_t.clone()),
            [m * NUM_TAPS, c_in].into(),
        );
        let d = B::scatter_add_rows(d_cols, idx, rows_ext);
        d_ext = Some(match d_ext {
            Some(a) => B::float_add(a, d),
            None => d,
        });
        r0 += m;
    }
    let d_weight = match d_w_mat {
        // [27 C_in, C_out] -> [C_out, 27 C_in] -> the weight's shape
        Some(d) => B::float_reshape(B::float_transpose(d), w_shape),
        None => B::float_zeros(w_shape, &device, dtype.into()),
    };
    let Some(d_ext) = d_ext else {
        return (
            B::float_zeros([n, c_in].into(), &device, dtype.into()),
            d_weight,
            d_bias,
        );
    };
    let mut dx = narrow_rows::<B>(d_ext.clone(), 0, n);
    if let Some((members, ids)) = layout.groups() {
        let d_groups = narrow_rows::<B>(d_ext, n, layout.num_groups);
        let to_members = B::gather_rows(d_groups, table::<B>(tables, ids));
        let back = B::scatter_add_rows(to_members, table::<B>(tables, members), n);
        dx = B::float_add(dx, back);
    }
    (dx, d_weight, d_bias)
}

/// The host copy of the tables ([`HostConvTables`]); `None` when the list cannot be read or
/// is inconsistent.
fn host_tables<B: Backend>(tables: &IntTensor<B>, layout: &ConvLayout) -> Option<HostConvTables> {
    HostConvTables::from_packed(&read_indices_primitive::<B>(tables)?, layout)
}

/// `(x, weight, grad)` handed back for the composed fallback, or `(d x, d weight, d bias)`.
type Three<B> = (FloatTensor<B>, FloatTensor<B>, FloatTensor<B>);

/// The host backward ([`crate::host_conv_grad::subm_conv_backward`]: one GEMM per tap block for
/// the weight, one for the sources, taps over the rayon pool); `Err((x, weight, grad))` when a
/// tensor is not f32 or a table does not fit.
pub(super) fn subm_conv_backward_host<B: HostFloat>(
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    grad: FloatTensor<B>,
    tables: &IntTensor<B>,
    layout: &ConvLayout,
) -> Result<Three<B>, Three<B>> {
    let (xs, ws) = (x.shape(), weight.shape());
    let Some(host) = host_tables::<B>(tables, layout) else {
        return Err((x, weight, grad));
    };
    let (c_in, c_out) = (xs[1], ws[0]);
    let out = B::with_f32(&x, |xv| {
        B::with_f32(&weight, |wv| {
            B::with_f32(&grad, |gv| {
                subm_conv_backward(xv, gv, wv, c_in, c_out, &host)
            })
        })
    })
    .flatten()
    .flatten()
    .flatten();
    match out {
        Some(d) => {
            let dx = B::from_f32(d.input, xs, &x);
            let dw = B::from_f32(d.weight, ws, &x);
            let db = B::from_f32(d.bias, Shape::new([c_out]), &x);
            Ok((dx, dw, db))
        }
        None => Err((x, weight, grad)),
    }
}
