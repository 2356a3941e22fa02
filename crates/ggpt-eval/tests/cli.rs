//! End-to-end tests of the `ggpt-eval` binary on a small synthetic scene.
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

use std::path::Path;
use std::process::Command;

use ggpt_core::io::npy::{NpyArray, NpyData, write_npy};
use ggpt_core::io::read_scene;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_ggpt-eval"))
}

fn run_ok(cmd: &mut Command) -> String {
    let out = cmd.output().expect("running ggpt-eval");
    assert!(
        out.status.success(),
        "ggpt-eval failed: {}\nstdout:\n{}\nstderr:\n{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn read_json(path: &Path) -> serde_json::Value {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_slice(&bytes).unwrap()
}

fn f(v: &serde_json::Value, path: &[&str]) -> f64 {
    let mut x = v;
    for k in path {
        x = &x[*k];
    }
    x.as_f64()
        .unwrap_or_else(|| panic!("{path:?} missing in {v}"))
}

/// The depth columns of the table row of `label`: `(header, row)` cells of the last four
/// columns (AbsRel, δ<1.01, δ<1.03, δ<1.25).
fn depth_cells(stdout: &str, label: &str) -> (Vec<String>, Vec<String>) {
    let last4 = |line: &str| {
        let t: Vec<String> = line.split_whitespace().map(str::to_string).collect();
        t[t.len().saturating_sub(4)..].to_vec()
    };
    let header = stdout
        .lines()
        .find(|l| l.starts_with("prediction"))
        .unwrap_or_else(|| panic!("no table header:\n{stdout}"));
    let row = stdout
        .lines()
        .find(|l| l.split_whitespace().next() == Some(label))
        .unwrap_or_else(|| panic!("no row {label}:\n{stdout}"));
    (last4(header), last4(row))
}

/// The table's depth columns are AbsRel, δ<1.01, δ<1.03, δ<1.25 with the report's values.
fn assert_depth_columns(stdout: &str, label: &str, report: &serde_json::Value) {
    let (header, row) = depth_cells(stdout, label);
    assert_eq!(header, ["AbsRel", "δ<1.01", "δ<1.03", "δ<1.25"], "{stdout}");
    let d = |k: &str| f(report, &["depth", k]);
    let want = [
        format!("{:.4}", d("abs_rel")),
        format!("{:.1}", d("delta_1_01")),
        format!("{:.1}", d("delta_1_03")),
        format!("{:.1}", d("delta_1_25")),
    ];
    assert_eq!(row, want, "{stdout}");
}

#[test]
fn demo_and_scene_evaluation() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let stdout = run_ok(
        bin()
            .args([
                "demo", "--views", "3", "--width", "112", "--height", "84", "--seed", "7", "--out",
            ])
            .arg(&out),
    );
    assert!(
        stdout.contains("AUC@5") && stdout.contains("eval_ff.json"),
        "{stdout}"
    );
    let scene_dir = out.join("scene");

    // Demo reports: ff clearly imperfect, GT perfect.
    let ff = read_json(&out.join("eval_ff.json"));
    let gt = read_json(&out.join("eval_gt.json"));
    for key in ["auc_1", "auc_3", "auc_5", "auc_10"] {
        assert_eq!(f(&gt, &["points", key]), 100.0, "gt {key}");
        assert_eq!(f(&gt, &["cameras", key]), 100.0, "gt cameras {key}");
    }
    assert!(
        f(&ff, &["points", "auc_5"]) < 90.0 && f(&ff, &["points", "auc_10"]) < 95.0,
        "{ff}"
    );
    assert!(f(&ff, &["points", "auc_5"]) > 0.0);
    assert_eq!(f(&gt, &["depth", "delta_1_01"]), 100.0);
    // The demo's table has one row per report, with the same depth columns.
    assert_depth_columns(&stdout, "ff", &ff);
    assert_depth_columns(&stdout, "gt", &gt);

    // Evaluate the written scene through the CLI.
    let json = tmp.path().join("ff.json");
    let stdout = run_ok(
        bin()
            .arg("--scene")
            .arg(&scene_dir)
            .args(["--seed", "7", "--pred", "ff", "--json"])
            .arg(&json),
    );
    assert!(stdout.contains("AUC@10"), "{stdout}");
    let r = read_json(&json);
    assert_depth_columns(&stdout, "ff", &r);
    // The ff prediction is imperfect: δ<1.01 is strictly below δ<1.03 (so the columns differ).
    assert!(
        f(&r, &["depth", "delta_1_01"]) < f(&r, &["depth", "delta_1_03"]),
        "{r}"
    );
    assert_eq!(r["prediction"], "ff");
    assert_eq!(r["camera_source"], "ff");
    // Same seed, same scene: identical to the demo's report.
    assert_eq!(r["points"], ff["points"]);

    let json_gt = tmp.path().join("gt.json");
    let stdout = run_ok(
        bin()
            .arg("--scene")
            .arg(&scene_dir)
            .args(["--pred", "gt", "--cameras", "gt", "--json"])
            .arg(&json_gt),
    );
    let r = read_json(&json_gt);
    assert_depth_columns(&stdout, "gt", &r);
    assert_eq!(depth_cells(&stdout, "gt").1[1], "100.0");
    assert_eq!(f(&r, &["points", "auc_10"]), 100.0);
    assert!(f(&r, &["points", "median_cm"]) < 1e-6);

    // A .npy prediction: GT points under a similarity (scale 2, shift) evaluates as perfect.
    let scene = read_scene(&scene_dir).unwrap();
    let gt_pts = &scene.gt.as_ref().unwrap().points;
    let d = scene.dims;
    let pred: Vec<f32> = gt_pts.iter().map(|v| 2.0 * v + 1.0).collect();
    let npy = tmp.path().join("pred.npy");
    write_npy(
        &npy,
        &NpyArray::new(vec![d.n, d.h, d.w, 3], NpyData::F32(pred)).unwrap(),
    )
    .unwrap();
    let json_npy = tmp.path().join("npy.json");
    run_ok(
        bin()
            .arg("--scene")
            .arg(&scene_dir)
            .arg("--pred")
            .arg(&npy)
            .args(["--cameras", "none", "--json"])
            .arg(&json_npy),
    );
    let r = read_json(&json_npy);
    assert!(f(&r, &["points", "auc_1"]) > 99.9, "{r}");
    assert!(r["cameras"].is_null());

    // Wrong shape: clear error, non-zero exit, no report.
    let bad = tmp.path().join("bad.npy");
    write_npy(
        &bad,
        &NpyArray::new(vec![2, 3], NpyData::F32(vec![0.0; 6])).unwrap(),
    )
    .unwrap();
    let json_bad = tmp.path().join("bad.json");
    let o = bin()
        .arg("--scene")
        .arg(&scene_dir)
        .arg("--pred")
        .arg(&bad)
        .arg("--json")
        .arg(&json_bad)
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("bad.npy") && err.contains("shape"), "{err}");
    assert!(!json_bad.exists());
}

