//! Backward of the host window-attention core ([`crate::host_attention`]) for CPU training
//! (network.md §7, `docs/training.md` "Memory-efficient training").
//!
//! ```text
//! rows  [W L, 3C]  (q | k | v, head h in columns h d..(h+1) d of each), d_out [W L, C]
//! per (window, head), per block of QB query rows (scores recomputed, never stored):
//!   S   = s · Q_blk Kᵀ                 [QB, L]
//!   P   = softmax_rows(S)              [QB, L]
//!   dP  = dO_blk Vᵀ                    [QB, L]
//!   dS  = P ∘ (dP − rowsum(P ∘ dP))    [QB, L]
//!   dQ_blk  = s · dS K                 [QB, d]   (written)
//!   dK     += s · dSᵀ Q_blk            [L, d]    (accumulated over the blocks)
//!   dV     += Pᵀ dO_blk                [L, d]
//! d_rows [W L, 3C]  (dq | dk | dv)
//! ```
//!
//! Why hand-written: under Burn's autodiff the core is `softmax(q kᵀ s) v` on tensors, whose
//! graph keeps the `[W, H, L, L]` scores, softmax and their gradients (hundreds of MB per window
//! group of the released configuration) and whose element-wise backward kernels run on one
//! thread. Here one task per (window, head) holds two `[QB, L]` blocks; the products are GEMMs
//! and the work is spread over the rayon pool. It is the exact gradient of the same function,
//! so the segment recomputation of [`crate::recompute`] stays equal to plain autodiff.

use rayon::prelude::*;

use crate::host_attention::{QUERY_BLOCK, WindowShape, softmax_rows};

/// Gradient of the window-attention core with respect to its `qkv` rows.
///
/// `rows` `[W L, 3C]` and `d_out` `[W L, C]` row-major, as for
/// [`crate::host_attention::window_attention`] (whose output `d_out` is the gradient of).
/// Returns `d_rows` `[W L, 3C]`, or `None` when a length does not match `shape`.
pub fn window_attention_backward(
    rows: &[f32],
    d_out: &[f32],
    shape: WindowShape,
    scale: f32,
) -> Option<Vec<f32>> {
    let WindowShape {
        windows,
        len,
        heads,
        ..
    } = shape;
    let c = shape.channels();
    if rows.len() != windows * len * 3 * c || d_out.len() != windows * len * c {
        return None;
    }
    let mut d_rows = vec![0.0f32; rows.len()];
    if d_rows.is_empty() {
        return Some(d_rows);
    }
    let dst = SharedOut(d_rows.as_mut_ptr());
    (0..windows * heads).into_par_iter().for_each_init(
        || Scratch::new(len, shape.head_dim),
        |scratch, task| {
            let (w, h) = (task / heads, task % heads);
            // SAFETY: task (w, h) writes only rows w L .. (w+1) L, columns h d.., c + h d..,
            // 2c + h d.. (d wide each) of `d_rows`: disjoint from every other task, and
            // `d_rows` outlives the parallel loop. The lengths were checked above.
            unsafe { window_head(rows, d_out, &dst, scratch, shape, scale, w, h) };
        },
    );
    Some(d_rows)
}

/// The gradient buffer shared by the tasks (each writes its own disjoint block).
struct SharedOut(*mut f32);
// SAFETY: the tasks write disjoint elements (see `window_attention_backward`).
unsafe impl Sync for SharedOut {}

/// Per-thread buffers of one (window, head) task.
struct Scratch {
    /// `P` of a query block, `[QB, L]`.
    p: Vec<f32>,
    /// `dP`, then `dS`, of a query block, `[QB, L]`.
    ds: Vec<f32>,
    /// `dK` `[L, d]`.
    dk: Vec<f32>,
    /// `dV` `[L, d]`.
    dv: Vec<f32>,
}

impl Scratch {
    fn new(len: usize, d: usize) -> Self {
        Self {
            p: vec![0.0; QUERY_BLOCK * len],
            ds: vec![0.0; QUERY_BLOCK * len],
            dk: vec![0.0; len * d],
            dv: vec![0.0; len * d],
        }
    }
}

