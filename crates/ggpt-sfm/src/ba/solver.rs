//! Levenberg–Marquardt core of the bundle adjuster (`sfm.md` §7.2): analytic Jacobians, IRLS
//! weights, Schur complement on the points, dense Cholesky of the reduced camera system.
//!
//! The camera block of one observation has `D = 6 + nf` columns (`δω, δt` of its view, then the
//! `nf ∈ {0, 1, 2}` focal parameters of its camera); the solver is generic over `D` so that the
//! hot loops work on fixed-size arrays.

use nalgebra::{Cholesky, DMatrix, DVector, Matrix3, Matrix3x4, Point3, Rotation3, Vector2, Vector3};
use rayon::prelude::*;

use super::{
    BaOptions, BaProblem, BaReport, CameraModel, Damping, LossFunction, MAX_POINT_COORD, MIN_DEPTH, orthonormalize_rotation,
};
use crate::error::SfmError;

/// Damping above which the solver gives up looking for a decrease (relative to the initial
/// damping; Ceres' `max_trust_region_radius` plays the same role).
const MAX_DAMPING_GROWTH: f64 = 1e32;
/// Lower / upper clamp of the Marquardt scaling `diag(JᵀWJ)` (Ceres' `min/max_lm_diagonal`).
const MIN_LM_DIAGONAL: f64 = 1e-6;
const MAX_LM_DIAGONAL: f64 = 1e32;
/// Observations per work chunk (chunks of whole points). The chunking depends only on the
/// problem, never on the thread count, and partial sums are combined in chunk order: results are
/// identical with any number of threads and with `parallel = false`. Problems of at most this
/// many observations form one chunk and run sequentially (rayon overhead dominates).
const CHUNK_OBSERVATIONS: usize = 4096;
/// `t_1` counts as zero (pure rotation: scale gauge left free) when its largest component is
/// below this fraction of the scene extent.
const PURE_ROTATION_REL: f64 = 1e-9;

/// Static problem layout: the active observations grouped by point.
struct Layout {
    n_views: usize,
    /// Focal parameters per camera (0, 1 or 2).
    nf: usize,
    /// Camera (focal) index of each view.
    cam_of_view: Vec<usize>,
    /// Indices (into `BaProblem::points`) of the points that take part.
    point_ids: Vec<usize>,
    /// `obs_*[pt_start[j]..pt_start[j+1]]` are the observations of active point `j`.
    pt_start: Vec<usize>,
    obs_view: Vec<usize>,
    obs_xy: Vec<Vector2<f64>>,
    /// Fixed principal point `(cx, cy)` of each camera (ff pixels, pixel-centre convention): the
    /// initial intrinsics' (view 0's for a shared camera), `sfm.md` §7.1.
    principal_point: Vec<[f64; 2]>,
    loss: LossFunction,
    /// Reduced camera system size: `6 n_views + n_cams nf`.
    nc: usize,
    /// Camera parameters held constant (gauge).
    fixed: Vec<usize>,
    /// Contiguous point ranges processed by one task.
    chunks: Vec<(usize, usize)>,
    /// Process the chunks with rayon (`BaOptions::parallel` and more than one chunk).
    parallel: bool,
    marquardt: bool,
}

/// Current estimate.
#[derive(Clone)]
struct State {
    rot: Vec<Matrix3<f64>>,
    trans: Vec<Vector3<f64>>,
    /// `(fx, fy)` per camera.
    focal: Vec<[f64; 2]>,
    /// Active points.
    points: Vec<Vector3<f64>>,
}

/// One linearisation (Jacobians at the current state), reused for all damping trials.
struct Linearization<const D: usize> {
    /// Per observation: `W_oᵀ = J_pᵀ w J_c` (3 x D, rows contiguous for the vectorised Schur loop).
    w: Vec<[[f64; D]; 3]>,
    /// Per point: `V_j = Σ J_pᵀ w J_p` and `g_j = Σ J_pᵀ w r`.
    v: Vec<Matrix3<f64>>,
    gp: Vec<Vector3<f64>>,
    /// Camera block of `JᵀWJ` and gradient (dense, size `nc`).
    hcc: DMatrix<f64>,
    gc: DVector<f64>,
}

