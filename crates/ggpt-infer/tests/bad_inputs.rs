//! `ggpt-infer run` on bad inputs, through the command line: every case stops with a non-zero
//! exit and a message naming the file / the problem (no panic), and the empty-guidance scene
//! follows its documented behaviour (error, or the unrefined points with `--allow-unrefined`).
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use ggpt_core::io::infer_folder::write_infer_folder;
use ggpt_core::io::npy::{NpyArray, NpyData, read_npz, write_npz};
use ggpt_core::{Scene, SfmResult};

struct Fixture {
    dir: tempfile::TempDir,
    weights: PathBuf,
    scene: Scene,
}

/// A tiny random-init network and a 3-view 56 x 42 synthetic scene with matches and SfM.
fn fixture() -> Fixture {
    let dir = tempfile::tempdir().expect("tempdir");
    let weights = dir.path().join("tiny.bpk");
    common::save_tiny_weights(&weights);
    Fixture {
        dir,
        weights,
        scene: common::tiny_scene(5),
    }
}

fn run(scene: &Path, weights: &Path, out: &Path, extra: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_ggpt-infer"))
        .args(["run", "--scene"])
        .arg(scene)
        .arg("--weights")
        .arg(weights)
        .args([
            "--preset",
            "tiny",
            "--device",
            "ndarray",
            "--quiet",
            "--no-error-maps",
            "--out",
        ])
        .arg(out)
        .args(extra)
        .env("NO_COLOR", "1")
        .output()
        .expect("runs")
}

/// Fails with a message containing every one of `needles`, without a panic.
fn assert_fails_with(o: &Output, needles: &[&str]) -> String {
    let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(
        !o.status.success(),
        "expected a failure, got success: {stderr}"
    );
    assert!(
        !stderr.contains("panicked"),
        "panic instead of an error: {stderr}"
    );
    for n in needles {
        assert!(stderr.contains(n), "message lacks {n:?}: {stderr}");
    }
    stderr
}

/// An SfM result that puts a DLT point on every `every`-th pixel (the feed-forward point), on
/// the feed-forward cameras; `every = 0` gives none (empty guidance).
fn sfm_on_ff(scene: &Scene, every: usize) -> SfmResult {
    let ff = scene.ff.as_ref().unwrap();
    let n_pix = scene.dims.n * scene.dims.hw();
    let mask: Vec<bool> = (0..n_pix).map(|i| every > 0 && i % every == 0).collect();
    let points = (0..3 * n_pix)
        .map(|j| if mask[j / 3] { ff.points[j] } else { 0.0 })
        .collect();
    SfmResult {
        points,
        mask,
        cameras: ff.cameras.clone(),
        camera_success: true,
        points_success: every > 0,
    }
}

/// A §5.1 folder of `scene` (feed-forward, SfM when present, matches when present).
fn folder(f: &Fixture, name: &str, scene: &Scene) -> PathBuf {
    let d = f.dir.path().join(name);
    write_infer_folder(&d, scene).unwrap();
    d
}

#[test]
fn missing_scene_and_missing_weights_are_named() {
    let f = fixture();
    let out = f.dir.path().join("out");
    let nowhere = f.dir.path().join("no-such-scene");
    assert_fails_with(&run(&nowhere, &f.weights, &out, &[]), &["no-such-scene"]);
    let scene = folder(&f, "scene", &f.scene);
    let no_weights = f.dir.path().join("missing.safetensors");
    assert_fails_with(
        &run(&scene, &no_weights, &out, &[]),
        &["weights", "missing.safetensors"],
    );
    assert!(!out.join("refined.safetensors").exists());
}

#[test]
fn scene_without_sfm_or_matches_is_rejected() {
    let f = fixture();
    let mut s = f.scene.clone();
    s.matches.clear();
    s.sfm = None;
    let scene = folder(&f, "bare", &s);
    assert_fails_with(
        &run(&scene, &f.weights, &f.dir.path().join("out"), &[]),
        &["bare", "neither sfm.npz / sfm_dlt_outputs.bin nor matches"],
    );
}

#[test]
fn nan_feed_forward_points_are_rejected_naming_the_file() {
    let f = fixture();
    let scene = folder(&f, "nan", &f.scene);
    let npz = scene.join("ff.npz");
    let mut arrays = read_npz(&npz).unwrap();
    let points = arrays.get_mut("points").unwrap();
    let mut v = points.to_f32().unwrap();
    v[3 * 17 + 1] = f32::NAN;
    *points = NpyArray::new(points.shape.clone(), NpyData::F32(v)).unwrap();
    let list: Vec<(&str, &NpyArray)> = arrays.iter().map(|(k, a)| (k.as_str(), a)).collect();
    write_npz(&npz, &list, false).unwrap();
    let e = assert_fails_with(
        &run(&scene, &f.weights, &f.dir.path().join("out"), &[]),
        &["ff.npz"],
    );
    assert!(e.contains("NaN") || e.contains("finite"), "{e}");
}

#[test]
fn sfm_with_another_view_count_is_rejected() {
    let f = fixture();
    let mut s = f.scene.clone();
    s.sfm = Some(sfm_on_ff(&s, 7));
    let scene = folder(&f, "mismatch", &s);
    let npz = scene.join("sfm.npz");
    let mut arrays = read_npz(&npz).unwrap();
    // Keep the first two of the three views in every per-view SfM array.
    for key in ["cam_from_world", "K", "points", "mask"] {
        let a = arrays.get_mut(key).unwrap();
        let per_view: usize = a.shape[1..].iter().product();
        let mut shape = a.shape.clone();
        shape[0] = 2;
        let data = match &a.data {
            NpyData::F32(v) => NpyData::F32(v[..2 * per_view].to_vec()),
            NpyData::F64(v) => NpyData::F64(v[..2 * per_view].to_vec()),
            NpyData::Bool(v) => NpyData::Bool(v[..2 * per_view].to_vec()),
            other => panic!("unexpected dtype {other:?}"),
        };
        *a = NpyArray::new(shape, data).unwrap();
    }
    let list: Vec<(&str, &NpyArray)> = arrays.iter().map(|(k, a)| (k.as_str(), a)).collect();
    write_npz(&npz, &list, false).unwrap();
    assert_fails_with(
        &run(&scene, &f.weights, &f.dir.path().join("out"), &[]),
        &["sfm.npz"],
    );
}

/// No DLT point: an error by default; with `--allow-unrefined` the feed-forward points are
/// exported unchanged with confidence 0 and no pixel marked covered.
#[test]
fn empty_guidance_scene_errors_or_passes_through_with_allow_unrefined() {
    let f = fixture();
    let mut s = f.scene.clone();
    s.matches.clear();
    let ff = s.ff.clone().unwrap();
    s.sfm = Some(sfm_on_ff(&s, 0));
    let scene = folder(&f, "empty", &s);
    let out = f.dir.path().join("out");
    assert_fails_with(&run(&scene, &f.weights, &out, &[]), &["no DLT point"]);
    let o = run(&scene, &f.weights, &out, &["--allow-unrefined"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let bytes = std::fs::read(out.join("refined.safetensors")).unwrap();
    let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let f32s = |name: &str| -> Vec<f32> {
        let t = st.tensor(name).unwrap();
        t.data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect()
    };
    assert_eq!(f32s("points"), ff.points);
    assert!(f32s("confidence").iter().all(|&c| c == 0.0));
    assert!(st.tensor("covered").unwrap().data().iter().all(|&b| b == 0));
}