/// One (window, head) task.
///
/// # Safety
/// `rows` has `W L 3C` elements, `d_out` `W L C`, `out` points to `W L 3C` writable elements
/// of which no other thread writes this task's block (see [`window_attention_backward`]).
#[allow(clippy::too_many_arguments)]
unsafe fn window_head(
    rows: &[f32],
    d_out: &[f32],
    out: &SharedOut,
    scratch: &mut Scratch,
    shape: WindowShape,
    scale: f32,
    w: usize,
    h: usize,
) {
    let WindowShape {
        len, head_dim: d, ..
    } = shape;
    let c = shape.channels();
    let rs = (3 * c) as isize;
    let win = w * len * 3 * c;
    let k = rows.as_ptr().wrapping_add(win + c + h * d);
    let v = rows.as_ptr().wrapping_add(win + 2 * c + h * d);
    let Scratch { p, ds, dk, dv } = scratch;
    dk.fill(0.0);
    dv.fill(0.0);
    let mut inv_sum = [0.0f32; QUERY_BLOCK];
    let mut q0 = 0;
    while q0 < len {
        let qb = QUERY_BLOCK.min(len - q0);
        let q = rows.as_ptr().wrapping_add(win + q0 * 3 * c + h * d);
        let g = d_out.as_ptr().wrapping_add((w * len + q0) * c + h * d);
        let dq = out.0.wrapping_add(win + q0 * 3 * c + h * d);
        let (p, ds) = (&mut p[..qb * len], &mut ds[..qb * len]);
        let l = len as isize;
        // SAFETY (every GEMM): the strides stay inside `rows`, `d_out`, the scratch buffers and
        // this task's block of `out` (the caller's contract).
        unsafe {
            // S [qb, L] = scale · Q [qb, d] · Kᵀ [d, L]
            gemm::gemm(
                qb,
                len,
                d,
                p.as_mut_ptr(),
                1,
                l,
                false,
                q,
                1,
                rs,
                k,
                rs,
                1,
                0.0f32,
                scale,
                false,
                false,
                false,
                gemm::Parallelism::None,
            );
        }
        softmax_rows(p, len, &mut inv_sum[..qb]);
        for (row, &inv) in p.chunks_exact_mut(len).zip(&inv_sum[..qb]) {
            for x in row {
                *x *= inv;
            }
        }
        unsafe {
            // dP [qb, L] = dO [qb, d] · Vᵀ [d, L]
            gemm::gemm(
                qb,
                len,
                d,
                ds.as_mut_ptr(),
                1,
                l,
                false,
                g,
                1,
                c as isize,
                v,
                rs,
                1,
                0.0f32,
                1.0f32,
                false,
                false,
                false,
                gemm::Parallelism::None,
            );
        }
        for (dsr, pr) in ds.chunks_exact_mut(len).zip(p.chunks_exact(len)) {
            let dot = dot(dsr, pr);
            for (x, &pv) in dsr.iter_mut().zip(pr) {
                *x = pv * (*x - dot);
            }
        }
        unsafe {
            // dQ [qb, d] = scale · dS [qb, L] · K [L, d]
            gemm::gemm(
                qb,
                d,
                len,
                dq,
                1,
                rs,
                false,
                ds.as_ptr(),
                1,
                l,
                k,
                1,
                rs,
                0.0f32,
                scale,
                false,
                false,
                false,
                gemm::Parallelism::None,
            );
            // dK [L, d] += scale · dSᵀ [L, qb] · Q [qb, d]
            gemm::gemm(
                len,
                d,
                qb,
                dk.as_mut_ptr(),
                1,
                d as isize,
                true,
                ds.as_ptr(),
                l,
                1,
                q,
                1,
                rs,
                1.0f32,
                scale,
                false,
                false,
                false,
                gemm::Parallelism::None,
            );
            // dV [L, d] += Pᵀ [L, qb] · dO [qb, d]
            gemm::gemm(
                len,
                d,
                qb,
                dv.as_mut_ptr(),
                1,
                d as isize,
                true,
                p.as_ptr(),
                l,
                1,
                g,
                1,
                c as isize,
                1.0f32,
                1.0f32,
                false,
                false,
                false,
                gemm::Parallelism::None,
            );
        }
        q0 += qb;
    }
    for t in 0..len {
        let row = out.0.wrapping_add(win + t * 3 * c);
        // SAFETY: row t of this window, columns c + h d .. + d and 2c + h d .. + d (this task's).
        unsafe {
            std::ptr::copy_nonoverlapping(dk.as_ptr().add(t * d), row.add(c + h * d), d);
            std::ptr::copy_nonoverlapping(dv.as_ptr().add(t * d), row.add(2 * c + h * d), d);
        }
    }
}