/// Result of one damped solve.
struct Step {
    dc: DVector<f64>,
    dp: Vec<Vector3<f64>>,
    /// Predicted decrease of the (IRLS) model.
    predicted: f64,
}

/// Runs the solver on a validated problem.
pub(super) fn solve(problem: &BaProblem, options: &BaOptions) -> Result<BaReport, SfmError> {
    let fail = |message: String, cost: f64, active: usize| BaReport {
        cam_from_world: problem.cam_from_world.clone(),
        intrinsics: problem.intrinsics.clone(),
        points: problem.points.clone(),
        initial_cost: cost,
        final_cost: cost,
        iterations: 0,
        num_active_observations: active,
        success: false,
        message,
    };
    let n = problem.cam_from_world.len();
    if n < 2 {
        return Ok(fail(format!("bundle adjustment needs at least 2 views, got {n}"), 0.0, 0));
    }
    if let Some(v) = problem.cam_from_world.iter().position(|m| m.iter().any(|x| !x.is_finite())) {
        return Ok(fail(format!("camera {v} is not finite"), 0.0, 0));
    }
    if problem.intrinsics.len() != n {
        return Ok(fail(format!("{} intrinsics for {n} views", problem.intrinsics.len()), 0.0, 0));
    }
    let focal_ok = |k: &Matrix3<f64>| k[(0, 0)].is_finite() && k[(1, 1)].is_finite() && k[(0, 0)] > 0.0 && k[(1, 1)] > 0.0;
    if let Some(v) = problem.intrinsics.iter().position(|k| !focal_ok(k)) {
        return Ok(fail(format!("intrinsics of view {v} have a non-finite or non-positive focal length"), 0.0, 0));
    }
    if let Some(v) = problem.intrinsics.iter().position(|k| !(k[(0, 2)].is_finite() && k[(1, 2)].is_finite())) {
        return Ok(fail(format!("intrinsics of view {v} have a non-finite principal point"), 0.0, 0));
    }
    let state = initial_state(problem);
    let layout = build_layout(problem, options, &state);
    let state = State { points: layout.point_ids.iter().map(|&i| problem.points[i].coords).collect(), ..state };
    let n_active = layout.obs_view.len();
    if n_active == 0 {
        return Ok(fail("no usable observation (none in front of its camera with a finite point)".into(), 0.0, 0));
    }
    let report = match layout.nf {
        0 => run::<6>(problem, options, &layout, state),
        1 => run::<7>(problem, options, &layout, state),
        _ => run::<8>(problem, options, &layout, state),
    };
    Ok(match report {
        Ok(r) => r,
        Err((message, cost)) => fail(message, cost, n_active),
    })
}

fn initial_state(problem: &BaProblem) -> State {
    let rot = problem.cam_from_world.iter().map(|m| orthonormalize_rotation(&m.fixed_view::<3, 3>(0, 0).into_owned())).collect();
    let trans = problem.cam_from_world.iter().map(|m| m.column(3).into_owned()).collect();
    let focal_of = |k: &Matrix3<f64>| match problem.model {
        CameraModel::Pinhole => [k[(0, 0)], k[(1, 1)]],
        CameraModel::SimplePinhole => {
            let f = ggpt_core::io::colmap::simple_pinhole_focal(k);
            [f, f]
        }
    };
    let focal = if problem.shared_camera {
        problem.intrinsics.first().map(focal_of).into_iter().collect()
    } else {
        problem.intrinsics.iter().map(focal_of).collect()
    };
    State { rot, trans, focal, points: Vec::new() }
}

