//! Host (CPU) kernel of the serialized window attention core for inference (network.md §7):
//! `softmax((q s) kᵀ) v` per window and head, read straight from the `qkv` projection rows and
//! written straight into the `[W L, C]` output, without the `[3, W, H, L, d]` permutation.
//!
//! ```text
//! rows [W L, 3C]  (columns q | k | v; head h owns h d..(h+1) d of each)
//! per (window, head, block of QB query rows):
//!   S   = s · Q_blk Kᵀ            [QB, L]   one GEMM (k = d), strided views of `rows`
//!   P   = exp(S - rowmax(S))      [QB, L]   vectorised exp, row sums kept
//!   O   = (P V) / rowsum(P)       [QB, d]   one GEMM (k = L) into out[rows, h d..(h+1) d]
//! out  [W L, C]
//! ```
//!
//! Why: with head dimensions 16-32 (released `enc1`-`enc4`, all decoder stages) a score costs
//! only 4d flops, and the per-score work of an online-softmax flash kernel (scalar `exp`,
//! running max / rescale) dominated: ~6-8 ns per score whatever `d` (docs/performance.md). Here
//! the scores of a block go through GEMMs (the `gemm` crate's runtime-dispatched SIMD kernels)
//! and a branch-free polynomial `exp` that the compiler vectorises (AVX2 + FMA when the CPU has
//! them, detected at run time). Work is split over the rayon pool by (window, head, block).
//! Its gradient is [`crate::host_attention_grad`] (CPU training); the GPU path keeps the
//! tensor formulation.

use rayon::prelude::*;

/// Query rows per task: the `[QB, L]` score block of a 1024-token window is 256 KiB (L2-sized).
pub const QUERY_BLOCK: usize = 64;

/// Shape of one window group: `windows` windows of `len` tokens, `heads` heads of `head_dim`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WindowShape {
    /// Windows `W`.
    pub windows: usize,
    /// Tokens per window `L`.
    pub len: usize,
    /// Heads `H`.
    pub heads: usize,
    /// Head dimension `d` (`C = H d`).
    pub head_dim: usize,
}

impl WindowShape {
    /// Channels `C = H d`.
    pub fn channels(&self) -> usize {
        self.heads * self.head_dim
    }
}

/// The attention core of one window group.
///
/// `rows`: `[W L, 3C]` row-major, the `qkv` projection of the gathered tokens (window `w`,
/// token `t` is row `w L + t`). Returns `[W L, C]` row-major (head `h` in columns
/// `h d..(h+1) d`), each row `softmax(scale q kᵀ) v` over the `L` tokens of its own window.
/// Returns `None` when `rows` does not have `W L 3C` elements.
pub fn window_attention(rows: &[f32], shape: WindowShape, scale: f32) -> Option<Vec<f32>> {
    let WindowShape {
        windows,
        len,
        heads,
        ..
    } = shape;
    let c = shape.channels();
    if rows.len() != windows * len * 3 * c {
        return None;
    }
    let mut out = vec![0.0f32; windows * len * c];
    if out.is_empty() {
        return Some(out);
    }
    let blocks = len.div_ceil(QUERY_BLOCK);
    let tasks = windows * heads * blocks;
    let dst = SharedOut(out.as_mut_ptr());
    (0..tasks).into_par_iter().for_each_init(
        || vec![0.0f32; QUERY_BLOCK * len],
        |scores, task| {
            let (wh, b) = (task / blocks, task % blocks);
            let (w, h) = (wh / heads, wh % heads);
            let q0 = b * QUERY_BLOCK;
            let qb = QUERY_BLOCK.min(len - q0);
            // SAFETY: task (w, h, b) writes only rows w L + q0 .. + qb, columns h d .. (h+1) d of
            // `out`: disjoint from every other task, and `out` outlives the parallel loop.
            unsafe { block(rows, &dst, scores, shape, scale, w, h, q0, qb) };
        },
    );
    Some(out)
}

/// The output buffer shared by the tasks (each writes its own disjoint block).
struct SharedOut(*mut f32);
// SAFETY: the tasks write disjoint elements (see `window_attention`).
unsafe impl Sync for SharedOut {}

