//! Bundle adjustment of the SfM stage (`sfm.md` §7).
//!
//! A hand-written Levenberg–Marquardt solver in f64 (nalgebra) with the Schur complement on the
//! points (`sfm.md` §7.2):
//!
//! * unknowns: every view's pose `cam_from_world = [R | t]` (updated on SE(3) as
//!   `R <- exp([δω]×) R`, `t <- t + δt`), every point, and the focal length(s) (one camera shared by
//!   all views or one per view; `SIMPLE_PINHOLE`: one focal, `PINHOLE`: `fx, fy`); the principal
//!   point is held fixed at the initial intrinsics' (view 0's for a shared camera), as the official
//!   BA keeps the feed-forward principal point (`sfm.md` §7.1);
//! * residual `r = π(K (R X + t)) - u` in pixels, cost `½ Σ ρ(‖r‖²)` (Ceres convention) with the
//!   trivial or the Cauchy loss `ρ(s) = a² log(1 + s/a²)`, minimised by IRLS re-weighting (which is
//!   what Ceres does for the Cauchy loss: its second derivative is negative, so Ceres' Triggs
//!   correction reduces to the square-root weight);
//! * analytic Jacobians, per-point `3x3` blocks eliminated, the reduced camera system solved by a
//!   dense Cholesky factorisation; Jacobian and Schur accumulation are parallelised with rayon;
//! * gauge: view 0's pose and the largest-magnitude component of `t_1` are held constant (a
//!   two-camera gauge); when `t_1 ≈ 0` (pure rotation) the scale is left free and damping keeps it.
//!
//! An observation whose point is not in front of its camera (depth `<` [`PROJECTION_MIN_DEPTH`])
//! costs nothing and has zero Jacobians, at the start and at every later state: COLMAP's
//! reprojection cost, which the official BA minimises (a step may move a point behind a camera
//! that observes it, and back). A problem with no observation in front at the start fails.
//! Points that are not finite or have a coordinate of magnitude `≥` [`MAX_POINT_COORD`] are left
//! out (`sfm.md` §7.1 [project]).
//!
//! Code layout: `layout.rs` (parameter layout, solver state, step updates), `residual.rs`
//! (residuals, analytic Jacobians, cost and linearisation), `schur.rs` (Schur complement, Cholesky
//! solve, back-substitution) and `solver.rs` (the LM loop behind [`bundle_adjust`]).

mod layout;
mod residual;
mod schur;
mod solver;
pub mod synthetic;
#[cfg(test)]
mod tests;

use nalgebra::{Matrix3, Matrix3x4, Point3, Rotation3, UnitQuaternion, Vector2, Vector3};

use crate::error::SfmError;

/// Points with a coordinate of magnitude at least this are not added to the BA (`sfm.md` §7.1,
/// official: `≥ 3000` upper bound; [project]: magnitude, and non-finite points).
pub const MAX_POINT_COORD: f64 = 3000.0;

/// Smallest camera-frame depth `z` of a point for [`project`] and the COLMAP export to project
/// it (same units as the cameras' translations).
pub const MIN_DEPTH: f64 = 1e-8;

/// Smallest camera-frame depth `z` for which the BA's reprojection residual is evaluated:
/// COLMAP's `ImgFromCam` refuses `w < ε` (f64 machine epsilon) and its reprojection cost is then
/// zero, with zero Jacobians (`sfm.md` §7.2). The official BA runs on that cost, so ours does too.
pub const PROJECTION_MIN_DEPTH: f64 = f64::EPSILON;

/// Camera model of the bundle adjustment (`sfm.md` §7.1); serialised as its COLMAP name.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub enum CameraModel {
    /// `fx`, `fy` refined separately (COLMAP `PINHOLE`).
    Pinhole,
    /// One focal `f = fx = fy` (COLMAP `SIMPLE_PINHOLE`), initialised to `(fx + fy) / 2`.
    SimplePinhole,
}

/// Robust loss `ρ(s)` applied to the squared residual norm `s = ‖r‖²` (pixels²).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LossFunction {
    /// `ρ(s) = s`.
    Trivial,
    /// `ρ(s) = a² log(1 + s / a²)` with `a = scale` pixels (GGPT: `a = 0.1`).
    Cauchy {
        /// Scale `a` in pixels (must be positive).
        scale: f64,
    },
}

impl LossFunction {
    /// `(ρ(s), ρ'(s))` for a squared residual norm `s ≥ 0`.
    pub fn evaluate(&self, s: f64) -> (f64, f64) {
        match *self {
            LossFunction::Trivial => (s, 1.0),
            LossFunction::Cauchy { scale } => {
                let b = scale * scale;
                let q = 1.0 + s / b;
                (b * q.ln(), 1.0 / q)
            }
        }
    }
}