fn build_layout(problem: &BaProblem, options: &BaOptions, state: &State) -> Layout {
    let n = problem.cam_from_world.len();
    let point_ok = |p: &Point3<f64>| p.iter().all(|c| c.is_finite() && c.abs() < MAX_POINT_COORD);
    // Active observations: usable point, finite observation, point in front of the camera.
    let mut per_point: Vec<Vec<(usize, Vector2<f64>)>> = vec![Vec::new(); problem.points.len()];
    for o in &problem.observations {
        let (Some(p), Some(list)) = (problem.points.get(o.point), per_point.get_mut(o.point)) else { continue };
        if !point_ok(p) || !o.xy.iter().all(|c| c.is_finite()) {
            continue;
        }
        let z = state.rot[o.view].row(2).dot(&p.coords.transpose()) + state.trans[o.view].z;
        if z > MIN_DEPTH {
            list.push((o.view, o.xy));
        }
    }
    let mut point_ids = Vec::new();
    let mut pt_start = vec![0];
    let mut obs_view = Vec::new();
    let mut obs_xy = Vec::new();
    for (i, list) in per_point.iter().enumerate() {
        if list.is_empty() {
            continue;
        }
        point_ids.push(i);
        for &(v, xy) in list {
            obs_view.push(v);
            obs_xy.push(xy);
        }
        pt_start.push(obs_view.len());
    }
    let nf = if problem.refine_focal {
        match problem.model {
            CameraModel::Pinhole => 2,
            CameraModel::SimplePinhole => 1,
        }
    } else {
        0
    };
    let n_cams = if problem.shared_camera { 1 } else { n };
    let cam_of_view = (0..n).map(|v| if problem.shared_camera { 0 } else { v }).collect();
    // Gauge: view 0 and the largest component of t_1 (sfm.md §7.2).
    let mut fixed = Vec::new();
    if options.fix_gauge {
        fixed.extend(0..6);
        let t1 = state.trans[1];
        let extent = scene_extent(problem, &point_ids).max(t1.amax()).max(f64::MIN_POSITIVE);
        if t1.amax() > PURE_ROTATION_REL * extent {
            fixed.push(6 + 3 + t1.iamax());
        }
    }
    // Chunks of about CHUNK_OBSERVATIONS observations (independent of the thread count).
    let mut chunks = Vec::new();
    let target = CHUNK_OBSERVATIONS;
    let mut start = 0;
    for j in 0..point_ids.len() {
        if pt_start[j + 1] - pt_start[start] >= target || j + 1 == point_ids.len() {
            chunks.push((start, j + 1));
            start = j + 1;
        }
    }
    Layout {
        n_views: n,
        nf,
        cam_of_view,
        point_ids,
        pt_start,
        obs_view,
        obs_xy,
        principal_point: problem.intrinsics.iter().take(n_cams).map(|k| [k[(0, 2)], k[(1, 2)]]).collect(),
        loss: problem.loss,
        nc: 6 * n + n_cams * nf,
        fixed,
        parallel: options.parallel && chunks.len() > 1,
        chunks,
        marquardt: options.damping == Damping::Marquardt,
    }
}

/// Mean distance of the active points to their centroid (scale for the pure-rotation test).
fn scene_extent(problem: &BaProblem, ids: &[usize]) -> f64 {
    if ids.is_empty() {
        return 0.0;
    }
    let c = ids.iter().map(|&i| problem.points[i].coords).sum::<Vector3<f64>>() / ids.len() as f64;
    ids.iter().map(|&i| (problem.points[i].coords - c).norm()).sum::<f64>() / ids.len() as f64
}

/// Global indices of the `D` camera parameters of view `v` (`usize::MAX`: padding, unused).
fn cam_indices<const D: usize>(l: &Layout, v: usize) -> [usize; D] {
    let mut idx = [usize::MAX; D];
    for (k, slot) in idx.iter_mut().enumerate().take(6) {
        *slot = 6 * v + k;
    }
    let base = 6 * l.n_views + l.cam_of_view[v] * l.nf;
    for k in 0..l.nf {
        idx[6 + k] = base + k;
    }
    idx
}

/// Residual, camera Jacobian (2 x D) and point Jacobian (2 x 3) of one observation.
type ObsJacobian<const D: usize> = (Vector2<f64>, [[f64; D]; 2], [[f64; 3]; 2]);

