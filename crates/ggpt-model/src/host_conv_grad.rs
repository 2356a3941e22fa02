//! Backward of the submanifold sparse convolution ([`crate::sparse_conv`]) on the host, for CPU
//! training (network.md §6, `docs/training.md` "Memory-efficient training").
//!
//! ```text
//! X_ext = [x; group sums]                         [N + G, C_in]   (duplicate-voxel rule, §6)
//! out[target_f[p]] += W_f X_ext[source_f[p]]      per tap f, pair p;  W_f = weight[:, f, :]
//! backward, g = d out [N, C_out]:
//!   d bias              = Σ_rows g
//!   d W_f   [C_out, C_in] = Σ_p g[target_f[p]]ᵀ X_ext[source_f[p]]          (one GEMM per block)
//!   d X_ext[source_f[p]] += g[target_f[p]] W_f                              (one GEMM per block)
//!   d x = d X_ext[0..N] + d X_ext[N + group] at each group member
//! ```
//!
//! Why hand-written: under Burn's autodiff the tap-wise form slices the weight once per tap,
//! and the backward of each slice is a zero-filled weight-sized tensor (27 of them per conv,
//! each `27 C_in C_out` floats, summed one by one on one thread). On the deep levels (weights of
//! 27 · 512² floats, a few hundred tokens) that was most of a training step's conv time. Here
//! each tap's weight gradient is written once, the products are GEMMs and the taps are spread
//! over the rayon pool (one accumulator of `d X_ext` per worker). It is the exact gradient of
//! the same function, so [`crate::recompute`] stays equal to plain autodiff.

use rayon::prelude::*;

use crate::conv_layout::{ConvLayout, NUM_TAPS};
use crate::prepared::ConvIndex;
use crate::readback::read_indices;

/// Pairs per GEMM block (bounds the gathered buffers: `PAIR_BLOCK (2 C_in + C_out)` floats).
const PAIR_BLOCK: usize = 4096;

/// Host copies of the tables of one [`ConvIndex`].
#[derive(Debug, Clone)]
pub struct HostConvTables {
    /// Tokens `N`.
    pub num_tokens: usize,
    /// Summed groups `G` (rows `N .. N + G` of `X_ext`).
    pub num_groups: usize,
    /// `(member token, group)` of every group entry.
    pub group_entries: Vec<(usize, usize)>,
    /// Per tap with pairs: the tap `f`, the `X_ext` row of each pair, its output row.
    pub taps: Vec<(usize, Vec<usize>, Vec<usize>)>,
}

impl HostConvTables {
    /// Reads the tables of `index` back; `None` when they cannot be read or are inconsistent
    /// (an index out of range, tables of different lengths).
    pub fn read(index: &ConvIndex) -> Option<Self> {
        Self::from_packed(&read_indices(&index.tables)?, &index.layout)
    }

    /// The tables of the packed list `packed` read by `layout` ([`crate::conv_layout`]);
    /// `None` when it is too short or inconsistent.
    pub fn from_packed(packed: &[usize], layout: &ConvLayout) -> Option<Self> {
        let table = |(a, len): (usize, usize)| packed.get(a..a + len);
        let group_entries = match layout.groups() {
            Some((members, ids)) => table(members)?
                .iter()
                .copied()
                .zip(table(ids)?.iter().copied())
                .collect(),
            None => Vec::new(),
        };
        let mut taps = Vec::with_capacity(layout.taps.len());
        for (tap, (source, target)) in layout.taps.iter().zip(layout.tap_spans()) {
            taps.push((tap.tap, table(source)?.to_vec(), table(target)?.to_vec()));
        }
        Self::checked(layout.num_tokens, layout.num_groups, group_entries, taps)
    }

    /// The tables of `n` tokens and `g` groups; `None` when they are inconsistent (a member
    /// outside `0..n`, a group outside `0..g`, a tap outside `0..27`, a source outside
    /// `0..n + g`, a target outside `0..n`, sources and targets of different lengths).
    pub fn checked(
        n: usize,
        g: usize,
        group_entries: Vec<(usize, usize)>,
        taps: Vec<(usize, Vec<usize>, Vec<usize>)>,
    ) -> Option<Self> {
        if group_entries.iter().any(|&(m, i)| m >= n || i >= g) {
            return None;
        }
        let bad_tap = |(tap, source, target): &(usize, Vec<usize>, Vec<usize>)| {
            *tap >= NUM_TAPS
                || source.len() != target.len()
                || source.iter().any(|&s| s >= n + g)
                || target.iter().any(|&r| r >= n)
        };
        if taps.iter().any(bad_tap) {
            return None;
        }
        Some(Self {
            num_tokens: n,
            num_groups: g,
            group_entries,
            taps,
        })
    }
}