/// One observation of a point in a view.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaObservation {
    /// View index into [`BaProblem::cam_from_world`].
    pub view: usize,
    /// Point index into [`BaProblem::points`].
    pub point: usize,
    /// Observed position in ff pixels, pixel-centre convention (top-left pixel centre = (0,0)).
    pub xy: Vector2<f64>,
}

/// A bundle-adjustment problem (`sfm.md` §7.1). Frames: `cam_from_world` maps world points
/// (the feed-forward frame) to OpenCV camera coordinates; pixels are ff pixels, pixel-centre
/// convention.
#[derive(Debug, Clone)]
pub struct BaProblem {
    /// Initial cameras `[R | t]`, `X_cam = R X_world + t`. The rotation may be a slightly
    /// non-orthonormal f32 matrix: it is re-orthonormalised by a unit-quaternion round trip
    /// (as COLMAP stores it).
    pub cam_from_world: Vec<Matrix3x4<f64>>,
    /// Initial intrinsics per view (ff pixels, pixel-centre convention): `fx = K[0,0]`,
    /// `fy = K[1,1]` initialise the focal length(s); the principal point `(K[0,2], K[1,2])` is held
    /// fixed at its initial value (view 0's for a shared camera; `sfm.md` §7.1: the official BA
    /// keeps the feed-forward principal point, e.g. VGGT's `(w/2, h/2)`, and does not re-centre it).
    pub intrinsics: Vec<Matrix3<f64>>,
    /// Initial points (world frame).
    pub points: Vec<Point3<f64>>,
    /// Observations (any order).
    pub observations: Vec<BaObservation>,
    /// Camera model.
    pub model: CameraModel,
    /// One camera (focal) shared by all views, initialised from view 0's intrinsics.
    pub shared_camera: bool,
    /// Refine the focal length(s); otherwise they are held constant.
    pub refine_focal: bool,
    /// Robust loss.
    pub loss: LossFunction,
    /// Image size `(h, w)` in ff pixels: the output intrinsics' principal point is
    /// `((w-1)/2, (h-1)/2)` whatever the BA used (`sfm.md` §7.1 output).
    pub image_size: (usize, usize),
}

/// Damping of the LM normal equations `(JᵀWJ + μ D) δ = -JᵀWr`; `μ` follows Nielsen's rule
/// (divided by `max(1/3, 1 - (2ρ - 1)³)` on accepted steps, multiplied by `ν = 2, 4, 8, ...` on
/// rejected ones).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Damping {
    /// `D = diag(JᵀWJ)` clamped to `[1e-6, 1e32]`, `μ₀ = τ` (Ceres' LM: scale-invariant, so the
    /// focal length (pixels), rotations (radians) and points (scene units) are damped alike).
    Marquardt,
    /// `D = I`, `μ₀ = τ · max diag(JᵀWJ)` (Madsen–Nielsen).
    Levenberg,
}

/// Solver options (`sfm.md` §7.2).
#[derive(Debug, Clone)]
pub struct BaOptions {
    /// Maximum number of LM iterations (accepted or rejected trial steps), default 100.
    pub max_iterations: usize,
    /// Stop when an accepted step decreases the cost by less than this fraction (default 1e-6).
    pub function_tolerance: f64,
    /// Stop when `‖δ‖ ≤ tol (‖x‖ + tol)` (default 1e-8).
    pub parameter_tolerance: f64,
    /// Initial damping factor `τ` (default 1e-4): `μ = τ` with [`Damping::Marquardt`],
    /// `μ = τ · max diag(JᵀWJ)` with [`Damping::Levenberg`].
    pub initial_damping: f64,
    /// How the damping enters the normal equations (default [`Damping::Marquardt`]).
    pub damping: Damping,
    /// Hold view 0's pose and the largest component of `t_1` constant (default true). When false
    /// the gauge is free and only damping holds it (like the official call).
    pub fix_gauge: bool,
    /// Use rayon for the Jacobian / Schur accumulation (default true; small problems run
    /// sequentially anyway).
    pub parallel: bool,
    /// Checked before every LM iteration: a cancelled token ends the solve with
    /// [`SfmError::Cancelled`] (default: never cancelled).
    pub cancel: ggpt_core::Cancel,
}

impl Default for BaOptions {
    fn default() -> Self {
        BaOptions {
            max_iterations: 100,
            function_tolerance: 1e-6,
            parameter_tolerance: 1e-8,
            initial_damping: 1e-4,
            damping: Damping::Marquardt,
            fix_gauge: true,
            parallel: true,
            cancel: ggpt_core::Cancel::default(),
        }
    }
}