/// `Σ a_i b_i` with independent lane accumulators (vectorised).
#[inline(always)]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    const LANES: usize = 8;
    let mut acc = [0.0f32; LANES];
    let (ca, cb) = (a.chunks_exact(LANES), b.chunks_exact(LANES));
    let tail: f32 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(x, y)| x * y)
        .sum();
    for (xa, xb) in ca.zip(cb) {
        for i in 0..LANES {
            acc[i] += xa[i] * xb[i];
        }
    }
    tail + acc.iter().sum::<f32>()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::host_attention::window_attention;

    /// Deterministic values in [-1, 1).
    fn pseudo_random(n: usize, seed: u64) -> Vec<f32> {
        crate::host_attention::tests::pseudo_random(n, seed)
            .into_iter()
            .map(|x| 0.5 * x)
            .collect()
    }

    /// `Σ g ∘ attention(rows)` in f64: the function whose gradient the kernel returns.
    fn objective(rows: &[f64], g: &[f32], s: WindowShape, scale: f64) -> f64 {
        let (l, h, d, c) = (s.len, s.heads, s.head_dim, s.channels());
        let at = |w: usize, t: usize, part: usize, hh: usize, j: usize| {
            rows[(w * l + t) * 3 * c + part * c + hh * d + j]
        };
        let mut total = 0.0;
        for w in 0..s.windows {
            for hh in 0..h {
                for i in 0..l {
                    let sc: Vec<f64> = (0..l)
                        .map(|t| {
                            (0..d)
                                .map(|j| at(w, i, 0, hh, j) * at(w, t, 1, hh, j))
                                .sum::<f64>()
                                * scale
                        })
                        .collect();
                    let m = sc.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
                    let e: Vec<f64> = sc.iter().map(|x| (x - m).exp()).collect();
                    let z: f64 = e.iter().sum();
                    for j in 0..d {
                        let o = (0..l).map(|t| e[t] * at(w, t, 2, hh, j)).sum::<f64>() / z;
                        total += o * f64::from(g[(w * l + i) * c + hh * d + j]);
                    }
                }
            }
        }
        total
    }

    /// Central finite differences in f64 of every input element, against the kernel.
    #[test]
    fn matches_finite_differences() {
        for (i, &(w, l, h, d)) in [(2, 5, 2, 3), (1, 70, 1, 4), (1, 1, 2, 2)]
            .iter()
            .enumerate()
        {
            let shape = WindowShape {
                windows: w,
                len: l,
                heads: h,
                head_dim: d,
            };
            let rows = pseudo_random(w * l * 3 * h * d, 2 * i as u64 + 1);
            let g = pseudo_random(w * l * h * d, 2 * i as u64 + 2);
            let scale = (d as f32).powf(-0.5);
            let got = window_attention_backward(&rows, &g, shape, scale).unwrap();
            let base: Vec<f64> = rows.iter().map(|&x| f64::from(x)).collect();
            let eps = 1e-5;
            let mut worst = 0.0f64;
            for e in 0..rows.len() {
                let mut plus = base.clone();
                plus[e] += eps;
                let mut minus = base.clone();
                minus[e] -= eps;
                let want = (objective(&plus, &g, shape, f64::from(scale))
                    - objective(&minus, &g, shape, f64::from(scale)))
                    / (2.0 * eps);
                worst = worst.max((want - f64::from(got[e])).abs());
            }
            assert!(worst < 2e-5, "{shape:?}: worst gradient error {worst:e}");
        }
    }

    /// The forward kernel and this backward see the same function: a step along the gradient
    /// changes `Σ g ∘ out` by `|grad|² · step` to first order.
    #[test]
    fn consistent_with_the_forward_kernel() {
        let shape = WindowShape {
            windows: 3,
            len: 130,
            heads: 2,
            head_dim: 8,
        };
        let rows = pseudo_random(3 * 130 * 3 * 16, 9);
        let g = pseudo_random(3 * 130 * 16, 10);
        let scale = 8f32.powf(-0.5);
        let grad = window_attention_backward(&rows, &g, shape, scale).unwrap();
        let f = |r: &[f32]| -> f64 {
            window_attention(r, shape, scale)
                .unwrap()
                .iter()
                .zip(&g)
                .map(|(o, g)| f64::from(o * g))
                .sum()
        };
        let step = 1e-3f32;
        let moved: Vec<f32> = rows.iter().zip(&grad).map(|(x, d)| x + step * d).collect();
        let norm2: f64 = grad.iter().map(|d| f64::from(d * d)).sum();
        let predicted = norm2 * f64::from(step);
        let actual = f(&moved) - f(&rows);
        assert!(
            (actual - predicted).abs() < 0.02 * predicted,
            "{actual} vs {predicted}"
        );
    }

    #[test]
    fn rejects_wrong_lengths_and_handles_empty() {
        let shape = WindowShape {
            windows: 1,
            len: 4,
            heads: 1,
            head_dim: 2,
        };
        assert!(window_attention_backward(&[0.0; 24], &[0.0; 7], shape, 1.0).is_none());
        assert!(window_attention_backward(&[0.0; 23], &[0.0; 8], shape, 1.0).is_none());
        let empty = WindowShape {
            windows: 0,
            len: 4,
            heads: 1,
            head_dim: 2,
        };
        assert_eq!(
            window_attention_backward(&[], &[], empty, 1.0),
            Some(Vec::new())
        );
    }
}