/// Weight gradients `[C_out, C_in]` of some taps, with the tap index.
type TapGrads = Vec<(usize, Vec<f32>)>;

/// Gradients of one submanifold conv.
#[derive(Debug, Clone, PartialEq)]
pub struct ConvGrads {
    /// `d weight` in the weight's KRSC layout `[C_out, 27, C_in]`.
    pub weight: Vec<f32>,
    /// `d bias` `[C_out]`.
    pub bias: Vec<f32>,
    /// `d x` `[N, C_in]`.
    pub input: Vec<f32>,
}

/// Gradient of `out = subm_conv(x)` for `g = d out`.
///
/// `x` `[N, C_in]`, `g` `[N, C_out]`, `weight` `[C_out, 27, C_in]` (KRSC), all row-major.
/// `None` when a length does not match the tables or the channels.
pub fn subm_conv_backward(
    x: &[f32],
    g: &[f32],
    weight: &[f32],
    c_in: usize,
    c_out: usize,
    tables: &HostConvTables,
) -> Option<ConvGrads> {
    let n = tables.num_tokens;
    if x.len() != n * c_in || g.len() != n * c_out || weight.len() != c_out * NUM_TAPS * c_in {
        return None;
    }
    let rows_ext = n + tables.num_groups;
    // X_ext = [x; group sums]
    let mut x_ext = Vec::with_capacity(rows_ext * c_in);
    x_ext.extend_from_slice(x);
    x_ext.resize(rows_ext * c_in, 0.0);
    for &(m, grp) in &tables.group_entries {
        let (dst, src) = ((n + grp) * c_in, m * c_in);
        for i in 0..c_in {
            x_ext[dst + i] += x[src + i];
        }
    }
    let mut bias = vec![0.0f32; c_out];
    for row in g.chunks_exact(c_out.max(1)) {
        for (b, v) in bias.iter_mut().zip(row) {
            *b += v;
        }
    }
    // per tap: its weight gradient; per group of consecutive taps: an accumulator of d X_ext.
    // The groups are fixed by the tap list and the thread count (not by rayon's scheduling) and
    // added in order, so a step is reproducible (exact resume, docs/training.md).
    let groups = rayon::current_num_threads().clamp(1, tables.taps.len().max(1));
    let per_group = tables.taps.len().div_ceil(groups).max(1);
    let partial: Vec<(Vec<f32>, TapGrads)> = tables
        .taps
        .par_chunks(per_group)
        .map(|taps| {
            let mut acc = vec![0.0f32; rows_ext * c_in];
            let dws = taps
                .iter()
                .map(|(tap, source, target)| {
                    let dw = tap_backward(
                        &x_ext, g, weight, c_in, c_out, *tap, source, target, &mut acc,
                    );
                    (*tap, dw)
                })
                .collect::<Vec<_>>();
            (acc, dws)
        })
        .collect();
    let mut d_ext: Vec<f32> = Vec::new();
    let mut tap_grads = Vec::with_capacity(tables.taps.len());
    for (acc, dws) in partial {
        if d_ext.is_empty() {
            d_ext = acc;
        } else {
            d_ext.iter_mut().zip(&acc).for_each(|(a, v)| *a += v);
        }
        tap_grads.extend(dws);
    }
    let mut d_weight = vec![0.0f32; weight.len()];
    for (tap, dw) in tap_grads {
        // dw [C_out, C_in] -> rows o, block tap of the KRSC layout (taps appear once)
        for o in 0..c_out {
            let dst = o * NUM_TAPS * c_in + tap * c_in;
            for (acc, v) in d_weight[dst..dst + c_in]
                .iter_mut()
                .zip(&dw[o * c_in..(o + 1) * c_in])
            {
                *acc += v;
            }
        }
    }
    let mut input = vec![0.0f32; n * c_in];
    if !d_ext.is_empty() {
        input.copy_from_slice(&d_ext[..n * c_in]);
        for &(m, grp) in &tables.group_entries {
            let (dst, src) = (m * c_in, (n + grp) * c_in);
            for i in 0..c_in {
                input[dst + i] += d_ext[src + i];
            }
        }
    }
    Some(ConvGrads {
        weight: d_weight,
        bias,
        input,
    })
}

