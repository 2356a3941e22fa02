//! Tests of the bundle adjuster: the `sfm_small` and `sfm_native_seed3` fixtures (Ceres costs,
//! converged reference cameras), synthetic problems with exact ground truth, degenerate inputs.

use nalgebra::{Matrix3, Matrix3x4, Point3, Vector2, Vector3};
use safetensors::{Dtype, SafeTensors};

use super::synthetic::{SyntheticConfig, generate};
use super::*;

/// The `steps.safetensors` of the SfM fixture `set`.
fn fixture_path(set: &str) -> String {
    format!(
        "{}/../../../shared/fixtures/{set}/steps.safetensors",
        env!("CARGO_MANIFEST_DIR")
    )
}

fn read_f64(st: &SafeTensors<'_>, key: &str) -> (Vec<usize>, Vec<f64>) {
    let t = st
        .tensor(key)
        .unwrap_or_else(|e| panic!("fixture: missing tensor {key}: {e}"));
    assert_eq!(t.dtype(), Dtype::F64, "{key}");
    let v = t
        .data()
        .chunks_exact(8)
        .map(|b| f64::from_le_bytes(b.try_into().unwrap()))
        .collect();
    (t.shape().to_vec(), v)
}

fn read_i64(st: &SafeTensors<'_>, key: &str) -> Vec<i64> {
    let t = st
        .tensor(key)
        .unwrap_or_else(|e| panic!("fixture: missing tensor {key}: {e}"));
    assert_eq!(t.dtype(), Dtype::I64, "{key}");
    t.data()
        .chunks_exact(8)
        .map(|b| i64::from_le_bytes(b.try_into().unwrap()))
        .collect()
}

fn cams_3x4(shape: &[usize], v: &[f64]) -> Vec<Matrix3x4<f64>> {
    assert_eq!(&shape[1..], &[3, 4]);
    v.chunks_exact(12).map(Matrix3x4::from_row_slice).collect()
}

/// The fixture problem of prefix `ba` or `ba_upstream`, in pixel-centre coordinates; the
/// principal point handed to COLMAP must be `pp` (pixel-centre convention) + 0.5.
fn fixture_problem(st: &SafeTensors<'_>, prefix: &str, pp: (f64, f64)) -> BaProblem {
    let (_, params) = read_f64(st, &format!("{prefix}/init_camera_params"));
    let (shape, cams) = read_f64(st, &format!("{prefix}/init_cam_from_world"));
    let (pshape, pts) = read_f64(st, &format!("{prefix}/init_points3D"));
    let (_, xy) = read_f64(st, &format!("{prefix}/obs_xy"));
    let img = read_i64(st, &format!("{prefix}/obs_image_id"));
    let pid = read_i64(st, &format!("{prefix}/obs_point3D_id"));
    assert_eq!(pshape[1], 3);
    let cam_from_world = cams_3x4(&shape, &cams);
    let (h, w) = (42usize, 56usize);
    // COLMAP principal point = pixel-centre principal point + 0.5.
    assert_eq!((params[2] - 0.5, params[3] - 0.5), pp);
    let k = Matrix3::new(
        params[0],
        0.0,
        params[2] - 0.5,
        0.0,
        params[1],
        params[3] - 0.5,
        0.0,
        0.0,
        1.0,
    );
    let observations = (0..img.len())
        .map(|i| BaObservation {
            view: (img[i] - 1) as usize,
            point: (pid[i] - 1) as usize,
            xy: Vector2::new(xy[2 * i] - 0.5, xy[2 * i + 1] - 0.5),
        })
        .collect();
    BaProblem {
        intrinsics: vec![k; cam_from_world.len()],
        cam_from_world,
        points: pts
            .chunks_exact(3)
            .map(|p| Point3::new(p[0], p[1], p[2]))
            .collect(),
        observations,
        model: CameraModel::Pinhole,
        shared_camera: true,
        refine_focal: true,
        loss: LossFunction::Cauchy { scale: 0.1 },
        image_size: (h, w),
    }
}

