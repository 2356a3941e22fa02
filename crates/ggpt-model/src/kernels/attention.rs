//! The window-attention core (network.md §7) as an op of the kernel layer: its composed body
//! (the explicit `softmax((q s) kᵀ) v` and its hand-written gradient, one window sub-group at a
//! time so that no `[W, H, L, L]` score tensor exceeds [`SCORE_BUDGET_FLOATS`]), and the bridge
//! to the host kernels of [`crate::host_attention`] / [`crate::host_attention_grad`], which
//! hold no score tensor at all.
//!
//! ```text
//! rows [W L, 3C] -> [W, L, 3, H, d] -> q, k, v [W, H, L, d]     (columns q | k | v, head h
//!                                                                  owns h d..(h+1) d)
//! P    = softmax((q s) kᵀ)        [W, H, L, L]                   (s = d^-1/2)
//! out  = P v                      [W, H, L, d] -> [W L, C]
//! backward, from g = d out:
//!   dv = Pᵀ g,  dP = g vᵀ,  dS = P ⊙ (dP - rowsum(dP ⊙ P)),  dq = s dS k,  dk = s dSᵀ q
//!   d rows = [dq | dk | dv] in the layout of rows              [W L, 3C]
//! ```

use burn::backend::Backend;
use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn::tensor::Shape;

use super::composed::narrow_rows;
use super::host::HostFloat;
use crate::host_attention::WindowShape;

/// Upper bound on the floats of one score tensor `[W, H, L, L]` of the composed body (128 MiB of
/// f32, network.md §7.5).
pub const SCORE_BUDGET_FLOATS: usize = 32 * 1024 * 1024;

/// The [`WindowShape`] of `rows [W L, 3C]` cut into `windows` windows and `heads` heads; `None`
/// when the sizes do not divide (`W L` rows, `3 H d` columns).
pub fn window_shape(rows: &Shape, windows: usize, heads: usize) -> Option<WindowShape> {
    if rows.num_dims() != 2 || windows == 0 || heads == 0 {
        return None;
    }
    let (m, c3) = (rows[0], rows[1]);
    if m % windows != 0 || c3 % (3 * heads) != 0 {
        return None;
    }
    Some(WindowShape {
        windows,
        len: m / windows,
        heads,
        head_dim: c3 / (3 * heads),
    })
}

/// The softmax scale `s = d^-1/2` of a head width `d` (network.md §7).
pub fn attention_scale(head_dim: usize) -> f64 {
    (head_dim as f64).powf(-0.5)
}

/// Windows per sub-group of the composed body: at most `budget` floats of scores, at least one
/// window.
fn windows_per_group(shape: WindowShape, budget: usize) -> usize {
    let per_window = shape.heads * shape.len * shape.len;
    (budget / per_window.max(1)).max(1)
}

/// `q, k, v [W, H, L, d]` of `rows [W L, 3C]`.
fn split_qkv<B: Backend>(
    rows: FloatTensor<B>,
    shape: WindowShape,
) -> (FloatTensor<B>, FloatTensor<B>, FloatTensor<B>) {
    let WindowShape {
        windows: w,
        len: l,
        heads: h,
        head_dim: d,
    } = shape;
    // [3, W, H, L, d]: one permutation, then q, k, v are views
    let qkv = B::float_permute(
        B::float_reshape(rows, [w, l, 3, h, d].into()),
        &[2, 0, 3, 1, 4],
    );
    let part =
        |i: usize| B::float_reshape(narrow_rows::<B>(qkv.clone(), i, 1), [w, h, l, d].into());
    (part(0), part(1), part(2))
}

/// `softmax((q s) kᵀ)` over the last axis: `[W, H, L, L]`.
fn probabilities<B: Backend>(q: FloatTensor<B>, k: FloatTensor<B>, scale: f64) -> FloatTensor<B> {
    let scores = B::float_matmul(
        B::float_mul_scalar(q, scale.into()),
        B::float_swap_dims(k, 2, 3),
    );
    let max = B::float_max_dim(scores.clone(), 3);
    let e = B::float_exp(B::float_sub(scores, max));
    let sum = B::float_sum_dim(e.clone(), 3);
    B::float_div(e, sum)
}

/// `[W, H, L, d] -> [W L, C]` (heads concatenated per token).
fn merge_heads<B: Backend>(o: FloatTensor<B>, shape: WindowShape) -> FloatTensor<B> {
    B::float_reshape(
        B::float_swap_dims(o, 1, 2),
        [shape.windows * shape.len, shape.channels()].into(),
    )
}

/// Applies `f` to each sub-group of windows (rows of `inputs`, all `[W L, ·]`) and concatenates
/// the results along axis 0.
fn by_sub_group<B: Backend, const N: usize>(
    inputs: [FloatTensor<B>; N],
    shape: WindowShape,
    budget: usize,
    f: impl Fn([FloatTensor<B>; N], WindowShape) -> FloatTensor<B>,
) -> FloatTensor<B> {
    let step = windows_per_group(shape, budget);
    if step >= shape.windows {
        return f(inputs, shape);
    }
    let mut outs = Vec::with_capacity(shape.windows.div_ceil(step));
    let mut w0 = 0;
    while w0 < shape.windows {
        let windows = step.min(shape.windows - w0);
        let part = std::array::from_fn(|i| {
            narrow_rows::<B>(inputs[i].clone(), w0 * shape.len, windows * shape.len)
        });
        outs.push(f(part, WindowShape { windows, ..shape }));
        w0 += windows;
    }
    B::float_cat(outs, 0)
}