/// Residual and Jacobians of one observation. Returns `None` when the point is not in front.
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
    if p.z <= MIN_DEPTH {
        return None;
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

/// Cost `½ Σ ρ(‖r‖²)` of a state; `None` if an observation is behind its camera or a value is
/// not finite.
fn evaluate(l: &Layout, s: &State) -> Option<f64> {
    let chunk_cost = |&(a, b): &(usize, usize)| -> Option<f64> {
        let mut cost = 0.0;
        for j in a..b {
            let x = s.points[j];
            for o in l.pt_start[j]..l.pt_start[j + 1] {
                let v = l.obs_view[o];
                let p = s.rot[v] * x + s.trans[v];
                if p.z.is_nan() || p.z <= MIN_DEPTH {
                    return None;
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

struct LinChunk<const D: usize> {
    w: Vec<[[f64; D]; 3]>,
    v: Vec<Matrix3<f64>>,
    gp: Vec<Vector3<f64>>,
    hv: Vec<[[f64; D]; D]>,
    gv: Vec<[f64; D]>,
}

fn linearize<const D: usize>(l: &Layout, s: &State) -> Option<Linearization<D>> {
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

/// Marquardt scaling of a diagonal entry.
#[inline]
fn lm_diag(l: &Layout, d: f64) -> f64 {
    if l.marquardt { d.clamp(MIN_LM_DIAGONAL, MAX_LM_DIAGONAL) } else { 1.0 }
}

struct SchurChunk<const D: usize> {
    /// Upper view-pair blocks `(v, v2)`, `v ≤ v2`, flat `v n + v2`.
    blocks: Vec<[[f64; D]; D]>,
    rhs: Vec<[f64; D]>,
    vinv: Vec<Matrix3<f64>>,
}

/// Solves the damped normal equations `(JᵀWJ + μ D) δ = -JᵀWr` with the Schur complement.
fn damped_step<const D: usize>(l: &Layout, lin: &Linearization<D>, mu: f64) -> Option<Step> {
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
                        yo[c][b2] = w[0][c] * vinv[(0, b2)] + w[1][c] * vinv[(1, b2)] + w[2][c] * vinv[(2, b2)];
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
    (predicted.is_finite() && dp.iter().all(|d| d.iter().all(|x| x.is_finite()))).then_some(Step { dc, dp, predicted })
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

#[inline]
fn add_block<const D: usize>(acc: &mut [[f64; D]; D], b: &[[f64; D]; D], transpose: bool) {
    for c in 0..D {
        for c2 in 0..D {
            acc[c][c2] += if transpose { b[c2][c] } else { b[c][c2] };
        }
    }
}

fn apply_step(l: &Layout, s: &State, step: &Step) -> State {
    let mut out = s.clone();
    for v in 0..l.n_views {
        let w = Vector3::new(step.dc[6 * v], step.dc[6 * v + 1], step.dc[6 * v + 2]);
        out.rot[v] = Rotation3::new(w).matrix() * s.rot[v];
        out.trans[v] += Vector3::new(step.dc[6 * v + 3], step.dc[6 * v + 4], step.dc[6 * v + 5]);
    }
    let base = 6 * l.n_views;
    for (c, f) in out.focal.iter_mut().enumerate() {
        match l.nf {
            1 => {
                let d = step.dc[base + c];
                f[0] += d;
                f[1] += d;
            }
            2 => {
                f[0] += step.dc[base + 2 * c];
                f[1] += step.dc[base + 2 * c + 1];
            }
            _ => {}
        }
    }
    for (x, d) in out.points.iter_mut().zip(&step.dp) {
        *x += d;
    }
    out
}

fn param_norm(s: &State) -> f64 {
    let mut sq = s.rot.len() as f64; // unit quaternions
    sq += s.trans.iter().map(|t| t.norm_squared()).sum::<f64>();
    sq += s.focal.iter().map(|f| f[0] * f[0] + f[1] * f[1]).sum::<f64>();
    sq += s.points.iter().map(|p| p.norm_squared()).sum::<f64>();
    sq.sqrt()
}

/// The LM loop. `Err((message, initial_cost))` on failure.
fn run<const D: usize>(
    problem: &BaProblem,
    options: &BaOptions,
    l: &Layout,
    mut state: State,
) -> Result<BaReport, (String, f64)> {
    let Some(initial_cost) = evaluate(l, &state) else {
        return Err(("initial cost is not finite".into(), 0.0));
    };
    let mut cost = initial_cost;
    let mut lin = linearize::<D>(l, &state).ok_or(("initial Jacobian is not finite".to_string(), initial_cost))?;
    let mut mu = if l.marquardt {
        options.initial_damping
    } else {
        let max_diag = (0..l.nc)
            .map(|i| lin.hcc[(i, i)])
            .chain(lin.v.iter().flat_map(|v| [v[(0, 0)], v[(1, 1)], v[(2, 2)]]))
            .fold(0.0_f64, f64::max);
        (options.initial_damping * max_diag).max(f64::MIN_POSITIVE)
    };
    let mu_limit = mu * MAX_DAMPING_GROWTH;
    let mut nu = 2.0;
    let mut iterations = 0;
    let mut solved_any = false;
    let mut message = format!("maximum number of iterations reached ({})", options.max_iterations);
    while iterations < options.max_iterations {
        if cost == 0.0 {
            message = "zero cost".into();
            break;
        }
        iterations += 1;
        let accepted = match damped_step::<D>(l, &lin, mu) {
            None => None,
            Some(step) => {
                solved_any = true;
                let step_norm = (step.dc.norm_squared() + step.dp.iter().map(|d| d.norm_squared()).sum::<f64>()).sqrt();
                let tol = options.parameter_tolerance;
                if step_norm <= tol * (param_norm(&state) + tol) {
                    message = format!("converged: step norm {step_norm:.3e} below the parameter tolerance");
                    break;
                }
                let cand = apply_step(l, &state, &step);
                match evaluate(l, &cand) {
                    Some(new_cost) if step.predicted > 0.0 && new_cost < cost => {
                        Some((cand, new_cost, (cost - new_cost) / step.predicted))
                    }
                    _ => None,
                }
            }
        };
        tracing::trace!(iteration = iterations, cost, mu, accepted = accepted.is_some(), "bundle adjustment");
        match accepted {
            Some((cand, new_cost, rho)) => {
                let rel = (cost - new_cost) / cost;
                state = cand;
                cost = new_cost;
                if rel < options.function_tolerance {
                    message = format!("converged: relative cost decrease {rel:.3e} below the function tolerance");
                    break;
                }
                let Some(new_lin) = linearize::<D>(l, &state) else {
                    // Cannot happen for a finite cost (all depths positive); stop at this state.
                    message = "stopped: Jacobian not finite".into();
                    break;
                };
                lin = new_lin;
                mu *= (1.0 - (2.0 * rho - 1.0).powi(3)).max(1.0 / 3.0);
                nu = 2.0;
            }
            None => {
                mu *= nu;
                nu *= 2.0;
                if mu.is_nan() || mu >= mu_limit {
                    message = "converged: no decrease found (damping limit reached)".into();
                    break;
                }
            }
        }
    }
    if !solved_any {
        return Err((format!("the damped normal equations could not be solved ({iterations} iterations)"), initial_cost));
    }
    // Output.
    let (h, w) = problem.image_size;
    let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    let cam_from_world = (0..l.n_views)
        .map(|v| {
            let mut m = Matrix3x4::zeros();
            m.fixed_view_mut::<3, 3>(0, 0).copy_from(&state.rot[v]);
            m.set_column(3, &state.trans[v]);
            m
        })
        .collect();
    let intrinsics = (0..l.n_views)
        .map(|v| {
            let [fx, fy] = state.focal[l.cam_of_view[v]];
            Matrix3::new(fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0)
        })
        .collect();
    let mut points = problem.points.clone();
    for (&i, x) in l.point_ids.iter().zip(&state.points) {
        points[i] = Point3::from(*x);
    }
    Ok(BaReport {
        cam_from_world,
        intrinsics,
        points,
        initial_cost,
        final_cost: cost,
        iterations,
        num_active_observations: l.obs_view.len(),
        success: true,
        message,
    })
}
