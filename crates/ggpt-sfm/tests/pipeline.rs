//! Whole-pipeline tests: the `sfm_small` fixture end to end (recorded BA cameras injected, and
//! with our own BA), the output files, and the bad-input behaviour.
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

mod common;

use common::synth::synth;
use common::{check_colmap_model, fixture, max_abs_diff, open};
use ggpt_core::io::st::StFile;
use ggpt_sfm::input::{read_ff, read_matches};
use ggpt_sfm::masks::Preset;
use ggpt_sfm::output::{ColmapExport, ColmapPoints, write_outputs};
use ggpt_sfm::pipeline::{SfmConfig, run_sfm, run_sfm_correspondences};

fn fixture_config() -> SfmConfig {
    let mut cfg = SfmConfig::preset(Preset::Benchmark);
    cfg.thresholds.mintrack_per_view = 64;
    cfg
}

/// Acceptance: raw inputs -> pipeline with the recorded official BA cameras -> `scatter/*`.
#[test]
fn fixture_end_to_end_with_recorded_cameras() {
    let fx = open();
    let path = fixture("inputs.safetensors");
    let ff = read_ff(&path).unwrap();
    let m = read_matches(&path, ff.dims).unwrap();
    let cams = fx.ba_out_cameras();
    let out = run_sfm_correspondences(
        &ff.ff,
        &ff.images,
        &m.sets,
        m.rank_scores.as_deref(),
        &fixture_config(),
        Some(&cams),
    )
    .unwrap();
    assert_eq!(
        out.selection
            .track_ids()
            .iter()
            .map(|&x| x as i64)
            .collect::<Vec<_>>(),
        fx.i64("tracks/track_ids")
    );
    assert_eq!(out.summary.dlt_tracks, [7782, 7782, 7595, 7415, 7415]);
    assert_eq!(
        out.result.mask,
        fx.bool("scatter/point_masks"),
        "point masks"
    );
    let (d, i) = max_abs_diff(&out.result.points, &fx.f32("scatter/points"));
    assert!(d <= 2e-3, "points: max |Δ| = {d} at {i}");
    assert!(out.result.points_success && out.result.camera_success);

    // output files
    let dir = tempfile::tempdir().unwrap();
    let cs = write_outputs(dir.path(), &out, &ff.images, &[], &ColmapExport::default()).unwrap();
    let st = StFile::open(&dir.path().join("sfm_dlt_outputs.safetensors")).unwrap();
    assert_eq!(
        st.bool_tensor("point_masks").unwrap().data,
        fx.bool("scatter/point_masks")
    );
    assert_eq!(st.f32_tensor("points").unwrap().shape, vec![4, 42, 56, 3]);
    assert_eq!(
        st.f32_tensor("extrinsics").unwrap().data,
        fx.f32("ba/out_extrinsics")
    );
    assert_eq!(
        st.f32_tensor("intrinsics").unwrap().data,
        fx.f32("ba/out_intrinsics")
    );
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["points_kept"], 7794);
    assert_eq!(summary["camera_model"], "PINHOLE"); // the benchmark preset's BA model

    // COLMAP model: the recorded cameras, and the 93 BA tracks (BA skipped: triangulated from
    // their BA observations with those cameras) minus the tracks the 4 px filter empties
    let sparse = dir.path().join("sparse/0");
    let chk = check_colmap_model(&sparse, false);
    let model = &chk.model;
    assert_eq!(model.images.len(), 4);
    assert_eq!(model.cameras.len(), 1);
    let (cams, _) = model.to_cameras(&sparse).unwrap();
    for v in 0..4 {
        let want = fx.ba_out_cameras();
        assert!(
            (cams.intrinsics[v] - want.intrinsics[v]).abs().max() < 1e-5,
            "view {v}: K"
        );
        assert!(
            (cams.cam_from_world[v] - want.cam_from_world[v])
                .abs()
                .max()
                < 1e-5,
            "view {v}: [R|t]"
        );
    }
    assert!(!out.ba_points_refined);
    assert!(!cs.ba_points_refined);
    assert_eq!(cs.candidates, 93);
    assert_eq!(out.ba_points.len(), 93);
    eprintln!(
        "recorded cameras: {:?}; check: {} points, {} observations, max error {}, mean {}",
        cs, chk.points, chk.observations, chk.max_error, chk.mean_error
    );
    assert_eq!(chk.points, cs.points3d);
    assert_eq!(chk.observations, cs.observations);
    assert_eq!(cs.points3d, cs.candidates - cs.dropped_points);
    assert_eq!(
        cs.observations + cs.dropped_observations,
        273,
        "every BA observation is written or counted as dropped"
    );
    assert_eq!(summary["colmap"]["points3d"], cs.points3d);
    assert_eq!(
        (
            cs.points3d,
            cs.observations,
            cs.dropped_points,
            cs.dropped_observations
        ),
        (91, 267, 2, 6)
    );
    assert!(
        chk.max_error <= 4.0 + 1e-9,
        "max reprojection error {}",
        chk.max_error
    );
    assert!(
        chk.mean_error < 1.0,
        "mean reprojection error {}",
        chk.mean_error
    );
    assert_source_colours(&chk.model, &out.ba_tracks.track_ids, &ff.images, 42, 56);

    // --colmap-points dlt: every kept DLT track (the earlier content); none: cameras only
    let d2 = tempfile::tempdir().unwrap();
    let cs = write_outputs(
        d2.path(),
        &out,
        &ff.images,
        &[],
        &ColmapExport {
            points: ColmapPoints::Dlt,
            ..ColmapExport::default()
        },
    )
    .unwrap();
    let chk = check_colmap_model(&d2.path().join("sparse/0"), true);
    assert_eq!((cs.points3d, chk.points), (7415, 7415));
    assert_eq!(cs.observations, chk.observations);
    assert!(chk.max_error < 4.0 * 4.0, "DLT max error {}", chk.max_error);
    let cs = write_outputs(
        d2.path(),
        &out,
        &ff.images,
        &[],
        &ColmapExport {
            points: ColmapPoints::None,
            ..ColmapExport::default()
        },
    )
    .unwrap();
    let chk = check_colmap_model(&d2.path().join("sparse/0"), false);
    assert_eq!(
        (
            cs.points3d,
            chk.points,
            chk.observations,
            chk.model.images.len()
        ),
        (0, 0, 0, 4)
    );
}

