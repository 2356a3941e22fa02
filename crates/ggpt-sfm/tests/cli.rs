//! The `ggpt-sfm` binary on the `sfm_small` fixture.

mod common;

use std::process::Command;

use common::{fixture, max_abs_diff, open};
use ggpt_sfm::st::StFile;

#[test]
fn cli_reproduces_fixture_scatter_with_recorded_cameras() {
    let fx = open();
    let dir = tempfile::tempdir().unwrap();
    let inputs = fixture("inputs.safetensors");
    let out = Command::new(env!("CARGO_BIN_EXE_ggpt-sfm"))
        .args(["run", "--ff"])
        .arg(&inputs)
        .arg("--matches")
        .arg(&inputs)
        .args(["--preset", "benchmark", "--mintrack-per-view", "64", "--no-progress", "--cameras"])
        .arg(fixture("steps.safetensors"))
        .arg("--out")
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(out.status.success(), "stderr: {}", String::from_utf8_lossy(&out.stderr));
    let st = StFile::open(&dir.path().join("sfm_dlt_outputs.safetensors")).unwrap();
    assert_eq!(st.bool("point_masks").unwrap().data, fx.bool("scatter/point_masks"));
    let (d, i) = max_abs_diff(&st.f32("points").unwrap().data, &fx.f32("scatter/points"));
    assert!(d <= 2e-3, "points: max |Δ| = {d} at {i}");
    assert!(dir.path().join("sparse/0/cameras.bin").is_file());
    assert!(dir.path().join("summary.json").is_file());
}

#[test]
fn cli_end_to_end_with_our_ba_and_errors() {
    let dir = tempfile::tempdir().unwrap();
    let inputs = fixture("inputs.safetensors");
    let out = Command::new(env!("CARGO_BIN_EXE_ggpt-sfm"))
        .args(["run", "--ff"])
        .arg(&inputs)
        .arg("--matches")
        .arg(&inputs)
        .args(["--mintrack-per-view", "64", "--no-progress", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(out.status.success(), "stderr: {}", String::from_utf8_lossy(&out.stderr));
    let summary: serde_json::Value = serde_json::from_slice(&std::fs::read(dir.path().join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["ba"]["success"], true);
    assert_eq!(summary["tracks_selected"], 93);
    // a bad --matches file: error naming the file
    let out = Command::new(env!("CARGO_BIN_EXE_ggpt-sfm"))
        .args(["run", "--ff"])
        .arg(&inputs)
        .arg("--matches")
        .arg(fixture("README.md"))
        .args(["--no-progress", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("README.md"), "{err}");
}