fn rotation(m: &Matrix3x4<f64>) -> Matrix3<f64> {
    m.fixed_view::<3, 3>(0, 0).into_owned()
}

/// Angle (degrees) between two rotations.
fn rot_angle_deg(a: &Matrix3<f64>, b: &Matrix3<f64>) -> f64 {
    let c = ((a * b.transpose()).trace() - 1.0) / 2.0;
    c.clamp(-1.0, 1.0).acos().to_degrees()
}

/// Largest difference (degrees) of the relative rotations `R_i R_jᵀ` over all view pairs.
fn max_relative_rotation_error(a: &[Matrix3x4<f64>], b: &[Matrix3x4<f64>]) -> f64 {
    let mut worst = 0.0_f64;
    for i in 0..a.len() {
        for j in 0..a.len() {
            if i != j {
                let ra = rotation(&a[i]) * rotation(&a[j]).transpose();
                let rb = rotation(&b[i]) * rotation(&b[j]).transpose();
                worst = worst.max(rot_angle_deg(&ra, &rb));
            }
        }
    }
    worst
}

/// The checks of one fixture BA (`set`, `prefix` = `ba` / `ba_upstream`) whose feed-forward
/// principal point is `pp` (pixel-centre convention); `default_rel` and `default_deg` bound the
/// relative cost difference and the relative rotations of the project's default options, which
/// end in another local minimum (see part 3).
fn check_fixture(set: &str, prefix: &str, pp: (f64, f64), default_rel: f64, default_deg: f64) {
    let path = fixture_path(set);
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("fixture {path} missing: {e}"));
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let problem = fixture_problem(&st, prefix, pp);
    let (_, init_cost) = read_f64(&st, &format!("{prefix}/initial_cost"));
    let (_, final_cost) = read_f64(&st, &format!("{prefix}/final_cost"));
    let (_, ref_cost) = read_f64(&st, &format!("{prefix}/reference_cost"));
    let (_, ref_params) = read_f64(&st, &format!("{prefix}/reference_camera_params"));
    let (shape, ref_cams) = read_f64(&st, &format!("{prefix}/reference_cam_from_world"));
    let ref_cams = cams_3x4(&shape, &ref_cams);

    // 1. The official call (free gauge, no tolerances, 100 iterations) follows Ceres' path.
    let official = bundle_adjust(&problem, &BaOptions::official()).unwrap();
    assert!(official.success, "{}", official.message);
    assert_eq!(official.num_active_observations, problem.observations.len());
    let rel0 = (official.initial_cost - init_cost[0]).abs() / init_cost[0];
    assert!(
        rel0 < 1e-8,
        "{prefix}: initial cost {} vs Ceres {} (rel {rel0:e})",
        official.initial_cost,
        init_cost[0]
    );
    let rel100 = (official.final_cost - final_cost[0]).abs() / final_cost[0];
    eprintln!(
        "{set} {prefix}: 100-iteration cost {} vs Ceres {} (rel {rel100:e})",
        official.final_cost, final_cost[0]
    );
    assert!(
        rel100 < 1e-6,
        "{prefix}: 100-iteration cost {} vs Ceres {} (rel {rel100:e})",
        official.final_cost,
        final_cost[0]
    );

    // 2. Converged (tight tolerance): the converged reference optimum.
    let opts = BaOptions {
        function_tolerance: 1e-10,
        max_iterations: 500,
        ..BaOptions::official()
    };
    let report = bundle_adjust(&problem, &opts).unwrap();
    assert!(report.success, "{}", report.message);
    let rel = (report.final_cost - ref_cost[0]) / ref_cost[0];
    eprintln!(
        "{set} {prefix}: converged cost {} vs reference {} (rel {rel:e}, {} iterations)",
        report.final_cost, ref_cost[0], report.iterations
    );
    assert!(
        rel.abs() < 1e-6,
        "{prefix}: final cost {} vs converged reference {} (rel {rel:e}, {} iterations, {})",
        report.final_cost,
        ref_cost[0],
        report.iterations,
        report.message
    );
    let k = &report.intrinsics[0];
    assert!(
        (k[(0, 0)] - ref_params[0]).abs() < 1e-2,
        "fx {} vs {}",
        k[(0, 0)],
        ref_params[0]
    );
    assert!(
        (k[(1, 1)] - ref_params[1]).abs() < 1e-2,
        "fy {} vs {}",
        k[(1, 1)],
        ref_params[1]
    );
    assert_eq!((k[(0, 2)], k[(1, 2)]), (27.5, 20.5));
    let drot = max_relative_rotation_error(&report.cam_from_world, &ref_cams);
    eprintln!(
        "{set} {prefix}: focal ({}, {}) vs ({}, {}), relative rotations within {drot:e} deg",
        k[(0, 0)],
        k[(1, 1)],
        ref_params[0],
        ref_params[1]
    );
    assert!(
        drot < 1e-2,
        "{prefix}: relative rotations differ by {drot} deg"
    );

    // 3. Project defaults (two-camera gauge, function tolerance 1e-6): view 0 unchanged, a cost
    // within `default_rel` of the reference (the Cauchy(0.1 px) problem has several local minima:
    // with the gauge fixed the LM path ends in a neighbouring one: on `sfm_small` for one 2-view
    // point, +0.1 % and < 0.1 deg; on `sfm_native_seed3` -0.7 %, below the official optimum, and
    // 0.2-0.45 deg: two observations there cross behind their camera on the official path).
    let default = bundle_adjust(&problem, &BaOptions::default()).unwrap();
    assert!(default.success, "{}", default.message);
    assert!((default.initial_cost - official.initial_cost).abs() < 1e-12 * official.initial_cost);
    let reld = (default.final_cost - ref_cost[0]) / ref_cost[0];
    assert!(
        reld.abs() < default_rel,
        "{prefix}: default options final cost {} (rel {reld:e})",
        default.final_cost
    );
    let r0 = orthonormalize_rotation(&rotation(&problem.cam_from_world[0]));
    assert!((rotation(&default.cam_from_world[0]) - r0).amax() < 1e-15);
    assert_eq!(
        default.cam_from_world[0].column(3),
        problem.cam_from_world[0].column(3)
    );
    let drot = max_relative_rotation_error(&default.cam_from_world, &ref_cams);
    assert!(
        drot < default_deg,
        "{prefix}: default options: relative rotations differ by {drot} deg"
    );
}