/// Every written BA point whose observation in its track's source view is still the source pixel
/// centre (`(x + 0.5, y + 0.5)` in that image) carries the colour of that pixel; at least 90 % of
/// the points are checked this way.
fn assert_source_colours(
    model: &ggpt_core::io::colmap::ColmapModel,
    track_ids: &[usize],
    images: &[f32],
    h: usize,
    w: usize,
) {
    let hw = h * w;
    let mut checked = 0;
    for p in &model.points3d {
        let found = p.track.iter().find_map(|&(iid, idx)| {
            let xy = model.images[iid as usize - 1].points2d[idx as usize].xy;
            let (x, y) = (xy[0] - 0.5, xy[1] - 0.5);
            if x.fract() != 0.0
                || y.fract() != 0.0
                || x < 0.0
                || y < 0.0
                || x >= w as f64
                || y >= h as f64
            {
                return None;
            }
            let j = (iid as usize - 1) * hw + y as usize * w + x as usize;
            track_ids.binary_search(&j).ok().map(|_| j)
        });
        if let Some(j) = found {
            let rgb: Vec<u8> = images[3 * j..3 * j + 3]
                .iter()
                .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
                .collect();
            assert_eq!(
                p.rgb.to_vec(),
                rgb,
                "point {}: colour vs source pixel of track {j}",
                p.id
            );
            checked += 1;
        }
    }
    assert!(
        checked * 10 >= model.points3d.len() * 9,
        "only {checked} of {} points have their source observation",
        model.points3d.len()
    );
}