/// One tap: returns `d W_f` `[C_out, C_in]` and adds `g[target] W_f` into `acc[source]`.
#[allow(clippy::too_many_arguments)]
fn tap_backward(
    x_ext: &[f32],
    g: &[f32],
    weight: &[f32],
    c_in: usize,
    c_out: usize,
    tap: usize,
    source: &[usize],
    target: &[usize],
    acc: &mut [f32],
) -> Vec<f32> {
    let mut dw = vec![0.0f32; c_out * c_in];
    let mut xs = vec![0.0f32; PAIR_BLOCK.min(source.len()) * c_in];
    let mut gs = vec![0.0f32; PAIR_BLOCK.min(source.len()) * c_out];
    let mut dx = vec![0.0f32; PAIR_BLOCK.min(source.len()) * c_in];
    let w_f = weight.as_ptr().wrapping_add(tap * c_in);
    for (b, (src, tgt)) in source
        .chunks(PAIR_BLOCK)
        .zip(target.chunks(PAIR_BLOCK))
        .enumerate()
    {
        let len = src.len();
        for (p, (&s, &t)) in src.iter().zip(tgt).enumerate() {
            xs[p * c_in..(p + 1) * c_in].copy_from_slice(&x_ext[s * c_in..(s + 1) * c_in]);
            gs[p * c_out..(p + 1) * c_out].copy_from_slice(&g[t * c_out..(t + 1) * c_out]);
        }
        // SAFETY (both GEMMs): every stride stays inside `dw` [C_out, C_in], `gs` [len, C_out],
        // `xs` / `dx` [len, C_in] and the tap's columns of `weight` [C_out, 27 C_in].
        unsafe {
            // d W_f [C_out, C_in] (+)= gsᵀ [C_out, len] · xs [len, C_in]
            gemm::gemm(
                c_out,
                c_in,
                len,
                dw.as_mut_ptr(),
                1,
                c_in as isize,
                b > 0,
                gs.as_ptr(),
                c_out as isize,
                1,
                xs.as_ptr(),
                1,
                c_in as isize,
                1.0f32,
                1.0f32,
                false,
                false,
                false,
                gemm::Parallelism::None,
            );
            // dx [len, C_in] = gs [len, C_out] · W_f [C_out, C_in]
            gemm::gemm(
                len,
                c_in,
                c_out,
                dx.as_mut_ptr(),
                1,
                c_in as isize,
                false,
                gs.as_ptr(),
                1,
                c_out as isize,
                w_f,
                1,
                (NUM_TAPS * c_in) as isize,
                0.0f32,
                1.0f32,
                false,
                false,
                false,
                gemm::Parallelism::None,
            );
        }
        for (p, &s) in src.iter().enumerate() {
            for (a, v) in acc[s * c_in..(s + 1) * c_in]
                .iter_mut()
                .zip(&dx[p * c_in..(p + 1) * c_in])
            {
                *a += v;
            }
        }
    }
    dw
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The conv in f64 from the tables: `out[target] += W_f x_ext[source]`, plus the bias.
    fn conv64(
        x: &[f64],
        weight: &[f64],
        bias: &[f64],
        c_in: usize,
        c_out: usize,
        t: &HostConvTables,
    ) -> Vec<f64> {
        let n = t.num_tokens;
        let mut x_ext = x.to_vec();
        x_ext.resize((n + t.num_groups) * c_in, 0.0);
        for &(m, grp) in &t.group_entries {
            for i in 0..c_in {
                x_ext[(n + grp) * c_in + i] += x[m * c_in + i];
            }
        }
        let mut out: Vec<f64> = (0..n).flat_map(|_| bias.iter().copied()).collect();
        for (tap, source, target) in &t.taps {
            for (&s, &r) in source.iter().zip(target) {
                for o in 0..c_out {
                    out[r * c_out + o] += (0..c_in)
                        .map(|i| weight[o * NUM_TAPS * c_in + tap * c_in + i] * x_ext[s * c_in + i])
                        .sum::<f64>();
                }
            }
        }
        out
    }

    fn pseudo_random(n: usize, seed: u64) -> Vec<f32> {
        crate::host_attention::tests::pseudo_random(n, seed)
    }

    /// Tables with a duplicate group, a full tap, a sparse tap and a tap reading the group row.
    fn tables(n: usize) -> HostConvTables {
        let full: Vec<usize> = (0..n).collect();
        let sparse_src: Vec<usize> = (1..n).step_by(2).collect();
        let sparse_tgt: Vec<usize> = (0..n - 1).step_by(2).collect();
        HostConvTables {
            num_tokens: n,
            num_groups: 1,
            group_entries: vec![(0, 0), (2, 0)],
            taps: vec![
                (13, full.clone(), full),
                (4, sparse_src, sparse_tgt),
                (26, vec![n, 1], vec![1, 3]),
            ],
        }
    }

    /// Every gradient against central finite differences of `Σ g ∘ conv` in f64.
    #[test]
    fn matches_finite_differences() {
        let (n, c_in, c_out) = (7, 3, 2);
        let t = tables(n);
        let x = pseudo_random(n * c_in, 1);
        let w = pseudo_random(c_out * NUM_TAPS * c_in, 2);
        let b = pseudo_random(c_out, 3);
        let g = pseudo_random(n * c_out, 4);
        let got = subm_conv_backward(&x, &g, &w, c_in, c_out, &t).expect("lengths match");
        let f64s = |v: &[f32]| v.iter().map(|&a| f64::from(a)).collect::<Vec<f64>>();
        let objective = |x: &[f64], w: &[f64], b: &[f64]| {
            conv64(x, w, b, c_in, c_out, &t)
                .iter()
                .zip(&g)
                .map(|(o, &gg)| o * f64::from(gg))
                .sum::<f64>()
        };
        let eps = 1e-6;
        let check = |which: usize, want_len: usize, got: &[f32]| {
            assert_eq!(got.len(), want_len);
            for k in 0..want_len {
                let (mut xp, mut wp, mut bp) = (f64s(&x), f64s(&w), f64s(&b));
                let (mut xm, mut wm, mut bm) = (xp.clone(), wp.clone(), bp.clone());
                match which {
                    0 => {
                        xp[k] += eps;
                        xm[k] -= eps;
                    }
                    1 => {
                        wp[k] += eps;
                        wm[k] -= eps;
                    }
                    _ => {
                        bp[k] += eps;
                        bm[k] -= eps;
                    }
                }
                let fd = (objective(&xp, &wp, &bp) - objective(&xm, &wm, &bm)) / (2.0 * eps);
                assert!(
                    (fd - f64::from(got[k])).abs() <= 1e-4 * fd.abs().max(1.0),
                    "input {which} element {k}: {fd} vs {}",
                    got[k]
                );
            }
        };
        check(0, n * c_in, &got.input);
        check(1, c_out * NUM_TAPS * c_in, &got.weight);
        check(2, c_out, &got.bias);
        // taps without pairs get exactly zero weight gradient
        assert!(got.weight[5 * c_in..6 * c_in].iter().all(|&v| v == 0.0));
    }

    /// Blocks of PAIR_BLOCK pairs accumulate into the same weight gradient.
    #[test]
    fn long_taps_are_blocked_without_changing_the_result() {
        let (n, c_in, c_out) = (PAIR_BLOCK + 37, 2, 3);
        let full: Vec<usize> = (0..n).collect();
        let t = HostConvTables {
            num_tokens: n,
            num_groups: 0,
            group_entries: vec![],
            taps: vec![(13, full.clone(), full)],
        };
        let x = pseudo_random(n * c_in, 5);
        let w = pseudo_random(c_out * NUM_TAPS * c_in, 6);
        let g = pseudo_random(n * c_out, 7);
        let got = subm_conv_backward(&x, &g, &w, c_in, c_out, &t).expect("lengths match");
        for o in 0..c_out {
            for i in 0..c_in {
                let want: f64 = (0..n)
                    .map(|p| f64::from(g[p * c_out + o]) * f64::from(x[p * c_in + i]))
                    .sum();
                let v = f64::from(got.weight[o * NUM_TAPS * c_in + 13 * c_in + i]);
                assert!(
                    (want - v).abs() <= 1e-4 * want.abs().max(1.0),
                    "{want} vs {v}"
                );
            }
        }
    }

    #[test]
    fn mismatched_lengths_are_rejected() {
        let t = tables(5);
        assert!(subm_conv_backward(&[0.0; 14], &[0.0; 10], &[0.0; 2 * 27 * 3], 3, 2, &t).is_none());
        assert!(subm_conv_backward(&[0.0; 15], &[0.0; 10], &[0.0; 5], 3, 2, &t).is_none());
    }
}
