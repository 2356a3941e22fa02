//! Linear solve of the bundle adjuster (`sfm.md` §7.2): the damped normal equations
//! `(JᵀWJ + μ D) δ = -JᵀWr` with the per-point `3x3` blocks eliminated (Schur complement), the
//! reduced camera system solved by a dense Cholesky factorisation, the points recovered by
//! back-substitution, and the model's predicted decrease.

use nalgebra::{Cholesky, DVector, Matrix3, Vector3};
use rayon::prelude::*;

use super::layout::{Layout, Step, cam_indices};
use super::residual::{Linearization, add_block};

/// Lower / upper clamp of the Marquardt scaling `diag(JᵀWJ)` (Ceres' `min/max_lm_diagonal`).
const MIN_LM_DIAGONAL: f64 = 1e-6;
const MAX_LM_DIAGONAL: f64 = 1e32;

/// Marquardt scaling of a diagonal entry.
#[inline]
fn lm_diag(l: &Layout, d: f64) -> f64 {
    if l.marquardt {
        d.clamp(MIN_LM_DIAGONAL, MAX_LM_DIAGONAL)
    } else {
        1.0
    }
}

/// Partial Schur complement of one chunk of points (combined in chunk order).
struct SchurChunk<const D: usize> {
    /// Upper view-pair blocks `(v, v2)`, `v ≤ v2`, flat `v n + v2`.
    blocks: Vec<[[f64; D]; D]>,
    /// Per-view reduced right-hand side contributions.
    rhs: Vec<[f64; D]>,
    /// Inverse damped point blocks `(V_j + μ D_j)⁻¹`.
    vinv: Vec<Matrix3<f64>>,
}

