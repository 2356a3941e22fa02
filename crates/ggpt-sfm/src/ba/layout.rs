//! Problem layout and solver state of the bundle adjuster (`sfm.md` §7.2): the active
//! observations grouped by point, the parameter indexing of the reduced camera system
//! (`6 n_views` pose parameters, then the focal parameters of each camera), the gauge, the work
//! chunks, the current estimate ([`State`]) and how a solved step updates it.

use nalgebra::{DVector, Matrix3, Point3, Rotation3, Vector2, Vector3};

use super::{
    BaOptions, BaProblem, CameraModel, Damping, LossFunction, MAX_POINT_COORD,
    PROJECTION_MIN_DEPTH, orthonormalize_rotation,
};

/// Result of one damped solve ([`super::schur`]), applied by [`apply_step`].
pub(super) struct Step {
    /// Camera parameter step (size `nc`).
    pub(super) dc: DVector<f64>,
    /// Step of each active point.
    pub(super) dp: Vec<Vector3<f64>>,
    /// Predicted decrease of the (IRLS) model.
    pub(super) predicted: f64,
}

/// Observations per work chunk (chunks of whole points). The chunking depends only on the
/// problem, never on the thread count, and partial sums are combined in chunk order: results are
/// identical with any number of threads and with `parallel = false`. Problems of at most this
/// many observations form one chunk and run sequentially (rayon overhead dominates).
const CHUNK_OBSERVATIONS: usize = 4096;
/// `t_1` counts as zero (pure rotation: scale gauge left free) when its largest component is
/// below this fraction of the scene extent.
const PURE_ROTATION_REL: f64 = 1e-9;

/// Static problem layout: the active observations grouped by point.
pub(super) struct Layout {
    /// Number of views.
    pub(super) n_views: usize,
    /// Focal parameters per camera (0, 1 or 2).
    pub(super) nf: usize,
    /// Camera (focal) index of each view.
    pub(super) cam_of_view: Vec<usize>,
    /// Indices (into `BaProblem::points`) of the points that take part.
    pub(super) point_ids: Vec<usize>,
    /// `obs_*[pt_start[j]..pt_start[j+1]]` are the observations of active point `j`.
    pub(super) pt_start: Vec<usize>,
    /// View of each active observation.
    pub(super) obs_view: Vec<usize>,
    /// Observed position of each active observation (ff pixels, pixel-centre convention).
    pub(super) obs_xy: Vec<Vector2<f64>>,
    /// Fixed principal point `(cx, cy)` of each camera (ff pixels, pixel-centre convention): the
    /// initial intrinsics' (view 0's for a shared camera), `sfm.md` §7.1.
    pub(super) principal_point: Vec<[f64; 2]>,
    /// Robust loss of the problem.
    pub(super) loss: LossFunction,
    /// Reduced camera system size: `6 n_views + n_cams nf`.
    pub(super) nc: usize,
    /// Camera parameters held constant (gauge).
    pub(super) fixed: Vec<usize>,
    /// Contiguous point ranges processed by one task.
    pub(super) chunks: Vec<(usize, usize)>,
    /// Process the chunks with rayon (`BaOptions::parallel` and more than one chunk).
    pub(super) parallel: bool,
    /// Marquardt damping ([`Damping::Marquardt`]); otherwise Levenberg.
    pub(super) marquardt: bool,
    /// Active observations whose point is in front of the camera at the start.
    pub(super) in_front: usize,
}

/// Current estimate.
#[derive(Clone)]
pub(super) struct State {
    /// Rotation `R` of each view (`cam_from_world`).
    pub(super) rot: Vec<Matrix3<f64>>,
    /// Translation `t` of each view (`cam_from_world`).
    pub(super) trans: Vec<Vector3<f64>>,
    /// `(fx, fy)` per camera.
    pub(super) focal: Vec<[f64; 2]>,
    /// Active points.
    pub(super) points: Vec<Vector3<f64>>,
}

