//! Acceptance on procedural scenes of `ggpt-synth` (4, 8, 16 views of the easy regime at small
//! resolution so that the debug build stays fast, and two benchmark-regime scenes at the
//! feed-forward resolution, where its texture-driven matcher failures are meaningful): after the SfM stage the camera AUC@5° is at least the
//! feed-forward cameras', and the DLT points are far more accurate than the feed-forward points
//! (pipeline.md §10 metrics from `ggpt_core::metrics`, the ones `ggpt-eval` reports).
//! The full-resolution numbers are in docs/sfm.md ("Accuracy on synthetic scenes").
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

use ggpt_core::metrics::{EVAL_ALIGN_MAX_ERROR, camera_metrics, point_metrics};
use ggpt_sfm::masks::Preset;
use ggpt_sfm::pipeline::{SfmConfig, run_sfm};
use ggpt_synth::{Regime, SceneKind, SynthConfig, generate};
use rand::SeedableRng;
use rand_pcg::Pcg64;

fn check(kind: SceneKind, views: usize, width: usize, height: usize, seed: u64) {
    check_in(Regime::Easy, kind, views, width, height, seed, (0.3, 1.0));
}

/// `coverage`: the accepted range of the fraction of GT pixels with a DLT point.
fn check_in(
    regime: Regime,
    kind: SceneKind,
    views: usize,
    width: usize,
    height: usize,
    seed: u64,
    coverage: (f64, f64),
) {
    let cfg = SynthConfig {
        kind,
        views,
        width,
        height,
        seed,
        ..SynthConfig::for_regime(regime)
    };
    let scene = generate(&cfg).unwrap().scene;
    let ff = scene.ff.as_ref().unwrap();
    let gt = scene.gt.as_ref().unwrap();
    let out = run_sfm(
        ff,
        &scene.images,
        scene.dims,
        &scene.matches,
        &SfmConfig::preset(Preset::Benchmark),
    )
    .unwrap();
    let r = &out.result;
    assert!(
        r.camera_success,
        "{kind:?} {views} views: BA failed: {}",
        out.summary.ba.message
    );
    assert!(r.points_success);
    let cam_ff = camera_metrics(&ff.cameras, &gt.cameras).unwrap();
    let cam_sfm = camera_metrics(&r.cameras, &gt.cameras).unwrap();
    let mut rng = Pcg64::seed_from_u64(42);
    let pts_ff = point_metrics(
        &ff.points,
        &gt.points,
        &gt.mask,
        None,
        EVAL_ALIGN_MAX_ERROR,
        &mut rng,
    )
    .unwrap()
    .metrics;
    let mut rng = Pcg64::seed_from_u64(42);
    let pts_sfm = point_metrics(
        &r.points,
        &gt.points,
        &gt.mask,
        Some(&r.mask),
        EVAL_ALIGN_MAX_ERROR,
        &mut rng,
    )
    .unwrap()
    .metrics;
    eprintln!(
        "{kind:?} {views} views seed {seed}: camera AUC@5 ff {:.1} -> sfm {:.1} (AUC@1 {:.1} -> {:.1}, FoV err {:.2} -> {:.2} deg); \
         points AUC@1cm ff {:.1} -> sfm {:.1} (AUC@5 {:.1} -> {:.1}, ratio {:.1} %)",
        cam_ff.auc_5,
        cam_sfm.auc_5,
        cam_ff.auc_1,
        cam_sfm.auc_1,
        cam_ff.fov_error_deg,
        cam_sfm.fov_error_deg,
        pts_ff.auc_1,
        pts_sfm.auc_1,
        pts_ff.auc_5,
        pts_sfm.auc_5,
        100.0 * pts_sfm.ratio.unwrap_or(0.0)
    );
    assert!(
        cam_sfm.auc_5 >= cam_ff.auc_5,
        "{kind:?} {views} views: camera AUC@5 {} < ff {}",
        cam_sfm.auc_5,
        cam_ff.auc_5
    );
    assert!(
        cam_sfm.auc_1 >= cam_ff.auc_1,
        "{kind:?} {views} views: camera AUC@1 {} < ff {}",
        cam_sfm.auc_1,
        cam_ff.auc_1
    );
    assert!(
        cam_sfm.fov_error_deg <= cam_ff.fov_error_deg,
        "{kind:?} {views} views: FoV error {} > ff {}",
        cam_sfm.fov_error_deg,
        cam_ff.fov_error_deg
    );
    assert!(
        pts_sfm.auc_1 > pts_ff.auc_1,
        "{kind:?} {views} views: point AUC@1cm {} <= ff {}",
        pts_sfm.auc_1,
        pts_ff.auc_1
    );
    let ratio = pts_sfm.ratio.unwrap_or(0.0);
    assert!(
        ratio > coverage.0 && ratio <= coverage.1,
        "{kind:?} {views} views: {ratio} of the GT pixels have a DLT point, expected {coverage:?}"
    );
}

/// The benchmark regime at the feed-forward resolution: sparse guidance (20-70 % of the pixels),
/// which still improves the cameras and is far more accurate than the feed-forward points.
#[test]
fn benchmark_regime_room_4_views_full_resolution() {
    check_in(
        Regime::Benchmark,
        SceneKind::Room,
        4,
        518,
        392,
        0,
        (0.2, 0.7),
    );
}

#[test]
fn benchmark_regime_object_8_views_full_resolution() {
    check_in(
        Regime::Benchmark,
        SceneKind::Object,
        8,
        518,
        392,
        3,
        (0.2, 0.7),
    );
}

#[test]
fn room_4_views_ba_improves_cameras() {
    check(SceneKind::Room, 4, 112, 84, 1);
}

#[test]
fn room_8_views_ba_improves_cameras() {
    check(SceneKind::Room, 8, 84, 56, 2);
}

#[test]
fn room_16_views_ba_improves_cameras() {
    check(SceneKind::Room, 16, 56, 42, 3);
}

#[test]
fn object_4_views_ba_improves_cameras() {
    check(SceneKind::Object, 4, 84, 56, 4);
}