/// Solves the damped normal equations `(JᵀWJ + μ D) δ = -JᵀWr` with the Schur complement.
pub(super) fn damped_step<const D: usize>(
    l: &Layout,
    lin: &Linearization<D>,
    mu: f64,
) -> Option<Step> {
    let n = l.n_views;
    let chunk_schur = |&(a, b): &(usize, usize)| -> Option<SchurChunk<D>> {
        let mut out = SchurChunk::<D> {
            blocks: vec![[[0.0; D]; D]; n * n],
            rhs: vec![[0.0; D]; n],
            vinv: Vec::with_capacity(b - a),
        };
        let mut y: Vec<[[f64; 3]; D]> = Vec::new();
        for j in a..b {
            let mut vd = lin.v[j];
            for k in 0..3 {
                vd[(k, k)] += mu * lm_diag(l, lin.v[j][(k, k)]);
            }
            let vinv = Cholesky::new(vd)?.inverse();
            let g = lin.gp[j];
            let (o0, o1) = (l.pt_start[j], l.pt_start[j + 1]);
            y.clear();
            for o in o0..o1 {
                let w = &lin.w[o];
                let mut yo = [[0.0; 3]; D];
                for c in 0..D {
                    for b2 in 0..3 {
                        yo[c][b2] = w[0][c] * vinv[(0, b2)]
                            + w[1][c] * vinv[(1, b2)]
                            + w[2][c] * vinv[(2, b2)];
                    }
                }
                let rv = &mut out.rhs[l.obs_view[o]];
                for c in 0..D {
                    rv[c] += yo[c][0] * g[0] + yo[c][1] * g[1] + yo[c][2] * g[2];
                }
                y.push(yo);
            }
            for (ia, o) in (o0..o1).enumerate() {
                let va = l.obs_view[o];
                for (ib, o2) in (o..o1).enumerate().map(|(k, o2)| (ia + k, o2)) {
                    let vb = l.obs_view[o2];
                    // Block (va, vb) += Y_a W_bᵀ; stored in the upper block (min, max): when
                    // va > vb use its transpose Y_b W_aᵀ (V⁻¹ is symmetric).
                    if va <= vb {
                        let blk = &mut out.blocks[va * n + vb];
                        acc_product(blk, &y[ia], &lin.w[o2]);
                        if va == vb && ia != ib {
                            acc_product(blk, &y[ib], &lin.w[o]);
                        }
                    } else {
                        acc_product(&mut out.blocks[vb * n + va], &y[ib], &lin.w[o]);
                    }
                }
            }
            out.vinv.push(vinv);
        }
        Some(out)
    };
    let parts: Vec<Option<SchurChunk<D>>> = if l.parallel {
        l.chunks.par_iter().map(chunk_schur).collect()
    } else {
        l.chunks.iter().map(chunk_schur).collect()
    };
    let nc = l.nc;
    let mut s = lin.hcc.clone();
    let mut rhs = -&lin.gc;
    let mut damp = DVector::zeros(nc);
    for i in 0..nc {
        damp[i] = lm_diag(l, lin.hcc[(i, i)]);
        s[(i, i)] += mu * damp[i];
    }
    let mut vinv = Vec::with_capacity(l.point_ids.len());
    let mut blocks = vec![[[0.0; D]; D]; n * n];
    let mut rhs_v = vec![[0.0; D]; n];
    for p in parts {
        let p = p?;
        vinv.extend(p.vinv);
        for (acc, b) in blocks.iter_mut().zip(&p.blocks) {
            add_block(acc, b, false);
        }
        for (acc, r) in rhs_v.iter_mut().zip(&p.rhs) {
            for c in 0..D {
                acc[c] += r[c];
            }
        }
    }
    let idx: Vec<[usize; D]> = (0..n).map(|v| cam_indices::<D>(l, v)).collect();
    for va in 0..n {
        for c in 0..D {
            if idx[va][c] != usize::MAX {
                rhs[idx[va][c]] += rhs_v[va][c];
            }
        }
        for vb in va..n {
            let blk = &blocks[va * n + vb];
            for c in 0..D {
                let i = idx[va][c];
                if i == usize::MAX {
                    continue;
                }
                for c2 in 0..D {
                    let k = idx[vb][c2];
                    if k == usize::MAX {
                        continue;
                    }
                    s[(i, k)] -= blk[c][c2];
                    if va != vb {
                        s[(k, i)] -= blk[c][c2];
                    }
                }
            }
        }
    }
    for &f in &l.fixed {
        for k in 0..nc {
            s[(f, k)] = 0.0;
            s[(k, f)] = 0.0;
        }
        s[(f, f)] = 1.0;
        rhs[f] = 0.0;
    }
    if !s.iter().all(|x| x.is_finite()) || !rhs.iter().all(|x| x.is_finite()) {
        return None;
    }
    let dc = Cholesky::new(s)?.solve(&rhs);
    if !dc.iter().all(|x| x.is_finite()) {
        return None;
    }
    // Back-substitution of the points.
    let back = |&(a, b): &(usize, usize)| -> Vec<Vector3<f64>> {
        (a..b)
            .map(|j| {
                let mut r = -lin.gp[j];
                for o in l.pt_start[j]..l.pt_start[j + 1] {
                    let w = &lin.w[o];
                    let ix = &idx[l.obs_view[o]];
                    for c in 0..D {
                        if ix[c] == usize::MAX {
                            continue;
                        }
                        let d = dc[ix[c]];
                        r[0] -= w[0][c] * d;
                        r[1] -= w[1][c] * d;
                        r[2] -= w[2][c] * d;
                    }
                }
                vinv[j] * r
            })
            .collect()
    };
    let dp: Vec<Vector3<f64>> = if l.parallel {
        l.chunks.par_iter().flat_map_iter(back).collect()
    } else {
        l.chunks.iter().flat_map(back).collect()
    };
    // Predicted decrease ½ (μ δᵀDδ - gᵀδ).
    let mut pred = 0.0;
    for i in 0..nc {
        pred += mu * damp[i] * dc[i] * dc[i] - lin.gc[i] * dc[i];
    }
    for (j, d) in dp.iter().enumerate() {
        for k in 0..3 {
            pred += mu * lm_diag(l, lin.v[j][(k, k)]) * d[k] * d[k] - lin.gp[j][k] * d[k];
        }
    }
    let predicted = 0.5 * pred;
    (predicted.is_finite() && dp.iter().all(|d| d.iter().all(|x| x.is_finite()))).then_some(Step {
        dc,
        dp,
        predicted,
    })
}

/// `acc += Y Wᵀ` for `Y` (D x 3, row-major) and `Wᵀ` (3 x D, row-major): the inner loop runs
/// over contiguous rows so that it vectorises.
#[inline(always)]
fn acc_product<const D: usize>(acc: &mut [[f64; D]; D], y: &[[f64; 3]; D], wt: &[[f64; D]; 3]) {
    for (row, yc) in acc.iter_mut().zip(y) {
        let (y0, y1, y2) = (yc[0], yc[1], yc[2]);
        for c2 in 0..D {
            row[c2] += y0 * wt[0][c2] + y1 * wt[1][c2] + y2 * wt[2][c2];
        }
    }
}