/// Initial estimate: re-orthonormalised rotations, translations and focal length(s) of the
/// problem; the active points are filled in once the layout is known.
pub(super) fn initial_state(problem: &BaProblem) -> State {
    let rot = problem
        .cam_from_world
        .iter()
        .map(|m| orthonormalize_rotation(&m.fixed_view::<3, 3>(0, 0).into_owned()))
        .collect();
    let trans = problem
        .cam_from_world
        .iter()
        .map(|m| m.column(3).into_owned())
        .collect();
    let focal_of = |k: &Matrix3<f64>| match problem.model {
        CameraModel::Pinhole => [k[(0, 0)], k[(1, 1)]],
        CameraModel::SimplePinhole => {
            let f = ggpt_core::io::colmap::simple_pinhole_focal(k);
            [f, f]
        }
    };
    let focal = if problem.shared_camera {
        problem
            .intrinsics
            .first()
            .map(focal_of)
            .into_iter()
            .collect()
    } else {
        problem.intrinsics.iter().map(focal_of).collect()
    };
    State {
        rot,
        trans,
        focal,
        points: Vec::new(),
    }
}

/// Groups the active observations by point and sets up the parameter layout, gauge and chunks.
pub(super) fn build_layout(problem: &BaProblem, options: &BaOptions, state: &State) -> Layout {
    let n = problem.cam_from_world.len();
    let point_ok = |p: &Point3<f64>| p.iter().all(|c| c.is_finite() && c.abs() < MAX_POINT_COORD);
    // Active observations: usable point, finite observation (in front of the camera or not: one
    // behind costs nothing until a step brings it in front, as in COLMAP).
    let mut per_point: Vec<Vec<(usize, Vector2<f64>)>> = vec![Vec::new(); problem.points.len()];
    let mut in_front = 0;
    for o in &problem.observations {
        let (Some(p), Some(list)) = (problem.points.get(o.point), per_point.get_mut(o.point))
        else {
            continue;
        };
        if !point_ok(p) || !o.xy.iter().all(|c| c.is_finite()) {
            continue;
        }
        let z = state.rot[o.view].row(2).dot(&p.coords.transpose()) + state.trans[o.view].z;
        if z >= PROJECTION_MIN_DEPTH {
            in_front += 1;
        }
        list.push((o.view, o.xy));
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
    let cam_of_view = (0..n)
        .map(|v| if problem.shared_camera { 0 } else { v })
        .collect();
    // Gauge: view 0 and the largest component of t_1 (sfm.md §7.2).
    let mut fixed = Vec::new();
    if options.fix_gauge {
        fixed.extend(0..6);
        let t1 = state.trans[1];
        let extent = scene_extent(problem, &point_ids)
            .max(t1.amax())
            .max(f64::MIN_POSITIVE);
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
        principal_point: problem
            .intrinsics
            .iter()
            .take(n_cams)
            .map(|k| [k[(0, 2)], k[(1, 2)]])
            .collect(),
        loss: problem.loss,
        nc: 6 * n + n_cams * nf,
        fixed,
        parallel: options.parallel && chunks.len() > 1,
        chunks,
        marquardt: options.damping == Damping::Marquardt,
        in_front,
    }
}

/// Mean distance of the active points to their centroid (scale for the pure-rotation test).
fn scene_extent(problem: &BaProblem, ids: &[usize]) -> f64 {
    if ids.is_empty() {
        return 0.0;
    }
    let c = ids
        .iter()
        .map(|&i| problem.points[i].coords)
        .sum::<Vector3<f64>>()
        / ids.len() as f64;
    ids.iter()
        .map(|&i| (problem.points[i].coords - c).norm())
        .sum::<f64>()
        / ids.len() as f64
}

/// Global indices of the `D` camera parameters of view `v` (`usize::MAX`: padding, unused).
pub(super) fn cam_indices<const D: usize>(l: &Layout, v: usize) -> [usize; D] {
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

/// Applies a solved step: `R <- exp([δω]×) R`, `t <- t + δt`, focal(s) and points additively.
pub(super) fn apply_step(l: &Layout, s: &State, step: &Step) -> State {
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

/// Norm of the parameter vector (for the parameter-tolerance test).
pub(super) fn param_norm(s: &State) -> f64 {
    let mut sq = s.rot.len() as f64; // unit quaternions
    sq += s.trans.iter().map(|t| t.norm_squared()).sum::<f64>();
    sq += s
        .focal
        .iter()
        .map(|f| f[0] * f[0] + f[1] * f[1])
        .sum::<f64>();
    sq += s.points.iter().map(|p| p.norm_squared()).sum::<f64>();
    sq.sqrt()
}