impl BaOptions {
    /// The official GGPT call (pycolmap's default bundle adjuster, `sfm.md` §7.1): no gauge fixed,
    /// function and parameter tolerances 0, 100 iterations, Marquardt damping `τ = 1e-4`. With
    /// these options the solver follows Ceres' LM path (the `sfm_small` fixture's 100-iteration
    /// Ceres cost is reproduced to ~1e-9 relative).
    pub fn official() -> Self {
        BaOptions {
            function_tolerance: 0.0,
            parameter_tolerance: 0.0,
            fix_gauge: false,
            ..BaOptions::default()
        }
    }
}

/// Result of [`bundle_adjust`]. On failure (`success == false`) the cameras, intrinsics and
/// points are the initial ones (rotations re-orthonormalised). All values are finite whenever
/// the inputs are.
#[derive(Debug, Clone)]
pub struct BaReport {
    /// Refined cameras `[R | t]` (world -> OpenCV camera), one per view.
    pub cam_from_world: Vec<Matrix3x4<f64>>,
    /// Refined intrinsics per view: `[[fx,0,(w-1)/2],[0,fy,(h-1)/2],[0,0,1]]` (ff pixels,
    /// pixel-centre convention).
    pub intrinsics: Vec<Matrix3<f64>>,
    /// Refined points (world frame); points left out of the problem are returned unchanged.
    pub points: Vec<Point3<f64>>,
    /// Cost `½ Σ ρ(‖r‖²)` at the start (pixels²).
    pub initial_cost: f64,
    /// Cost at the end (equals `initial_cost` on failure).
    pub final_cost: f64,
    /// LM iterations run (accepted and rejected trial steps).
    pub iterations: usize,
    /// Observations that took part (finite data; 0 when the solve did not run).
    pub num_active_observations: usize,
    /// The BA ran and produced usable cameras.
    pub success: bool,
    /// Why the solver stopped, or why it failed.
    pub message: String,
}

/// Re-orthonormalises a (possibly slightly non-orthonormal) rotation matrix through a unit
/// quaternion, as COLMAP does when it stores a `cam_from_world` rotation.
pub fn orthonormalize_rotation(r: &Matrix3<f64>) -> Matrix3<f64> {
    let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(*r));
    // nalgebra does not renormalise the quaternion of a non-orthonormal matrix; COLMAP does.
    UnitQuaternion::new_normalize(q.into_inner())
        .to_rotation_matrix()
        .into_inner()
}

/// Projects a camera-frame point `p` with focal `(fx, fy)` and principal point `(cx, cy)`
/// (pixels, pixel-centre convention). Returns `None` if `p.z ≤ MIN_DEPTH`.
pub fn project(p: &Vector3<f64>, fx: f64, fy: f64, cx: f64, cy: f64) -> Option<Vector2<f64>> {
    if p.z > MIN_DEPTH {
        Some(Vector2::new(fx * p.x / p.z + cx, fy * p.y / p.z + cy))
    } else {
        None
    }
}

/// Bundle-adjusts `problem` (`sfm.md` §7). Cameras are `cam_from_world` (OpenCV), pixels are ff
/// pixels in the pixel-centre convention, the cost is `½ Σ ρ(‖r‖²)` in pixels².
///
/// Returns `Err` only for malformed problems (inconsistent lengths, observation indices out of
/// range, empty image size, invalid loss scale). Degenerate problems (fewer than two views, no
/// usable observation, non-finite cameras, a system that cannot be solved) give `Ok` with
/// `success = false` and the initial cameras.
pub fn bundle_adjust(problem: &BaProblem, options: &BaOptions) -> Result<BaReport, SfmError> {
    validate(problem)?;
    solver::solve(problem, options)
}

fn validate(problem: &BaProblem) -> Result<(), SfmError> {
    let n = problem.cam_from_world.len();
    if problem.intrinsics.len() != n {
        return Err(SfmError::Shape(format!(
            "bundle adjustment: {} cameras but {} intrinsics",
            n,
            problem.intrinsics.len()
        )));
    }
    let (h, w) = problem.image_size;
    if h == 0 || w == 0 {
        return Err(SfmError::Invalid(format!(
            "bundle adjustment: empty image size (h, w) = ({h}, {w})"
        )));
    }
    if let LossFunction::Cauchy { scale } = problem.loss
        && !(scale.is_finite() && scale > 0.0)
    {
        return Err(SfmError::Invalid(format!(
            "bundle adjustment: Cauchy loss scale must be positive, got {scale}"
        )));
    }
    for (i, o) in problem.observations.iter().enumerate() {
        if o.view >= n {
            return Err(SfmError::Shape(format!(
                "bundle adjustment: observation {i} refers to view {} but there are {n} views",
                o.view
            )));
        }
        if o.point >= problem.points.len() {
            return Err(SfmError::Shape(format!(
                "bundle adjustment: observation {i} refers to point {} but there are {} points",
                o.point,
                problem.points.len()
            )));
        }
    }
    Ok(())
}