/// End to end with our BA: cameras differ from the official ones by solver path / gauge, so masks
/// and points are compared with a tolerance.
#[test]
fn fixture_end_to_end_with_our_ba() {
    let fx = open();
    let path = fixture("inputs.safetensors");
    let ff = read_ff(&path).unwrap();
    let m = read_matches(&path, ff.dims).unwrap();
    let out = run_sfm_correspondences(
        &ff.ff,
        &ff.images,
        &m.sets,
        m.rank_scores.as_deref(),
        &fixture_config(),
        None,
    )
    .unwrap();
    let s = &out.summary;
    assert!(s.ba.success, "{}", s.ba.message);
    assert_eq!(s.ba.points, 93);
    assert_eq!(s.ba.observations, 273);
    // focal close to the official refined focal (upstream: [49.5222, 49.8875])
    let k = &out.result.cameras.intrinsics[0];
    eprintln!(
        "ours: fx {} fy {}; cost {} -> {}",
        k[(0, 0)],
        k[(1, 1)],
        s.ba.initial_cost,
        s.ba.final_cost
    );
    assert!((k[(0, 0)] - 49.5222).abs() < 0.1 && (k[(1, 1)] - 49.8875).abs() < 0.1);
    // the two BAs fix the gauge differently: compared after a least-squares similarity
    let (diff, errs) = common::dlt_difference(&fx, &out.result.mask, &out.result.points);
    let want_mask = fx.bool("scatter/point_masks");
    let med = errs[errs.len() / 2];
    eprintln!(
        "our BA: {diff} mask differences of {}, median point difference {med:e}",
        want_mask.len()
    );
    assert!(diff <= want_mask.len() / 50, "{diff} mask differences");
    assert!(med < 5e-3, "median point difference {med}");

    // COLMAP model: the BA-refined points of Ceres' run (`ba_upstream/final_points3D`, same free
    // gauge path) with the BA observations
    assert!(out.ba_points_refined);
    let dir = tempfile::tempdir().unwrap();
    let cs = write_outputs(dir.path(), &out, &ff.images, &[], &ColmapExport::default()).unwrap();
    let chk = check_colmap_model(&dir.path().join("sparse/0"), false);
    assert_eq!(cs.candidates, 93);
    assert_eq!(
        (chk.points, chk.observations),
        (cs.points3d, cs.observations)
    );
    assert_eq!(
        (cs.points3d, cs.observations, cs.dropped_observations),
        (93, 271, 2)
    );
    let (de, dp) = common::compare_with_ceres(&fx, &chk, "ba_upstream");
    eprintln!(
        "our BA: {cs:?}; max |Δ observation error| vs Ceres {de:e} px, max BA point difference after Sim(3) {dp:e} (relative); check max error {} mean {}",
        chk.max_error, chk.mean_error
    );
    assert!(
        chk.max_error <= 4.0 && chk.mean_error < 0.5,
        "{} / {}",
        chk.max_error,
        chk.mean_error
    );
    assert_source_colours(&chk.model, &out.ba_tracks.track_ids, &ff.images, 42, 56);
}

#[test]
fn synthetic_scene_recovers_geometry() {
    let s = synth(3, 24, 32);
    let mut cfg = SfmConfig::preset(Preset::Benchmark);
    cfg.thresholds.mintrack_per_view = 128;
    let out = run_sfm(
        &s.ff,
        &s.images,
        s.dims,
        std::slice::from_ref(&s.matches),
        &cfg,
    )
    .unwrap();
    assert!(out.result.camera_success && out.result.points_success);
    assert_eq!(out.summary.ranking, "shi-tomasi");
    let k = out.result.cameras.intrinsics[0];
    let f_gt = s.gt.intrinsics[0][(0, 0)];
    // DLT points vs the GT point of each pixel after a similarity (the SfM frame is the GT frame
    // only up to the gauge the BA fixes from the perturbed feed-forward cameras)
    // (per track: the DLT point vs the GT point of its source pixel; per-pixel averages mix
    // tracks up to half a pixel apart)
    let kept: Vec<_> = out
        .dlt
        .tracks
        .iter()
        .filter(|t| t.status == ggpt_sfm::dlt::DltStatus::Kept)
        .collect();
    let src: Vec<_> = kept
        .iter()
        .map(|t| nalgebra::Point3::from(t.point))
        .collect();
    let tgt: Vec<_> = kept
        .iter()
        .map(|t| nalgebra::Point3::from(s.gt_points[t.track]))
        .collect();
    let sim = ggpt_core::sim3::umeyama(&src, &tgt).unwrap();
    let mut errs: Vec<f64> = src
        .iter()
        .zip(&tgt)
        .map(|(a, b)| (sim.apply(a) - b).norm())
        .collect();
    errs.sort_by(f64::total_cmp);
    let med = errs[errs.len() / 2];
    eprintln!(
        "synthetic: focal {} (gt {f_gt}, ff {}), {} pixels, median point error {med}",
        k[(0, 0)],
        s.ff.cameras.intrinsics[0][(0, 0)],
        out.summary.points_kept
    );
    assert!(out.summary.points_kept > 500);
    assert!(
        (k[(0, 0)] - f_gt).abs() < 0.01 * f_gt,
        "focal {} vs {f_gt}",
        k[(0, 0)]
    );
    assert!(med < 0.02, "median DLT point error {med}");
    assert!(out.result.points.iter().all(|v| v.is_finite()));
}

