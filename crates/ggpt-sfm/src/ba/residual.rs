//! Residuals and analytic Jacobians of the bundle adjuster (`sfm.md` §7.2): the reprojection
//! residual of one observation and its camera / point Jacobians, the robust cost of a state, and
//! the IRLS-weighted linearisation (`JᵀWJ`, `JᵀWr`, per-point blocks) accumulated chunk by chunk.
//!
//! The camera block of one observation has `D = 6 + nf` columns (`δω, δt` of its view, then the
//! `nf ∈ {0, 1, 2}` focal parameters of its camera); the code is generic over `D` so that the hot
//! loops work on fixed-size arrays.

use nalgebra::{DMatrix, DVector, Matrix3, Vector2, Vector3};
use rayon::prelude::*;

use super::PROJECTION_MIN_DEPTH;
use super::layout::{Layout, State, cam_indices};

/// One linearisation (Jacobians at the current state), reused for all damping trials.
pub(super) struct Linearization<const D: usize> {
    /// Per observation: `W_oᵀ = J_pᵀ w J_c` (3 x D, rows contiguous for the vectorised Schur loop).
    pub(super) w: Vec<[[f64; D]; 3]>,
    /// Per point: `V_j = Σ J_pᵀ w J_p` and `g_j = Σ J_pᵀ w r`.
    pub(super) v: Vec<Matrix3<f64>>,
    pub(super) gp: Vec<Vector3<f64>>,
    /// Camera block of `JᵀWJ` and gradient (dense, size `nc`).
    pub(super) hcc: DMatrix<f64>,
    pub(super) gc: DVector<f64>,
}

/// Residual, camera Jacobian (2 x D) and point Jacobian (2 x 3) of one observation.
type ObsJacobian<const D: usize> = (Vector2<f64>, [[f64; D]; 2], [[f64; 3]; 2]);

/// Residual and Jacobians of one observation: zero (residual and Jacobians) when the point is
/// not in front of the camera (`z <` [`PROJECTION_MIN_DEPTH`], COLMAP's reprojection cost);
/// `None` when its depth is not a number.
#[inline]
fn residual_jac<const D: usize>(
    l: &Layout,
    s: &State,
    v: usize,
    x: &Vector3<f64>,
    xy: &Vector2<f64>,
) -> Option<ObsJacobian<D>> {
    let r_mat = &s.rot[v];
    let q = r_mat * x;
    let p = q + s.trans[v];
    if p.z.is_nan() {
        return None;
    }
    if p.z < PROJECTION_MIN_DEPTH {
        return Some((Vector2::zeros(), [[0.0; D]; 2], [[0.0; 3]; 2]));
    }
    let [fx, fy] = s.focal[l.cam_of_view[v]];
    let [cx, cy] = l.principal_point[l.cam_of_view[v]];
    let iz = 1.0 / p.z;
    let xn = p.x * iz;
    let yn = p.y * iz;
    let r = Vector2::new(fx * xn + cx - xy.x, fy * yn + cy - xy.y);
    // dr/dp
    let a = [[fx * iz, 0.0, -fx * xn * iz], [0.0, fy * iz, -fy * yn * iz]];
    let mut jc = [[0.0; D]; 2];
    let mut jp = [[0.0; 3]; 2];
    for i in 0..2 {
        let ai = a[i];
        // dp/dω = -[q]x : columns (0, -q.z, q.y)?  -[q]x = [[0, qz, -qy], [-qz, 0, qx], [qy, -qx, 0]]
        jc[i][0] = -ai[1] * q.z + ai[2] * q.y;
        jc[i][1] = ai[0] * q.z - ai[2] * q.x;
        jc[i][2] = -ai[0] * q.y + ai[1] * q.x;
        jc[i][3] = ai[0];
        jc[i][4] = ai[1];
        jc[i][5] = ai[2];
        for b in 0..3 {
            jp[i][b] = ai[0] * r_mat[(0, b)] + ai[1] * r_mat[(1, b)] + ai[2] * r_mat[(2, b)];
        }
    }
    match l.nf {
        1 => {
            jc[0][6] = xn;
            jc[1][6] = yn;
        }
        2 => {
            jc[0][6] = xn;
            jc[1][7] = yn;
        }
        _ => {}
    }
    Some((r, jc, jp))
}

/// Cost `½ Σ ρ(‖r‖²)` of a state (an observation whose point is not in front of its camera costs
/// nothing, as in COLMAP); `None` if a value is not finite.
pub(super) fn evaluate(l: &Layout, s: &State) -> Option<f64> {
    let chunk_cost = |&(a, b): &(usize, usize)| -> Option<f64> {
        let mut cost = 0.0;
        for j in a..b {
            let x = s.points[j];
            for o in l.pt_start[j]..l.pt_start[j + 1] {
                let v = l.obs_view[o];
                let p = s.rot[v] * x + s.trans[v];
                if p.z.is_nan() {
                    return None;
                }
                if p.z < PROJECTION_MIN_DEPTH {
                    continue;
                }
                let [fx, fy] = s.focal[l.cam_of_view[v]];
                let [cx, cy] = l.principal_point[l.cam_of_view[v]];
                let rx = fx * p.x / p.z + cx - l.obs_xy[o].x;
                let ry = fy * p.y / p.z + cy - l.obs_xy[o].y;
                cost += 0.5 * l.loss.evaluate(rx * rx + ry * ry).0;
            }
        }
        cost.is_finite().then_some(cost)
    };
    let parts: Vec<Option<f64>> = if l.parallel {
        l.chunks.par_iter().map(chunk_cost).collect()
    } else {
        l.chunks.iter().map(chunk_cost).collect()
    };
    let mut total = 0.0;
    for p in parts {
        total += p?;
    }
    total.is_finite().then_some(total)
}

