//! The BA keeps the feed-forward principal point (`sfm.md` §7.1): VGGT's `(w/2, h/2)` is used
//! as given, not re-centred. Checked against a hand computation of the BA's initial cost, through
//! the library and through `ggpt-sfm run`, and on GT camera accuracy for both conventions.
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

use std::process::Command;

use ggpt_core::FeedForward;
use ggpt_core::metrics::camera_metrics;
use ggpt_sfm::ba::orthonormalize_rotation;
use ggpt_sfm::masks::Preset;
use ggpt_sfm::pipeline::{SfmConfig, SfmOutput, run_sfm};
use ggpt_sfm::tracks::BaTracks;
use ggpt_synth::{PrincipalPoint, Regime, SceneKind, SynthConfig, generate};
use nalgebra::Vector3;

const BA_CAUCHY_SCALE: f64 = 0.1;

fn scene(
    pp: PrincipalPoint,
    kind: SceneKind,
    views: usize,
    (w, h): (usize, usize),
    seed: u64,
) -> ggpt_core::Scene {
    generate(&SynthConfig {
        kind,
        views,
        width: w,
        height: h,
        seed,
        principal_point: pp,
        // the dense, clean matches of the easy regime: this test is about the principal point,
        // at resolutions too small for the benchmark regime's texture-driven failure modes
        ..SynthConfig::for_regime(Regime::Easy)
    })
    .unwrap()
    .scene
}

fn sfm(s: &ggpt_core::Scene) -> SfmOutput {
    run_sfm(
        s.ff.as_ref().unwrap(),
        &s.images,
        s.dims,
        &s.matches,
        &SfmConfig::preset(Preset::Benchmark),
    )
    .unwrap()
}

/// `½ Σ ρ(‖r‖²)` (Cauchy, a = 0.1 px) of the BA tracks under the feed-forward cameras with the
/// principal point `pp(K_ff)` for every view (shared camera: view 0's focal, PINHOLE), written
/// out independently of the solver: observations `f32(x + 0.5)` in COLMAP's corner convention,
/// principal point `f32(cx + 0.5)`.
fn hand_initial_cost(ff: &FeedForward, tracks: &BaTracks, pp: impl Fn(usize) -> (f64, f64)) -> f64 {
    let k0 = ff.cameras.intrinsics[0];
    let (fx, fy) = (k0[(0, 0)], k0[(1, 1)]);
    let (cx, cy) = pp(0);
    let (cx, cy) = (f64::from(cx as f32 + 0.5), f64::from(cy as f32 + 0.5));
    let a2 = BA_CAUCHY_SCALE * BA_CAUCHY_SCALE;
    let mut cost = 0.0;
    for o in &tracks.observations {
        let m = ff.cameras.cam_from_world[o.view];
        let r = orthonormalize_rotation(&m.fixed_view::<3, 3>(0, 0).into_owned());
        let t: Vector3<f64> = m.column(3).into_owned();
        let p = r * tracks.points[o.point].coords + t;
        if p.z <= 0.0 {
            continue;
        }
        let u = (
            f64::from(o.xy[0] as f32 + 0.5),
            f64::from(o.xy[1] as f32 + 0.5),
        );
        let (rx, ry) = (fx * p.x / p.z + cx - u.0, fy * p.y / p.z + cy - u.1);
        cost += 0.5 * a2 * (1.0 + (rx * rx + ry * ry) / a2).ln();
    }
    cost
}

#[test]
fn ba_initial_cost_uses_the_given_principal_point() {
    let s = scene(PrincipalPoint::Vggt, SceneKind::Room, 4, (112, 84), 5);
    let ff = s.ff.as_ref().unwrap();
    assert_eq!(
        (
            ff.cameras.intrinsics[0][(0, 2)],
            ff.cameras.intrinsics[0][(1, 2)]
        ),
        (56.0, 42.0)
    );
    let out = sfm(&s);
    assert!(out.summary.ba.success, "{}", out.summary.ba.message);
    let given = hand_initial_cost(ff, &out.ba_tracks, |v| {
        (
            ff.cameras.intrinsics[v][(0, 2)],
            ff.cameras.intrinsics[v][(1, 2)],
        )
    });
    let centred = hand_initial_cost(ff, &out.ba_tracks, |_| (55.5, 41.5));
    let got = out.summary.ba.initial_cost;
    eprintln!(
        "BA initial cost: solver {got}, hand (given pp) {given}, hand (re-centred) {centred}"
    );
    assert!(
        (got - given).abs() <= 1e-6 * given,
        "solver {got} vs hand computation {given}"
    );
    assert!(
        (centred - given).abs() > 1e3 * 1e-6 * given,
        "the principal point shift must change the cost: {given} vs {centred}"
    );
    // The output intrinsics reset the principal point to the centre (the DLT uses them).
    for k in &out.result.cameras.intrinsics {
        assert_eq!((k[(0, 2)], k[(1, 2)]), (55.5, 41.5));
    }
}