/// With the GT cameras injected the DLT points are exact up to the match noise (≤ 0.03 px).
#[test]
fn synthetic_scene_with_gt_cameras_is_exact() {
    let s = synth(3, 24, 32);
    let mut cfg = SfmConfig::preset(Preset::Benchmark);
    cfg.thresholds.mintrack_per_view = 128;
    let sets = [ggpt_sfm::matches::Correspondences::from_match_set(&s.matches, s.dims).unwrap()];
    let out = run_sfm_correspondences(&s.ff, &s.images, &sets, None, &cfg, Some(&s.gt)).unwrap();
    let mut errs: Vec<f64> = out
        .dlt
        .tracks
        .iter()
        .filter(|t| t.status == ggpt_sfm::dlt::DltStatus::Kept)
        .map(|t| {
            (0..3)
                .map(|a| (t.point[a] - s.gt_points[t.track][a]).powi(2))
                .sum::<f64>()
                .sqrt()
        })
        .collect();
    errs.sort_by(f64::total_cmp);
    let med = errs[errs.len() / 2];
    eprintln!(
        "synthetic with GT cameras: {} tracks, median point error {med}, max {}",
        errs.len(),
        errs[errs.len() - 1]
    );
    assert!(errs.len() > 1500);
    assert!(med < 2e-3, "median DLT point error {med}");
}

// Bad inputs (issue acceptance): clear errors or documented fallbacks (docs/sfm.md "Errors and
// fallbacks"), never panics, never NaN outputs.

fn assert_finite(out: &ggpt_sfm::pipeline::SfmOutput) {
    assert!(out.result.cameras.is_finite(), "non-finite cameras");
    assert!(
        out.result.points.iter().all(|v| v.is_finite()),
        "non-finite points"
    );
    assert!(
        out.dlt_reproj.iter().all(|v| v.is_finite()),
        "non-finite dlt_reproj"
    );
}

#[test]
fn bad_input_shape_mismatch_between_matches_and_images() {
    let s = synth(3, 12, 16);
    let cfg = SfmConfig::preset(Preset::Benchmark);
    let mut wrong = s.matches.clone();
    wrong.pred_scores.truncate(10);
    let e = run_sfm(&s.ff, &s.images, s.dims, std::slice::from_ref(&wrong), &cfg).unwrap_err();
    assert!(e.to_string().contains("shape mismatch"), "{e}");
    let mut wrong = s.matches.clone();
    wrong.pred_matches.pop();
    let e = run_sfm(&s.ff, &s.images, s.dims, std::slice::from_ref(&wrong), &cfg).unwrap_err();
    assert!(e.to_string().contains("shape mismatch"), "{e}");
    // images of another size than the matches
    let e = run_sfm(
        &s.ff,
        &s.images[..30],
        s.dims,
        std::slice::from_ref(&s.matches),
        &cfg,
    )
    .unwrap_err();
    assert!(e.to_string().contains("images"), "{e}");
    // matches of a 3-view scene with 4-view feed-forward outputs
    let big = synth(4, 12, 16);
    let e = run_sfm(
        &big.ff,
        &big.images,
        big.dims,
        std::slice::from_ref(&s.matches),
        &cfg,
    )
    .unwrap_err();
    assert!(e.to_string().contains("shape mismatch"), "{e}");
    // files: the fixture's matches read for another resolution / number of views
    let fx_path = fixture("inputs.safetensors");
    let e = read_matches(&fx_path, ggpt_core::Dims { n: 4, h: 42, w: 57 }).unwrap_err();
    assert!(
        e.to_string().contains("sp_scores") && e.to_string().contains("inputs.safetensors"),
        "{e}"
    );
    let e = read_matches(&fx_path, ggpt_core::Dims { n: 3, h: 42, w: 56 }).unwrap_err();
    assert!(e.to_string().contains("N=3"), "{e}");
}

#[test]
fn bad_input_all_zero_scores() {
    let s = synth(3, 12, 16);
    let cfg = SfmConfig::preset(Preset::Benchmark);
    for v in [0.0, f32::NAN, 1e-6] {
        let mut zero = s.matches.clone();
        zero.pred_scores.iter_mut().for_each(|x| *x = v);
        let Err(e) = run_sfm(&s.ff, &s.images, s.dims, std::slice::from_ref(&zero), &cfg) else {
            panic!("score {v}: no error")
        };
        assert!(
            e.to_string().contains("all matcher scores are zero"),
            "score {v}: {e}"
        );
    }
}

#[test]
fn bad_input_view_without_valid_matches() {
    // documented fallback: listed in the summary, no DLT point of its own, finite outputs
    let s = synth(3, 12, 16);
    let cfg = SfmConfig::preset(Preset::Benchmark);
    let mut nov = s.matches.clone();
    let hw = s.dims.hw();
    let n = s.dims.n;
    for t in 0..n {
        for sv in 0..n {
            if t != sv && (t == 2 || sv == 2) {
                let b = (t * n + sv) * hw;
                nov.pred_scores[b..b + hw].iter_mut().for_each(|v| *v = 0.0);
            }
        }
    }
    let out = run_sfm(&s.ff, &s.images, s.dims, std::slice::from_ref(&nov), &cfg).unwrap();
    assert_eq!(out.summary.views_without_matches, vec![2]);
    assert!(out.result.camera_success, "{}", out.summary.ba.message);
    assert!(out.result.mask[2 * hw..3 * hw].iter().all(|&m| !m));
    assert!(out.result.points_success);
    assert_finite(&out);
}