/// Partial linearisation of one chunk of points (combined in chunk order).
struct LinChunk<const D: usize> {
    w: Vec<[[f64; D]; 3]>,
    v: Vec<Matrix3<f64>>,
    gp: Vec<Vector3<f64>>,
    hv: Vec<[[f64; D]; D]>,
    gv: Vec<[f64; D]>,
}

/// Linearises the problem at `s`; `None` if a value is not finite.
pub(super) fn linearize<const D: usize>(l: &Layout, s: &State) -> Option<Linearization<D>> {
    let n = l.n_views;
    let chunk_lin = |&(a, b): &(usize, usize)| -> Option<LinChunk<D>> {
        let mut out = LinChunk::<D> {
            w: Vec::with_capacity(l.pt_start[b] - l.pt_start[a]),
            v: Vec::with_capacity(b - a),
            gp: Vec::with_capacity(b - a),
            hv: vec![[[0.0; D]; D]; n],
            gv: vec![[0.0; D]; n],
        };
        for j in a..b {
            let x = s.points[j];
            let mut vj = Matrix3::zeros();
            let mut gj = Vector3::zeros();
            for o in l.pt_start[j]..l.pt_start[j + 1] {
                let view = l.obs_view[o];
                let (r, jc, jp) = residual_jac::<D>(l, s, view, &x, &l.obs_xy[o])?;
                let wgt = l.loss.evaluate(r.norm_squared()).1;
                let mut wo = [[0.0; D]; 3];
                let hv = &mut out.hv[view];
                let gv = &mut out.gv[view];
                for i in 0..2 {
                    let ri = r[i] * wgt;
                    let jci = &jc[i];
                    let jpi = &jp[i];
                    for c in 0..D {
                        let wc = jci[c] * wgt;
                        if wc == 0.0 {
                            continue;
                        }
                        for c2 in c..D {
                            hv[c][c2] += wc * jci[c2];
                        }
                        for b2 in 0..3 {
                            wo[b2][c] += wc * jpi[b2];
                        }
                        gv[c] += jci[c] * ri;
                    }
                    for b1 in 0..3 {
                        let wb = jpi[b1] * wgt;
                        for b2 in b1..3 {
                            vj[(b1, b2)] += wb * jpi[b2];
                        }
                        gj[b1] += jpi[b1] * ri;
                    }
                }
                out.w.push(wo);
            }
            for b1 in 0..3 {
                for b2 in 0..b1 {
                    vj[(b1, b2)] = vj[(b2, b1)];
                }
            }
            out.v.push(vj);
            out.gp.push(gj);
        }
        Some(out)
    };
    let parts: Vec<Option<LinChunk<D>>> = if l.parallel {
        l.chunks.par_iter().map(chunk_lin).collect()
    } else {
        l.chunks.iter().map(chunk_lin).collect()
    };
    let mut lin = Linearization::<D> {
        w: Vec::with_capacity(l.obs_view.len()),
        v: Vec::with_capacity(l.point_ids.len()),
        gp: Vec::with_capacity(l.point_ids.len()),
        hcc: DMatrix::zeros(l.nc, l.nc),
        gc: DVector::zeros(l.nc),
    };
    let mut hv = vec![[[0.0; D]; D]; n];
    let mut gv = vec![[0.0; D]; n];
    for p in parts {
        let p = p?;
        lin.w.extend(p.w);
        lin.v.extend(p.v);
        lin.gp.extend(p.gp);
        for (acc, b) in hv.iter_mut().zip(&p.hv) {
            add_block(acc, b, false);
        }
        for (acc, g) in gv.iter_mut().zip(&p.gv) {
            for (a, x) in acc.iter_mut().zip(g) {
                *a += x;
            }
        }
    }
    for v in 0..n {
        let idx = cam_indices::<D>(l, v);
        for c in 0..D {
            if idx[c] == usize::MAX {
                continue;
            }
            lin.gc[idx[c]] += gv[v][c];
            for c2 in c..D {
                if idx[c2] == usize::MAX {
                    continue;
                }
                let val = hv[v][c][c2];
                lin.hcc[(idx[c], idx[c2])] += val;
                if idx[c] != idx[c2] {
                    lin.hcc[(idx[c2], idx[c])] += val;
                }
            }
        }
    }
    let finite = lin.hcc.iter().all(|x| x.is_finite()) && lin.gc.iter().all(|x| x.is_finite());
    finite.then_some(lin)
}

#[inline]
/// `acc += b` (or `acc += bᵀ` with `transpose`) for `D x D` blocks.
pub(super) fn add_block<const D: usize>(
    acc: &mut [[f64; D]; D],
    b: &[[f64; D]; D],
    transpose: bool,
) {
    for c in 0..D {
        for c2 in 0..D {
            acc[c][c2] += if transpose { b[c2][c] } else { b[c][c2] };
        }
    }
}