/// The composed forward: `rows [W L, 3C] -> [W L, C]` (module docs), by window sub-groups of
/// at most `score_budget` floats of scores ([`SCORE_BUDGET_FLOATS`] in the op).
pub fn window_attention<B: Backend>(
    rows: FloatTensor<B>,
    shape: WindowShape,
    score_budget: usize,
) -> FloatTensor<B> {
    let scale = attention_scale(shape.head_dim);
    by_sub_group::<B, 1>([rows], shape, score_budget, |[rows], shape| {
        let (q, k, v) = split_qkv::<B>(rows, shape);
        let p = probabilities::<B>(q, k, scale);
        merge_heads::<B>(B::float_matmul(p, v), shape)
    })
}

/// The composed backward: `rows [W L, 3C]`, `grad [W L, C]` (the output gradient) ->
/// `d rows [W L, 3C]` (module docs), by window sub-groups of at most `score_budget` floats of
/// scores (the probabilities are recomputed).
pub fn window_attention_backward<B: Backend>(
    rows: FloatTensor<B>,
    grad: FloatTensor<B>,
    shape: WindowShape,
    score_budget: usize,
) -> FloatTensor<B> {
    let scale = attention_scale(shape.head_dim);
    by_sub_group::<B, 2>([rows, grad], shape, score_budget, |[rows, grad], shape| {
        let WindowShape {
            windows: w,
            len: l,
            heads: h,
            head_dim: d,
        } = shape;
        let (q, k, v) = split_qkv::<B>(rows, shape);
        let p = probabilities::<B>(q.clone(), k.clone(), scale);
        // g [W L, C] -> [W, H, L, d]
        let g = B::float_swap_dims(B::float_reshape(grad, [w, l, h, d].into()), 1, 2);
        let dv = B::float_matmul(B::float_swap_dims(p.clone(), 2, 3), g.clone());
        let dp = B::float_matmul(g, B::float_swap_dims(v, 2, 3));
        let row = B::float_sum_dim(B::float_mul(dp.clone(), p.clone()), 3);
        let ds = B::float_mul(p, B::float_sub(dp, row));
        let dq = B::float_mul_scalar(B::float_matmul(ds.clone(), k), scale.into());
        let dk = B::float_mul_scalar(
            B::float_matmul(B::float_swap_dims(ds, 2, 3), q),
            scale.into(),
        );
        // [3, W, H, L, d] -> [W, L, 3, H, d] -> [W L, 3C]
        let one = |t: FloatTensor<B>| B::float_reshape(t, [1, w, h, l, d].into());
        let all = B::float_cat(vec![one(dq), one(dk), one(dv)], 0);
        B::float_reshape(
            B::float_permute(all, &[1, 3, 0, 2, 4]),
            [w * l, 3 * h * d].into(),
        )
    })
}

/// Whether Burn can choose its flash attention kernel: only its autotune does (burn-cubecl
/// 0.22.1 `ops/module.rs`: without autotune `module::attention` is the naive fallback, which
/// materialises the `[W, H, L, L]` scores and costs 4 more launches than the composed body).
pub const FLASH_REACHABLE: bool = cfg!(feature = "autotune");

/// The forward through Burn's fused `attention` with `scale = None` (its default `d^-1/2` is
/// the network's `s`, so q needs no pre-scaling), the only form for which burn-cubecl may pick
/// its flash kernel (any `scale` sends it to the naive fallback). All windows in one call: the
/// flash kernel holds no score tensor.
pub fn window_attention_fused<B: Backend>(
    rows: FloatTensor<B>,
    shape: WindowShape,
) -> FloatTensor<B> {
    let (q, k, v) = split_qkv::<B>(rows, shape);
    let options = burn::tensor::ops::AttentionModuleOptions {
        scale: None,
        softcap: None,
        is_causal: false,
    };
    merge_heads::<B>(B::attention(q, k, v, None, None, options), shape)
}

/// The host forward ([`crate::host_attention::window_attention`]); `Err(rows)` when `rows` is
/// not f32 or does not fit `shape`, for the composed fallback.
pub(super) fn window_attention_host<B: HostFloat>(
    rows: FloatTensor<B>,
    shape: WindowShape,
) -> Result<FloatTensor<B>, FloatTensor<B>> {
    let scale = attention_scale(shape.head_dim) as f32;
    let out = B::with_f32(&rows, |v| {
        crate::host_attention::window_attention(v, shape, scale)
    })
    .flatten();
    match out {
        Some(out) => {
            let out_shape = [shape.windows * shape.len, shape.channels()];
            Ok(B::from_f32(out, out_shape.into(), &rows))
        }
        None => Err(rows),
    }
}

/// The host backward ([`crate::host_attention_grad::window_attention_backward`]);
/// `Err((rows, grad))` when a tensor is not f32 or does not fit `shape`.
pub(super) fn window_attention_backward_host<B: HostFloat>(
    rows: FloatTensor<B>,
    grad: FloatTensor<B>,
    shape: WindowShape,
) -> Result<FloatTensor<B>, (FloatTensor<B>, FloatTensor<B>)> {
    let scale = attention_scale(shape.head_dim) as f32;
    let out = B::with_f32(&rows, |r| {
        B::with_f32(&grad, |g| {
            crate::host_attention_grad::window_attention_backward(r, g, shape, scale)
        })
    })
    .flatten()
    .flatten();
    match out {
        Some(out) => {
            let rows_shape = rows.shape();
            Ok(B::from_f32(out, rows_shape, &rows))
        }
        None => Err((rows, grad)),
    }
}