#[test]
fn shifting_the_principal_point_changes_the_ba_problem() {
    let s = scene(PrincipalPoint::Centre, SceneKind::Room, 4, (112, 84), 5);
    let base = sfm(&s);
    let mut shifted = s.clone();
    for k in &mut shifted.ff.as_mut().unwrap().cameras.intrinsics {
        k[(0, 2)] += 0.5;
        k[(1, 2)] -= 0.5;
    }
    let moved = sfm(&shifted);
    let (a, b) = (&base.summary.ba, &moved.summary.ba);
    assert!(a.success && b.success);
    assert_ne!(a.initial_cost, b.initial_cost);
    assert_ne!(a.final_cost, b.final_cost);
    assert_ne!(
        base.result.cameras.cam_from_world,
        moved.result.cameras.cam_from_world
    );
}

#[test]
fn both_conventions_reach_gt_level_camera_accuracy() {
    for (kind, views, size, seed) in [
        (SceneKind::Room, 4, (112, 84), 1),
        (SceneKind::Room, 8, (84, 56), 2),
        (SceneKind::Object, 4, (84, 56), 4),
    ] {
        for pp in [PrincipalPoint::Vggt, PrincipalPoint::Centre] {
            let s = scene(pp, kind, views, size, seed);
            let ff = s.ff.as_ref().unwrap();
            let gt = s.gt.as_ref().unwrap();
            let out = sfm(&s);
            assert!(
                out.result.camera_success,
                "{kind:?} {pp:?}: {}",
                out.summary.ba.message
            );
            let m_ff = camera_metrics(&ff.cameras, &gt.cameras).unwrap();
            let m = camera_metrics(&out.result.cameras, &gt.cameras).unwrap();
            eprintln!(
                "{kind:?} {views} views {pp:?}: camera AUC@1 {:.1} -> {:.1}, AUC@5 {:.1} -> {:.1}, FoV error {:.3} -> {:.3} deg",
                m_ff.auc_1, m.auc_1, m_ff.auc_5, m.auc_5, m_ff.fov_error_deg, m.fov_error_deg
            );
            assert!(m.auc_5 >= 90.0, "{kind:?} {pp:?}: camera AUC@5 {}", m.auc_5);
            assert!(
                m.auc_1 >= m_ff.auc_1 && m.auc_5 >= m_ff.auc_5,
                "{kind:?} {pp:?}: {m:?} vs ff {m_ff:?}"
            );
            // (At these tiny resolutions VGGT's half-pixel principal-point offset is ~1 % of the
            // image, which the BA partly absorbs in the focal length: the FoV error still improves
            // on the feed-forward one, and the pose AUC reaches 100.)
            assert!(
                m.fov_error_deg <= m_ff.fov_error_deg,
                "{kind:?} {pp:?}: FoV error {} > ff {}",
                m.fov_error_deg,
                m_ff.fov_error_deg
            );
        }
    }
}

/// `ggpt-sfm run` on a VGGT-convention scene directory reports the library's (hand-checked)
/// initial cost in `summary.json`.
#[test]
fn cli_uses_the_given_principal_point() {
    let s = scene(PrincipalPoint::Vggt, SceneKind::Room, 4, (112, 84), 5);
    let tmp = tempfile::tempdir().unwrap();
    let sdir = tmp.path().join("scene");
    ggpt_core::io::scene_dir::write_scene(&sdir, &s).unwrap();
    let read = ggpt_core::io::read_scene(&sdir).unwrap();
    let ff = read.ff.as_ref().unwrap();
    assert_eq!(
        (
            ff.cameras.intrinsics[1][(0, 2)],
            ff.cameras.intrinsics[1][(1, 2)]
        ),
        (56.0, 42.0)
    );
    let out = tmp.path().join("out");
    let o = Command::new(env!("CARGO_BIN_EXE_ggpt-sfm"))
        .args(["run", "--no-progress", "--preset", "benchmark", "--ff"])
        .arg(&sdir)
        .arg("--matches")
        .arg(&sdir)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
    let lib = sfm(&read);
    let hand = hand_initial_cost(ff, &lib.ba_tracks, |v| {
        (
            ff.cameras.intrinsics[v][(0, 2)],
            ff.cameras.intrinsics[v][(1, 2)],
        )
    });
    let cli = summary["ba"]["initial_cost"].as_f64().unwrap();
    assert!(
        (cli - hand).abs() <= 1e-6 * hand,
        "ggpt-sfm run: initial cost {cli}, hand computation {hand}"
    );
}