/// `sfm_small`'s feed-forward principal point: the image centre of its 56 x 42 views.
const CENTRE: (f64, f64) = (27.5, 20.5);
/// `sfm_native_seed3`'s: VGGT's `(w/2, h/2)`.
const VGGT_NATIVE: (f64, f64) = (28.0, 21.0);

#[test]
fn fixture_ba_matches_ceres() {
    check_fixture("sfm_small", "ba", CENTRE, 2e-3, 0.1);
}

#[test]
fn fixture_ba_upstream_matches_ceres() {
    check_fixture("sfm_small", "ba_upstream", CENTRE, 2e-3, 0.1);
}

#[test]
fn native_fixture_ba_matches_ceres() {
    check_fixture("sfm_native_seed3", "ba", VGGT_NATIVE, 1e-2, 0.5);
}

#[test]
fn native_fixture_ba_upstream_matches_ceres() {
    check_fixture("sfm_native_seed3", "ba_upstream", VGGT_NATIVE, 1e-2, 0.5);
}

#[test]
fn loss_values_match_spec_table() {
    // sfm.md §7.1: ||r|| = 0.05 -> 0.0022, 0.1 -> 0.0069, 1 -> 0.0462, 10 -> 0.0921 (rho/... per
    // the spec's table of ρ(s) with a = 0.1), weights 0.8, 0.5, 0.0099, 1e-4.
    let loss = LossFunction::Cauchy { scale: 0.1 };
    for (r, rho, wgt) in [
        (0.05, 0.0022, 0.8),
        (0.1, 0.0069, 0.5),
        (1.0, 0.0462, 0.0099),
        (10.0, 0.0921, 1e-4),
    ] {
        let (v, d) = loss.evaluate(r * r);
        assert!((v - rho).abs() < 1e-4, "rho({r}) = {v}");
        assert!((d - wgt).abs() / wgt < 0.01, "rho'({r}) = {d}");
    }
    assert_eq!(LossFunction::Trivial.evaluate(2.5), (2.5, 1.0));
}

