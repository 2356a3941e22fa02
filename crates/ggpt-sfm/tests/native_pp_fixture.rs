//! The `sfm_native_seed3` fixture: the official SfM on a problem with VGGT's native principal
//! point `(w/2, h/2)`, whose official BA moves two observations behind their camera (COLMAP
//! scores those zero). The BA problem, the Ceres path and the whole run, library and binary.
//! The step-by-step checks with the recorded cameras are in `fixture_steps.rs`.
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

mod common;

use std::process::Command;

use common::{Fx, SFM_NATIVE, check_colmap_model, compare_with_ceres, fixture_in, open_set};
use ggpt_sfm::ba::orthonormalize_rotation;
use ggpt_sfm::input::{read_ff, read_matches};
use ggpt_sfm::masks::Preset;
use ggpt_sfm::output::{ColmapExport, write_outputs};
use ggpt_sfm::pipeline::{SfmConfig, SfmOutput, ba_problem, run_sfm_correspondences};

fn config(fx: &Fx) -> SfmConfig {
    let mut cfg = SfmConfig::preset(Preset::Benchmark);
    cfg.thresholds.mintrack_per_view = fx.f64("config/ba_mintrack_per_view")[0] as usize;
    cfg
}

/// The whole SfM stage from the fixture's raw inputs with `cfg` (our BA).
fn run(fx: &Fx, cfg: &SfmConfig) -> (ggpt_sfm::input::FfInput, SfmOutput) {
    let path = fixture_in(SFM_NATIVE, "inputs.safetensors");
    let ff = read_ff(&path).unwrap();
    let m = read_matches(&path, ff.dims).unwrap();
    assert_eq!(ff.dims, fx.dims);
    let out = run_sfm_correspondences(
        &ff.ff,
        &ff.images,
        &m.sets,
        m.rank_scores.as_deref(),
        cfg,
        None,
    )
    .unwrap();
    (ff, out)
}

/// The BA problem our pipeline builds equals the official one exactly: observations (image,
/// point, COLMAP xy), initial points, cameras and camera parameters, for the newest official
/// initialisation (`ba_upstream/*`, principal point + 0.5) and the older one (`ba/*`, + 0.5 on
/// the focal lengths too, `legacy_focal_offset`).
#[test]
fn ba_problem_equals_the_official_one() {
    let fx = open_set(SFM_NATIVE);
    for (prefix, legacy) in [("ba_upstream", false), ("ba", true)] {
        let mut cfg = config(&fx);
        cfg.legacy_focal_offset = legacy;
        let (ff, out) = run(&fx, &cfg);
        let p = ba_problem(&ff.ff, ff.dims, &out.ba_tracks, &cfg);
        let ids = fx.i64(&format!("{prefix}/obs_point3D_id"));
        let imgs = fx.i64(&format!("{prefix}/obs_image_id"));
        let xy = fx.f64(&format!("{prefix}/obs_xy"));
        assert_eq!(p.observations.len(), ids.len(), "{prefix}: observations");
        assert_eq!(p.observations.len(), 334);
        for (i, o) in p.observations.iter().enumerate() {
            assert_eq!(
                (o.view as i64 + 1, o.point as i64 + 1),
                (imgs[i], ids[i]),
                "{prefix}: observation {i}"
            );
            // COLMAP coordinates are ours + 0.5, exactly (the f32 round trip of the official
            // conversion)
            assert_eq!(o.xy.x + 0.5, xy[2 * i], "{prefix}: observation {i} x");
            assert_eq!(o.xy.y + 0.5, xy[2 * i + 1], "{prefix}: observation {i} y");
        }
        let init = fx.f64(&format!("{prefix}/init_points3D"));
        assert_eq!(p.points.len(), 78);
        for (i, q) in p.points.iter().enumerate() {
            assert_eq!(
                [q.x, q.y, q.z],
                init[3 * i..3 * i + 3],
                "{prefix}: point {i}"
            );
        }
        // cameras: the f32 feed-forward extrinsics, whose rotation COLMAP stores as a unit
        // quaternion (our solver does the same round trip, `orthonormalize_rotation`; the two
        // conversions of the non-orthonormal f32 matrix agree to ~1e-9)
        let cams = fx.f64(&format!("{prefix}/init_cam_from_world"));
        for (v, m) in p.cam_from_world.iter().enumerate() {
            let r = orthonormalize_rotation(&m.fixed_view::<3, 3>(0, 0).into_owned());
            for row in 0..3 {
                for c in 0..3 {
                    let d = (r[(row, c)] - cams[12 * v + 4 * row + c]).abs();
                    assert!(
                        d < 1e-8,
                        "{prefix}: camera {v} rotation ({row}, {c}): {d:e}"
                    );
                }
                assert_eq!(
                    m[(row, 3)],
                    cams[12 * v + 4 * row + 3],
                    "{prefix}: camera {v}"
                );
            }
        }
        let params = fx.f64(&format!("{prefix}/init_camera_params"));
        let k = &p.intrinsics[0];
        assert_eq!(
            [k[(0, 0)], k[(1, 1)], k[(0, 2)] + 0.5, k[(1, 2)] + 0.5],
            params[..],
            "{prefix}: camera parameters"
        );
    }
}