#[test]
fn missing_scene_is_an_error() {
    let o = bin().output().unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("--scene"));
    let o = bin()
        .args(["--scene", "/nonexistent/dir"])
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("/nonexistent/dir"));
}

#[test]
fn help_documents_the_flags() {
    let o = bin().arg("--help").output().unwrap();
    let s = String::from_utf8_lossy(&o.stdout);
    for flag in ["--scene", "--pred", "--cameras", "--json", "--seed", "demo"] {
        assert!(s.contains(flag), "--help lacks {flag}:\n{s}");
    }
}

/// `--sfm FILE|DIR`: an SfM result written by `ggpt-sfm run` (here: GT points under a similarity on
/// half of the pixels, GT cameras as F32) is evaluated with `--pred sfm` / `--cameras sfm`.
#[test]
fn sfm_outputs_file_is_evaluated() {
    use ggpt_core::io::st::StWriter;
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    run_ok(
        bin()
            .args([
                "demo", "--views", "3", "--width", "56", "--height", "42", "--seed", "3", "--out",
            ])
            .arg(&out),
    );
    let scene_dir = out.join("scene");
    let scene = read_scene(&scene_dir).unwrap();
    let d = scene.dims;
    let gt = scene.gt.as_ref().unwrap();
    let pts: Vec<f32> = gt.points.iter().map(|v| 0.5 * v - 2.0).collect();
    let mask: Vec<bool> = (0..d.pixels()).map(|p| p % 2 == 0).collect();
    let masked: Vec<f32> = pts
        .iter()
        .enumerate()
        .map(|(i, &v)| if mask[i / 3] { v } else { 0.0 })
        .collect();
    let ext: Vec<f32> = gt
        .cameras
        .cam_from_world
        .iter()
        .flat_map(|m| m.transpose().iter().map(|&x| x as f32).collect::<Vec<_>>())
        .collect();
    let k: Vec<f32> = gt
        .cameras
        .intrinsics
        .iter()
        .flat_map(|m| m.transpose().iter().map(|&x| x as f32).collect::<Vec<_>>())
        .collect();
    let mut w = StWriter::new();
    w.f32("points", &[d.n, d.h, d.w, 3], &masked);
    w.bool("point_masks", &[d.n, d.h, d.w], &mask);
    w.f32("extrinsics", &[d.n, 3, 4], &ext);
    w.f32("intrinsics", &[d.n, 3, 3], &k);
    w.bool("camera_success", &[], &[true]);
    w.bool("points_success", &[], &[true]);
    let sfm_dir = tmp.path().join("sfm_out");
    std::fs::create_dir_all(&sfm_dir).unwrap();
    let file = sfm_dir.join("sfm_dlt_outputs.safetensors");
    std::fs::write(&file, w.finish(&file, None).unwrap()).unwrap();
    for arg in [file.clone(), sfm_dir.clone()] {
        let json = tmp.path().join("sfm.json");
        run_ok(
            bin()
                .arg("--scene")
                .arg(&scene_dir)
                .arg("--sfm")
                .arg(&arg)
                .args(["--pred", "sfm", "--json"])
                .arg(&json),
        );
        let r = read_json(&json);
        assert_eq!(r["camera_source"], "sfm");
        assert!(f(&r, &["points", "auc_1"]) > 99.9, "{r}");
        let ratio = f(&r, &["points", "ratio"]);
        assert!((ratio - 0.5).abs() < 0.05, "ratio {ratio}");
        assert_eq!(f(&r, &["cameras", "auc_5"]), 100.0);
    }
    // wrong size: error naming the file
    let mut w = StWriter::new();
    w.f32("points", &[1, 2, 2, 3], &[0.0; 12]);
    let bad = tmp.path().join("bad.safetensors");
    std::fs::write(&bad, w.finish(&bad, None).unwrap()).unwrap();
    let o = bin()
        .arg("--scene")
        .arg(&scene_dir)
        .arg("--sfm")
        .arg(&bad)
        .args(["--pred", "sfm"])
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("bad.safetensors") && err.contains("points"),
        "{err}"
    );
}