#[test]
fn orthonormalization_of_f32_rotation() {
    let r = nalgebra::Rotation3::from_euler_angles(0.3, -0.2, 0.9).into_inner();
    let r32 = r.map(|x| x as f32 as f64);
    let o = orthonormalize_rotation(&r32);
    assert!((o * o.transpose() - Matrix3::identity()).amax() < 1e-14);
    assert!((o - r32).amax() < 1e-7);
}

/// Solves a synthetic problem with the given model / camera sharing / loss.
fn synthetic(
    cfg: &SyntheticConfig,
    model: CameraModel,
    shared: bool,
    loss: LossFunction,
) -> (SyntheticBa, BaReport) {
    let mut s = generate(cfg);
    s.problem.model = model;
    s.problem.shared_camera = shared;
    s.problem.loss = loss;
    // Cauchy(0.1 px) IRLS converges linearly from a 2 % focal error: allow more iterations.
    let opts = BaOptions {
        max_iterations: 1000,
        function_tolerance: 1e-9,
        ..BaOptions::default()
    };
    let report = bundle_adjust(&s.problem, &opts).unwrap();
    (s, report)
}

use super::synthetic::SyntheticBa;

fn small_cfg(seed: u64) -> SyntheticConfig {
    SyntheticConfig {
        views: 4,
        points: 1000,
        track_length: 4,
        focal_noise: 0.02,
        perturb_first_view: true,
        seed,
        ..Default::default()
    }
}

#[test]
fn synthetic_recovers_ground_truth() {
    // 0.5 px noise with the trivial loss; with the Cauchy loss of scale 0.1 px (all residuals in
    // its outlier regime at 0.5 px) IRLS converges slowly, so that case uses 0.05 px noise.
    for (model, shared, loss, noise) in [
        (CameraModel::Pinhole, true, LossFunction::Trivial, 0.5),
        (CameraModel::SimplePinhole, true, LossFunction::Trivial, 0.5),
        (CameraModel::Pinhole, false, LossFunction::Trivial, 0.5),
        (
            CameraModel::Pinhole,
            true,
            LossFunction::Cauchy { scale: 0.1 },
            0.05,
        ),
    ] {
        let cfg = SyntheticConfig {
            pixel_noise: noise,
            views: 6,
            points: 1500,
            ..small_cfg(7)
        };
        let (s, report) = synthetic(&cfg, model, shared, loss);
        assert!(report.success, "{}", report.message);
        assert!(report.final_cost < report.initial_cost);
        let init_err = max_relative_rotation_error(&s.problem.cam_from_world, &s.gt_cam_from_world);
        let err = max_relative_rotation_error(&report.cam_from_world, &s.gt_cam_from_world);
        assert!(init_err > 0.3, "perturbation too small: {init_err}");
        assert!(
            err < 0.05,
            "{model:?} shared={shared} {loss:?}: rotation error {err} deg ({})",
            report.message
        );
        for k in &report.intrinsics {
            for f in [k[(0, 0)], k[(1, 1)]] {
                let rel = (f - s.gt_focal).abs() / s.gt_focal;
                assert!(
                    rel < 1e-3,
                    "{model:?} shared={shared} {loss:?}: focal {f} vs {} ({rel:e}, {})",
                    s.gt_focal,
                    report.message
                );
            }
            assert_eq!((k[(0, 2)], k[(1, 2)]), (511.5, 383.5));
        }
        // Translation directions (gauge: view 0 fixed, so compare camera-centre directions
        // relative to view 0 after removing the scale).
        let centre = |m: &Matrix3x4<f64>| -(rotation(m).transpose() * m.column(3));
        let c0 = centre(&report.cam_from_world[0]);
        let g0 = centre(&s.gt_cam_from_world[0]);
        for v in 1..report.cam_from_world.len() {
            let a: Vector3<f64> =
                rotation(&report.cam_from_world[0]) * (centre(&report.cam_from_world[v]) - c0);
            let b: Vector3<f64> =
                rotation(&s.gt_cam_from_world[0]) * (centre(&s.gt_cam_from_world[v]) - g0);
            let ang = a.angle(&b).to_degrees();
            assert!(ang < 0.2, "view {v}: baseline direction error {ang} deg");
        }
    }
}