#[test]
fn bad_input_nan_cameras() {
    let s = synth(3, 12, 16);
    let cfg = SfmConfig::preset(Preset::Benchmark);
    let mut ff = s.ff.clone();
    ff.cameras.cam_from_world[1][(0, 3)] = f64::NAN;
    let e = run_sfm(
        &ff,
        &s.images,
        s.dims,
        std::slice::from_ref(&s.matches),
        &cfg,
    )
    .unwrap_err();
    assert!(
        e.to_string().contains("view 1") && e.to_string().contains("non-finite"),
        "{e}"
    );
    let mut ff = s.ff.clone();
    ff.cameras.intrinsics[2][(1, 1)] = f64::INFINITY;
    let e = run_sfm(
        &ff,
        &s.images,
        s.dims,
        std::slice::from_ref(&s.matches),
        &cfg,
    )
    .unwrap_err();
    assert!(e.to_string().contains("view 2"), "{e}");
    let mut ff = s.ff.clone();
    ff.cameras.intrinsics[0][(0, 0)] = 0.0;
    let e = run_sfm(
        &ff,
        &s.images,
        s.dims,
        std::slice::from_ref(&s.matches),
        &cfg,
    )
    .unwrap_err();
    assert!(
        e.to_string().contains("view 0") && e.to_string().contains("positive"),
        "{e}"
    );
    // cameras given to replace the BA
    let mut cams = s.gt.clone();
    cams.cam_from_world[0][(2, 2)] = f64::NAN;
    let sets = [ggpt_sfm::matches::Correspondences::from_match_set(&s.matches, s.dims).unwrap()];
    let e = run_sfm_correspondences(&s.ff, &s.images, &sets, None, &cfg, Some(&cams)).unwrap_err();
    assert!(e.to_string().contains("non-finite"), "{e}");
}

#[test]
fn bad_input_nan_matches_points_and_images_are_skipped() {
    // non-finite match coordinates / scores become invalid entries; non-finite feed-forward
    // points are left out of the BA; a NaN image pixel ranks last: the stage still succeeds
    let s = synth(3, 12, 16);
    let cfg = SfmConfig::preset(Preset::Benchmark);
    let mut m = s.matches.clone();
    let hw = s.dims.hw();
    for k in (0..hw).step_by(7) {
        let i = s.dims.n * hw + k; // t = 1, s = 0
        m.pred_matches[2 * i] = f32::NAN;
        m.pred_scores[2 * s.dims.n * hw + k] = f32::NAN; // t = 2, s = 0
    }
    let mut ff = s.ff.clone();
    for p in (0..s.dims.pixels()).step_by(5) {
        ff.points[3 * p + 1] = f32::NAN;
    }
    let mut images = s.images.clone();
    images[..30].iter_mut().for_each(|v| *v = f32::NAN);
    let out = run_sfm(&ff, &images, s.dims, std::slice::from_ref(&m), &cfg).unwrap();
    assert!(out.result.camera_success, "{}", out.summary.ba.message);
    assert!(out.summary.ba.excluded_points > 0);
    assert!(out.result.points_success);
    assert_finite(&out);
}

#[test]
fn bad_input_single_view() {
    let cfg = SfmConfig::preset(Preset::Benchmark);
    let one = synth(1, 12, 16);
    let e = run_sfm(
        &one.ff,
        &one.images,
        one.dims,
        std::slice::from_ref(&one.matches),
        &cfg,
    )
    .unwrap_err();
    assert!(e.to_string().contains("at least 2 views"), "{e}");
}

/// `--ff` accepts the official `ff_outputs.bin` (torch pickle) with the same content as the
/// fixture's `ff/*` tensors.
#[test]
fn official_ff_outputs_bin_matches_safetensors_input() {
    let bin = fixture("../official_format/synth_room_s0/ff_outputs.bin");
    let a = read_ff(&bin).unwrap();
    let b = read_ff(&fixture("inputs.safetensors")).unwrap();
    assert_eq!(a.dims, b.dims);
    assert_eq!(a.images, b.images);
    assert_eq!(a.ff.points, b.ff.points);
    assert_eq!(a.ff.cameras, b.ff.cameras);
}
