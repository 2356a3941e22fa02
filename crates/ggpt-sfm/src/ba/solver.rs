//! Levenberg–Marquardt loop of the bundle adjuster (`sfm.md` §7.2): checks the problem's
//! cameras and intrinsics, builds the layout, dispatches on the camera block size `D = 6 + nf`,
//! and runs the damped trial steps (Nielsen's damping update) until convergence, then writes the
//! report.
//!
//! The other parts live next to it: [`super::layout`] (parameter layout, state, updates),
//! [`super::residual`] (residuals, Jacobians, linearisation) and [`super::schur`] (Schur
//! complement and Cholesky solve).

use nalgebra::{Matrix3, Matrix3x4, Point3};

use super::layout::{Layout, State, apply_step, build_layout, initial_state, param_norm};
use super::residual::{evaluate, linearize};
use super::schur::damped_step;
use super::{BaOptions, BaProblem, BaReport};
use crate::error::SfmError;

/// Damping above which the solver gives up looking for a decrease (relative to the initial
/// damping; Ceres' `max_trust_region_radius` plays the same role).
const MAX_DAMPING_GROWTH: f64 = 1e32;

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
        return Ok(fail(
            format!("bundle adjustment needs at least 2 views, got {n}"),
            0.0,
            0,
        ));
    }
    if let Some(v) = problem
        .cam_from_world
        .iter()
        .position(|m| m.iter().any(|x| !x.is_finite()))
    {
        return Ok(fail(format!("camera {v} is not finite"), 0.0, 0));
    }
    if problem.intrinsics.len() != n {
        return Ok(fail(
            format!("{} intrinsics for {n} views", problem.intrinsics.len()),
            0.0,
            0,
        ));
    }
    let focal_ok = |k: &Matrix3<f64>| {
        k[(0, 0)].is_finite() && k[(1, 1)].is_finite() && k[(0, 0)] > 0.0 && k[(1, 1)] > 0.0
    };
    if let Some(v) = problem.intrinsics.iter().position(|k| !focal_ok(k)) {
        return Ok(fail(
            format!("intrinsics of view {v} have a non-finite or non-positive focal length"),
            0.0,
            0,
        ));
    }
    if let Some(v) = problem
        .intrinsics
        .iter()
        .position(|k| !(k[(0, 2)].is_finite() && k[(1, 2)].is_finite()))
    {
        return Ok(fail(
            format!("intrinsics of view {v} have a non-finite principal point"),
            0.0,
            0,
        ));
    }
    let state = initial_state(problem);
    let layout = build_layout(problem, options, &state);
    let state = State {
        points: layout
            .point_ids
            .iter()
            .map(|&i| problem.points[i].coords)
            .collect(),
        ..state
    };
    let n_active = layout.obs_view.len();
    if layout.in_front == 0 {
        return Ok(fail(
            "no usable observation (none in front of its camera with a finite point)".into(),
            0.0,
            0,
        ));
    }
    let report = match layout.nf {
        0 => run::<6>(problem, options, &layout, state),
        1 => run::<7>(problem, options, &layout, state),
        _ => run::<8>(problem, options, &layout, state),
    };
    match report {
        Ok(r) => Ok(r),
        Err(Stop::Failed(message, cost)) => Ok(fail(message, cost, n_active)),
        Err(Stop::Cancelled) => Err(SfmError::Cancelled),
    }
}

/// Why the LM loop ended without a report.
enum Stop {
    /// The solve failed: message and initial cost.
    Failed(String, f64),
    /// [`BaOptions::cancel`] was cancelled.
    Cancelled,
}

/// The LM loop.
fn run<const D: usize>(
    problem: &BaProblem,
    options: &BaOptions,
    l: &Layout,
    mut state: State,
) -> Result<BaReport, Stop> {
    let Some(initial_cost) = evaluate(l, &state) else {
        return Err(Stop::Failed("initial cost is not finite".into(), 0.0));
    };
    let mut cost = initial_cost;
    let mut lin = linearize::<D>(l, &state).ok_or(Stop::Failed(
        "initial Jacobian is not finite".to_string(),
        initial_cost,
    ))?;
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
    let mut message = format!(
        "maximum number of iterations reached ({})",
        options.max_iterations
    );
    while iterations < options.max_iterations {
        if cost == 0.0 {
            message = "zero cost".into();
            break;
        }
        if options.cancel.is_cancelled() {
            return Err(Stop::Cancelled);
        }
        iterations += 1;
        let accepted = match damped_step::<D>(l, &lin, mu) {
            None => None,
            Some(step) => {
                solved_any = true;
                let step_norm = (step.dc.norm_squared()
                    + step.dp.iter().map(|d| d.norm_squared()).sum::<f64>())
                .sqrt();
                let tol = options.parameter_tolerance;
                if step_norm <= tol * (param_norm(&state) + tol) {
                    message = format!(
                        "converged: step norm {step_norm:.3e} below the parameter tolerance"
                    );
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
        tracing::trace!(
            iteration = iterations,
            cost,
            mu,
            accepted = accepted.is_some(),
            "bundle adjustment"
        );
        match accepted {
            Some((cand, new_cost, rho)) => {
                let rel = (cost - new_cost) / cost;
                state = cand;
                cost = new_cost;
                if rel < options.function_tolerance {
                    message = format!(
                        "converged: relative cost decrease {rel:.3e} below the function tolerance"
                    );
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
        return Err(Stop::Failed(
            format!("the damped normal equations could not be solved ({iterations} iterations)"),
            initial_cost,
        ));
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