#[test]
fn synthetic_exact_data_reaches_zero_cost() {
    let cfg = SyntheticConfig {
        pixel_noise: 0.0,
        ..small_cfg(3)
    };
    let (s, report) = synthetic(&cfg, CameraModel::Pinhole, true, LossFunction::Trivial);
    assert!(report.success, "{}", report.message);
    assert!(
        report.final_cost < 1e-12 * report.initial_cost.max(1.0),
        "final cost {}",
        report.final_cost
    );
    let err = max_relative_rotation_error(&report.cam_from_world, &s.gt_cam_from_world);
    assert!(err < 1e-4, "rotation error {err}");
}

#[test]
fn free_gauge_also_converges() {
    let mut s = generate(&small_cfg(11));
    s.problem.loss = LossFunction::Trivial;
    let opts = BaOptions {
        fix_gauge: false,
        ..BaOptions::default()
    };
    let free = bundle_adjust(&s.problem, &opts).unwrap();
    let fixed = bundle_adjust(&s.problem, &BaOptions::default()).unwrap();
    assert!(free.success && fixed.success);
    let rel = (free.final_cost - fixed.final_cost).abs() / fixed.final_cost;
    assert!(
        rel < 1e-4,
        "free gauge {} vs fixed {}",
        free.final_cost,
        fixed.final_cost
    );
}

#[test]
fn sequential_and_parallel_agree() {
    let cfg = SyntheticConfig {
        points: 1100,
        track_length: 4,
        ..small_cfg(5)
    };
    let s = generate(&cfg);
    let par = bundle_adjust(&s.problem, &BaOptions::default()).unwrap();
    let seq = bundle_adjust(
        &s.problem,
        &BaOptions {
            parallel: false,
            ..BaOptions::default()
        },
    )
    .unwrap();
    assert!(par.success && seq.success);
    // same chunks, summed in the same order: bit-identical whatever the thread count
    assert_eq!(par.final_cost.to_bits(), seq.final_cost.to_bits());
    assert_eq!(par.cam_from_world, seq.cam_from_world);
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let single = one.install(|| bundle_adjust(&s.problem, &BaOptions::default()).unwrap());
    assert_eq!(single.cam_from_world, par.cam_from_world);
    assert_eq!(single.intrinsics, par.intrinsics);
}

fn assert_initial_kept(problem: &BaProblem, report: &BaReport) {
    assert!(!report.success);
    assert_eq!(report.cam_from_world, problem.cam_from_world);
    assert_eq!(report.intrinsics, problem.intrinsics);
    assert!(report.initial_cost.is_finite() && report.final_cost.is_finite());
    assert!(!report.message.is_empty());
}

#[test]
fn no_observations_fails_and_keeps_cameras() {
    let mut s = generate(&small_cfg(1));
    s.problem.observations.clear();
    let report = bundle_adjust(&s.problem, &BaOptions::default()).unwrap();
    assert_initial_kept(&s.problem, &report);
}

#[test]
fn single_view_fails_and_keeps_cameras() {
    let mut s = generate(&small_cfg(2));
    s.problem.cam_from_world.truncate(1);
    s.problem.intrinsics.truncate(1);
    s.problem.observations.retain(|o| o.view == 0);
    let report = bundle_adjust(&s.problem, &BaOptions::default()).unwrap();
    assert_initial_kept(&s.problem, &report);
}