/// One (window, head, query block) task.
///
/// # Safety
/// `rows` has `W L 3C` elements, `out` points to `W L C` writable elements that no other
/// thread writes in this block, `scores` has at least `qb L` elements.
#[allow(clippy::too_many_arguments)]
unsafe fn block(
    rows: &[f32],
    out: &SharedOut,
    scores: &mut [f32],
    shape: WindowShape,
    scale: f32,
    w: usize,
    h: usize,
    q0: usize,
    qb: usize,
) {
    let WindowShape {
        len, head_dim: d, ..
    } = shape;
    let c = shape.channels();
    let row_stride = (3 * c) as isize;
    let win = w * len * 3 * c;
    let q = rows.as_ptr().wrapping_add(win + q0 * 3 * c + h * d);
    let k = rows.as_ptr().wrapping_add(win + c + h * d);
    let v = rows.as_ptr().wrapping_add(win + 2 * c + h * d);
    let s = &mut scores[..qb * len];
    // SAFETY (both GEMMs): every index the strides reach lies inside `rows` / `s` / `out`.
    unsafe {
        // S [qb, L] = scale · Q [qb, d] · Kᵀ [d, L]   (Kᵀ(j, t) = K(t, j): row stride 1, column stride 3C)
        gemm::gemm(
            qb,
            len,
            d,
            s.as_mut_ptr(),
            1,
            len as isize,
            false,
            q,
            1,
            row_stride,
            k,
            row_stride,
            1,
            0.0f32,
            scale,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
    let mut inv_sum = [0.0f32; QUERY_BLOCK];
    softmax_rows(s, len, &mut inv_sum[..qb]);
    let o = out.0.wrapping_add((w * len + q0) * c + h * d);
    unsafe {
        // O [qb, d] = P [qb, L] · V [L, d], written into the output rows (row stride C).
        gemm::gemm(
            qb,
            d,
            len,
            o,
            1,
            c as isize,
            false,
            s.as_ptr(),
            1,
            len as isize,
            v,
            1,
            row_stride,
            0.0f32,
            1.0f32,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
        for (r, &inv) in inv_sum[..qb].iter().enumerate() {
            let row = std::slice::from_raw_parts_mut(o.wrapping_add(r * c), d);
            for x in row {
                *x *= inv;
            }
        }
    }
}

/// Row-wise `exp(x - max)` in place over `s` (`rows × len`), `inv_sum[r] = 1 / Σ exp`.
pub(crate) fn softmax_rows(s: &mut [f32], len: usize, inv_sum: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: the CPU supports AVX2 and FMA (checked just above).
            unsafe { softmax_rows_avx2(s, len, inv_sum) };
            return;
        }
    }
    softmax_rows_generic(s, len, inv_sum);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn softmax_rows_avx2(s: &mut [f32], len: usize, inv_sum: &mut [f32]) {
    softmax_rows_generic(s, len, inv_sum);
}

/// Lanes of the vectorised reductions (independent accumulators the compiler keeps in one
/// SIMD register).
const LANES: usize = 8;

#[inline(always)]
fn softmax_rows_generic(s: &mut [f32], len: usize, inv_sum: &mut [f32]) {
    for (row, inv) in s.chunks_exact_mut(len).zip(inv_sum.iter_mut()) {
        let m = row_max(row);
        for x in row.iter_mut() {
            *x = exp_nonpositive(*x - m);
        }
        let total = row_sum(row);
        *inv = if total > 0.0 { 1.0 / total } else { 0.0 };
    }
}

#[inline(always)]
fn row_max(row: &[f32]) -> f32 {
    let mut acc = [f32::NEG_INFINITY; LANES];
    let mut it = row.chunks_exact(LANES);
    for ch in &mut it {
        for (a, &x) in acc.iter_mut().zip(ch) {
            *a = if x > *a { x } else { *a };
        }
    }
    let mut m = it
        .remainder()
        .iter()
        .fold(f32::NEG_INFINITY, |a, &x| if x > a { x } else { a });
    for a in acc {
        m = if a > m { a } else { m };
    }
    m
}

#[inline(always)]
fn row_sum(row: &[f32]) -> f32 {
    let mut acc = [0.0f32; LANES];
    let mut it = row.chunks_exact(LANES);
    for ch in &mut it {
        for (a, &x) in acc.iter_mut().zip(ch) {
            *a += x;
        }
    }
    it.remainder().iter().sum::<f32>() + acc.iter().sum::<f32>()
}

/// `2^23 + 2^22`: adding it rounds a float of magnitude < 2^22 to an integer held in the low
/// mantissa bits.
const ROUND_MAGIC: f32 = 12_582_912.0;
/// `ln 2` split in a high part exact in f32 products and the low remainder (Cody-Waite).
const LN2_HI: f32 = 0.693_145_75;
const LN2_LO: f32 = 1.428_606_8e-6;
/// Below this the result underflows f32 normals; clamped (`exp(-87) ≈ 1.6e-38`).
const EXP_MIN_ARG: f32 = -87.0;

/// `exp(x)` for `x ≤ 0` (softmax arguments after the row maximum), branch-free so that loops
/// over it vectorise: `x = n ln2 + r`, `|r| ≤ ln2 / 2`, degree-6 Taylor polynomial of `e^r`
/// (relative error < 2e-7), scaled by `2^n` through the exponent bits. NaN stays NaN; `-inf`
/// and arguments below -87 give ~1.6e-38 (negligible against the row maximum's 1).
#[inline(always)]
pub fn exp_nonpositive(x: f32) -> f32 {
    let x = if x < EXP_MIN_ARG { EXP_MIN_ARG } else { x };
    let t = x * std::f32::consts::LOG2_E + ROUND_MAGIC;
    let n = t - ROUND_MAGIC;
    let r = (x - n * LN2_HI) - n * LN2_LO;
    let p = 1.0
        + r * (1.0
            + r * (0.5
                + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (1.0 / 720.0))))));
    // The integer n sits in the low mantissa bits of t (offset 2^22).
    let ni = (t.to_bits() as i32).wrapping_sub(ROUND_MAGIC.to_bits() as i32);
    p * f32::from_bits((ni.wrapping_add(127) << 23) as u32)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// Straightforward f64 reference of the same core.
    fn reference(rows: &[f32], s: WindowShape, scale: f32) -> Vec<f32> {
        let (l, h, d, c) = (s.len, s.heads, s.head_dim, s.channels());
        let mut out = vec![0.0f32; s.windows * l * c];
        let at = |w: usize, t: usize, part: usize, hh: usize, j: usize| {
            rows[(w * l + t) * 3 * c + part * c + hh * d + j] as f64
        };
        for w in 0..s.windows {
            for hh in 0..h {
                for i in 0..l {
                    let sc: Vec<f64> = (0..l)
                        .map(|t| {
                            (0..d)
                                .map(|j| at(w, i, 0, hh, j) * at(w, t, 1, hh, j))
                                .sum::<f64>()
                                * scale as f64
                        })
                        .collect();
                    let m = sc.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
                    let e: Vec<f64> = sc.iter().map(|x| (x - m).exp()).collect();
                    let z: f64 = e.iter().sum();
                    for j in 0..d {
                        out[(w * l + i) * c + hh * d + j] =
                            ((0..l).map(|t| e[t] * at(w, t, 2, hh, j)).sum::<f64>() / z) as f32;
                    }
                }
            }
        }
        out
    }

    /// Deterministic values in [-2, 2).
    pub(crate) fn pseudo_random(n: usize, seed: u64) -> Vec<f32> {
        let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        (0..n)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                ((s >> 40) as f32 / (1u64 << 24) as f32) * 4.0 - 2.0
            })
            .collect()
    }

    #[test]
    fn exp_matches_std_on_the_softmax_range() {
        let mut worst = 0.0f64;
        for i in 0..=200_000 {
            let x = -(i as f32) * 87.0 / 200_000.0;
            let (a, b) = (exp_nonpositive(x) as f64, (x as f64).exp());
            worst = worst.max(((a - b) / b).abs());
        }
        assert!(worst < 3e-7, "worst relative error {worst}");
        assert_eq!(exp_nonpositive(0.0), 1.0);
        assert!(exp_nonpositive(f32::NEG_INFINITY) < 1e-37);
        assert!(exp_nonpositive(f32::NAN).is_nan());
    }

    #[test]
    fn matches_reference_for_short_long_and_odd_windows() {
        // (windows, len, heads, head_dim): odd length and a partial query block, several blocks,
        // a single token.
        for (i, &(w, l, h, d)) in [(2, 37, 3, 8), (1, 150, 2, 16), (3, 1, 2, 4), (1, 64, 1, 24)]
            .iter()
            .enumerate()
        {
            let shape = WindowShape {
                windows: w,
                len: l,
                heads: h,
                head_dim: d,
            };
            let rows = pseudo_random(w * l * 3 * h * d, i as u64 + 1);
            let scale = (d as f32).powf(-0.5);
            let got = window_attention(&rows, shape, scale).unwrap();
            let want = reference(&rows, shape, scale);
            let err = got
                .iter()
                .zip(&want)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            assert!(err < 2e-6, "{shape:?}: max abs error {err}");
        }
    }

    #[test]
    fn rejects_wrong_length_and_handles_empty() {
        let shape = WindowShape {
            windows: 2,
            len: 4,
            heads: 2,
            head_dim: 4,
        };
        assert!(window_attention(&[0.0; 10], shape, 1.0).is_none());
        let empty = WindowShape {
            windows: 0,
            len: 4,
            heads: 2,
            head_dim: 4,
        };
        assert_eq!(window_attention(&[], empty, 1.0), Some(Vec::new()));
    }
}