/// End to end with our BA (the newest official initialisation): the BA follows Ceres (100
/// iterations, 1e-6), the cameras and DLT points match the official run, and the COLMAP model's
/// observations carry Ceres' reprojection errors.
#[test]
fn end_to_end_with_our_ba_follows_ceres() {
    let fx = open_set(SFM_NATIVE);
    let (ff, out) = run(&fx, &config(&fx));
    let s = &out.summary.ba;
    assert!(s.success, "{}", s.message);
    assert_eq!((s.points, s.observations), (78, 334));
    let ceres = fx.f64("ba_upstream/final_cost")[0];
    let rel = (s.final_cost - ceres).abs() / ceres;
    eprintln!(
        "BA: {} -> {} (Ceres {ceres}, rel {rel:e})",
        s.initial_cost, s.final_cost
    );
    assert!((s.initial_cost - fx.f64("ba_upstream/initial_cost")[0]).abs() < 1e-8 * s.initial_cost);
    assert!(
        rel < 1e-6,
        "100-iteration cost {} vs Ceres {ceres}",
        s.final_cost
    );
    // output cameras: focal within 1e-2 px of the official run's
    let k = &out.result.cameras.intrinsics[0];
    let want_k = fx.f32("ba_upstream/out_intrinsics");
    assert!(
        (k[(0, 0)] - want_k[0] as f64).abs() < 1e-2 && (k[(1, 1)] - want_k[4] as f64).abs() < 1e-2,
        "focal ({}, {}) vs ({}, {})",
        k[(0, 0)],
        k[(1, 1)],
        want_k[0],
        want_k[4]
    );
    // DLT mask and points: the official run's (`scatter/*` were made with the fork's BA
    // cameras, `ba/*`; the upstream cameras differ from them by 2.6e-3 and flip 1 pixel)
    let (diff, errs) = common::dlt_difference(&fx, &out.result.mask, &out.result.points);
    let want_mask = fx.bool("scatter/point_masks");
    eprintln!("DLT mask: {diff} of {} pixels differ", want_mask.len());
    assert!(diff * 100 <= want_mask.len(), "{diff} mask differences");
    let moved = errs.iter().filter(|&&e| e > 5e-3).count();
    eprintln!(
        "DLT points: median difference {:e}, {moved} of {} beyond 5e-3",
        errs[errs.len() / 2],
        errs.len()
    );
    assert!(
        moved * 100 <= errs.len(),
        "{moved} points moved beyond 5e-3"
    );

    // COLMAP model: Ceres' final reprojection error on every written observation
    let dir = tempfile::tempdir().unwrap();
    let cs = write_outputs(dir.path(), &out, &ff.images, &[], &ColmapExport::default()).unwrap();
    let chk = check_colmap_model(&dir.path().join("sparse/0"), false);
    let (de, dp) = compare_with_ceres(&fx, &chk, "ba_upstream");
    eprintln!(
        "COLMAP: {} points, {} observations ({} dropped); max |Δ error| vs Ceres {de:e} px, points {dp:e}",
        cs.points3d, cs.observations, cs.dropped_observations
    );
    assert_eq!(cs.candidates, 78);
}

/// `ggpt-sfm run` on the fixture's raw inputs: the same BA (summary cost = Ceres'), the same
/// problem size, and a COLMAP model whose observations carry Ceres' errors.
#[test]
fn cli_end_to_end() {
    let fx = open_set(SFM_NATIVE);
    let dir = tempfile::tempdir().unwrap();
    let inputs = fixture_in(SFM_NATIVE, "inputs.safetensors");
    let out = Command::new(env!("CARGO_BIN_EXE_ggpt-sfm"))
        .args(["run", "--ff"])
        .arg(&inputs)
        .arg("--matches")
        .arg(&inputs)
        .args([
            "--sfm-preset",
            "benchmark",
            "--mintrack-per-view",
            "48",
            "--no-progress",
            "--out",
        ])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let s: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("summary.json")).unwrap()).unwrap();
    assert_eq!(s["ba"]["points"], 78);
    assert_eq!(s["ba"]["observations"], 334);
    let cost = s["ba"]["final_cost"].as_f64().unwrap();
    let ceres = fx.f64("ba_upstream/final_cost")[0];
    assert!(
        (cost - ceres).abs() < 1e-6 * ceres,
        "ggpt-sfm run BA cost {cost} vs Ceres {ceres}"
    );
    let chk = check_colmap_model(&dir.path().join("sparse/0"), false);
    compare_with_ceres(&fx, &chk, "ba_upstream");
}