#[test]
fn all_points_behind_cameras_fails_without_nan() {
    let mut s = generate(&small_cfg(4));
    for p in &mut s.problem.points {
        p.z = -p.z; // behind every camera (cameras look along +z towards z = 5)
    }
    let report = bundle_adjust(&s.problem, &BaOptions::default()).unwrap();
    assert_initial_kept(&s.problem, &report);
    assert_eq!(report.num_active_observations, 0);
}

#[test]
fn bad_start_stays_finite() {
    // Half of the points behind the cameras, wild focal, large pose errors, NaN point, gross
    // outlier observations: finite output and no increase of the cost.
    let cfg = SyntheticConfig {
        rotation_noise_deg: 10.0,
        translation_noise: 1.0,
        focal_noise: 0.5,
        ..small_cfg(9)
    };
    let mut s = generate(&cfg);
    for (i, p) in s.problem.points.iter_mut().enumerate() {
        if i % 2 == 0 {
            p.z = -p.z;
        }
    }
    s.problem.points[1] = Point3::new(f64::NAN, 0.0, 1.0);
    for (i, o) in s.problem.observations.iter_mut().enumerate() {
        if i % 7 == 0 {
            o.xy = Vector2::new(1e6, -1e6);
        }
    }
    let report = bundle_adjust(&s.problem, &BaOptions::default()).unwrap();
    assert!(report.final_cost <= report.initial_cost);
    assert!(report.final_cost.is_finite());
    assert!(
        report
            .cam_from_world
            .iter()
            .all(|m| m.iter().all(|x| x.is_finite()))
    );
    assert!(
        report
            .intrinsics
            .iter()
            .all(|m| m.iter().all(|x| x.is_finite()))
    );
    assert!(
        report.points[1].x.is_nan(),
        "excluded point returned unchanged"
    );
    assert!(
        report
            .points
            .iter()
            .enumerate()
            .all(|(i, p)| i == 1 || p.iter().all(|x| x.is_finite()))
    );
}

#[test]
fn non_finite_camera_fails() {
    let mut s = generate(&small_cfg(6));
    s.problem.cam_from_world[2][(0, 3)] = f64::NAN;
    let report = bundle_adjust(&s.problem, &BaOptions::default()).unwrap();
    assert!(!report.success);
    assert!(report.initial_cost.is_finite());
}

#[test]
fn malformed_problems_are_errors() {
    let s = generate(&small_cfg(8));
    let mut p = s.problem.clone();
    p.observations[0].view = 99;
    assert!(bundle_adjust(&p, &BaOptions::default()).is_err());
    let mut p = s.problem.clone();
    p.observations[0].point = p.points.len();
    assert!(bundle_adjust(&p, &BaOptions::default()).is_err());
    let mut p = s.problem.clone();
    p.intrinsics.pop();
    assert!(bundle_adjust(&p, &BaOptions::default()).is_err());
    let mut p = s.problem;
    p.loss = LossFunction::Cauchy { scale: 0.0 };
    assert!(bundle_adjust(&p, &BaOptions::default()).is_err());
}

#[test]
fn levenberg_damping_converges() {
    let cfg = SyntheticConfig {
        pixel_noise: 0.0,
        focal_noise: 0.0,
        ..small_cfg(12)
    };
    let mut s = generate(&cfg);
    s.problem.loss = LossFunction::Trivial;
    let opts = BaOptions {
        damping: Damping::Levenberg,
        function_tolerance: 1e-12,
        ..BaOptions::default()
    };
    let report = bundle_adjust(&s.problem, &opts).unwrap();
    assert!(report.success, "{}", report.message);
    assert!(
        report.final_cost < 1e-8 * report.initial_cost,
        "{} -> {}",
        report.initial_cost,
        report.final_cost
    );
    let err = max_relative_rotation_error(&report.cam_from_world, &s.gt_cam_from_world);
    assert!(err < 1e-3, "rotation error {err}");
}
