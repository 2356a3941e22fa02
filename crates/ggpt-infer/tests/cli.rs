//! `ggpt-infer chunk` reproduces the official fixture outputs (shared/fixtures/ggpt_small).
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

mod common;

use std::path::PathBuf;
use std::process::Command;

use safetensors::{Dtype, SafeTensors};

fn small_dir() -> PathBuf {
    PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../../shared/fixtures/ggpt_small"
    ))
}

fn f32s(st: &SafeTensors<'_>, name: &str) -> Vec<f32> {
    let v = st.tensor(name).unwrap_or_else(|e| panic!("{name}: {e}"));
    assert_eq!(v.dtype(), Dtype::F32, "{name}");
    v.data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

#[test]
fn chunk_subcommand_reproduces_fixture_outputs() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("out.safetensors");
    let status = Command::new(env!("CARGO_BIN_EXE_ggpt-infer"))
        .args(["chunk", "--model-config"])
        .arg(small_dir().join("manifest.json"))
        .arg("--weights")
        .arg(small_dir().join("weights.pth"))
        .arg("--input")
        .arg(small_dir().join("inputs.safetensors"))
        .arg("--output")
        .arg(&out)
        .args(["--device", "ndarray", "--threads", "1"])
        .status()
        .expect("runs");
    assert!(status.success(), "ggpt-infer chunk failed: {status}");
    let ours_bytes = std::fs::read(&out).expect("output written");
    let ours = SafeTensors::deserialize(&ours_bytes).expect("valid output");
    let ref_path = small_dir().join("outputs.safetensors");
    let ref_bytes =
        std::fs::read(&ref_path).unwrap_or_else(|e| panic!("{}: {e}", ref_path.display()));
    let reference = SafeTensors::deserialize(&ref_bytes).expect("valid reference");
    let mut names = reference.names();
    names.sort();
    assert_eq!(names.len(), 12);
    for name in names {
        let (a, b) = (f32s(&ours, name), f32s(&reference, name));
        assert_eq!(a.len(), b.len(), "{name}");
        let worst = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        assert!(
            worst <= 1e-4 && a.iter().all(|x| x.is_finite()),
            "{name}: max |Δ| = {worst:e}"
        );
    }
}

fn ggpt_infer(args: &[&std::ffi::OsStr]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_ggpt-infer"))
        .args(args)
        .output()
        .expect("runs")
}

#[test]
fn chunk_flags_are_documented_in_help() {
    for cmd in ["run", "demo"] {
        let out = ggpt_infer(&[cmd.as_ref(), "--help".as_ref()]);
        assert!(out.status.success());
        let help = String::from_utf8_lossy(&out.stdout);
        for flag in [
            "--chunk-size <F>",
            "--max-chunk-pixels <N>",
            "--min-chunk-dlt <N>",
            "--min-chunk-pixels <N>",
            "inference.json",
        ] {
            assert!(
                help.contains(flag),
                "`ggpt-infer {cmd} --help` lacks {flag}:\n{help}"
            );
        }
    }
}

/// A malformed `inference.json` next to the weights and a bad chunk flag stop `run` before the
/// scene is read, naming the file / the flag.
#[test]
fn bad_inference_json_and_chunk_flags_are_reported() {
    let dir = tempfile::tempdir().expect("tempdir");
    let w = dir.path().join("model.safetensors");
    std::fs::write(&w, b"not read").unwrap();
    let base = |extra: &[&str]| {
        let mut a: Vec<std::ffi::OsString> = vec![
            "run".into(),
            "--scene".into(),
            dir.path().join("no-scene").into(),
            "--weights".into(),
            dir.path().into(),
            "--preset".into(),
            "tiny".into(),
            "--out".into(),
            dir.path().join("o").into(),
        ];
        a.extend(extra.iter().map(|s| s.into()));
        a
    };
    let run = |args: Vec<std::ffi::OsString>| {
        let args: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_os_str()).collect();
        let out = ggpt_infer(&args);
        assert!(!out.status.success());
        String::from_utf8_lossy(&out.stderr).to_string()
    };
    let e = run(base(&["--chunk-size", "0"]));
    assert!(e.contains("--chunk-size = 0") && e.contains("> 0"), "{e}");
    let e = run(base(&["--max-chunk-pixels", "0"]));
    assert!(e.contains("--max-chunk-pixels = 0"), "{e}");
    let e = run(base(&["--min-chunk-dlt=-3"]));
    assert!(
        e.contains("invalid value") && e.contains("--min-chunk-dlt"),
        "{e}"
    );
    let settings = dir.path().join("inference.json");
    std::fs::write(&settings, r#"{"chunking": {"chunk_size": 0.2, "max_pixels": 10000, "min_dlt": 100, "min_pixels": 4000, "overlap": 2}}"#).unwrap();
    let e = run(base(&[]));
    assert!(
        e.contains(&settings.display().to_string())
            && e.contains("invalid settings: unknown field `overlap`"),
        "{e}"
    );
    std::fs::write(&settings, "{\"chunking\": ").unwrap();
    let e = run(base(&["--chunk-size", "0.3"]));
    assert!(
        e.contains(&settings.display().to_string()) && e.contains("malformed JSON"),
        "{e}"
    );
}

/// `run` on a tiny scene: an explicit flag wins over the model's `inference.json`, which wins
/// over the default; the resolved values and origins are logged and written to config.json.
#[test]
fn run_resolves_chunk_settings_flag_over_model_over_default() {
    let dir = tempfile::tempdir().expect("tempdir");
    let w = dir.path().join("tiny.bpk");
    common::save_tiny_weights(&w);
    std::fs::write(
        dir.path().join("inference.json"),
        r#"{"chunking": {"max_pixels": 5000, "min_dlt": 10, "min_pixels": 300}}"#,
    )
    .unwrap();
    let scene = common::tiny_scene(3);
    let sdir = dir.path().join("scene");
    ggpt_core::io::scene_dir::write_scene(&sdir, &scene).unwrap();
    let out = dir.path().join("out");
    let o = Command::new(env!("CARGO_BIN_EXE_ggpt-infer"))
        .args(["run", "--scene"])
        .arg(&sdir)
        .arg("--weights")
        .arg(&w)
        .args([
            "--preset",
            "tiny",
            "--device",
            "ndarray",
            "--quiet",
            "--no-error-maps",
            "--max-chunk-pixels",
            "1200",
            "--min-chunk-dlt",
            "40",
            "--out",
        ])
        .arg(&out)
        .env("RUST_LOG", "info")
        .env("NO_COLOR", "1")
        .output()
        .expect("runs");
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "ggpt-infer run failed: {stderr}");
    assert!(stderr.contains("chunk sampler: chunk_size 0.2 (default), max_pixels 1200 (flag), min_dlt 40 (flag), min_pixels 300 (model inference.json)"), "{stderr}");
    let config: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("config.json")).unwrap()).unwrap();
    let c = &config["chunking"];
    assert_eq!(
        c["chunk_size"],
        serde_json::json!({"value": 0.2, "origin": "default"}),
        "{c}"
    );
    assert_eq!(
        c["max_pixels"],
        serde_json::json!({"value": 1200, "origin": "flag"}),
        "{c}"
    );
    assert_eq!(
        c["min_dlt"],
        serde_json::json!({"value": 40, "origin": "flag"}),
        "{c}"
    );
    assert_eq!(
        c["min_pixels"],
        serde_json::json!({"value": 300, "origin": "model inference.json"}),
        "{c}"
    );
    assert_eq!(
        c["model_inference_json"],
        serde_json::json!(dir.path().join("inference.json"))
    );
    let r = &config["refine"]["chunking"];
    assert_eq!(
        (
            r["chunk_size"].as_f64(),
            r["max_pixels"].as_u64(),
            r["min_dlt"].as_u64(),
            r["min_pixels"].as_u64()
        ),
        (Some(0.2), Some(1200), Some(40), Some(300)),
        "{r}"
    );
    // The sampler ran with those settings: chunks of at most 1200 pixels (on average here).
    let meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("meta.json")).unwrap()).unwrap();
    let (chunks, dense) = (
        meta["counts"]["chunks"].as_u64().unwrap_or(0),
        meta["counts"]["dense_tokens"].as_u64().unwrap_or(u64::MAX),
    );
    assert!(
        chunks > 0 && dense <= 1200 * chunks,
        "{chunks} chunks, {dense} dense tokens"
    );
}

/// `demo` resolves the chunk settings the same way (model folder's inference.json under the
/// flags); its text COLMAP model (`--colmap-text`) is read by pycolmap.
#[test]
fn demo_resolves_chunk_settings_from_model_folder_and_flags() {
    let dir = tempfile::tempdir().expect("tempdir");
    let model_dir = dir.path().join("model");
    std::fs::create_dir_all(&model_dir).unwrap();
    common::save_tiny_weights(&model_dir.join("model.bpk"));
    std::fs::write(
        model_dir.join("inference.json"),
        r#"{"chunking": {"chunk_size": 0.25, "min_dlt": 40, "min_pixels": 300}}"#,
    )
    .unwrap();
    let out = dir.path().join("out");
    let o = Command::new(env!("CARGO_BIN_EXE_ggpt-infer"))
        .args([
            "demo",
            "--views",
            "3",
            "--width",
            "70",
            "--height",
            "56",
            "--weights",
        ])
        .arg(&model_dir)
        .args([
            "--preset",
            "tiny",
            "--device",
            "ndarray",
            "--quiet",
            "--no-error-maps",
            "--colmap-text",
            "--min-chunk-pixels",
            "200",
            "--out",
        ])
        .arg(&out)
        .output()
        .expect("runs");
    assert!(
        o.status.success(),
        "ggpt-infer demo failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let config: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("config.json")).unwrap()).unwrap();
    let c = &config["chunking"];
    assert_eq!(
        c["chunk_size"],
        serde_json::json!({"value": 0.25, "origin": "model inference.json"}),
        "{c}"
    );
    assert_eq!(
        c["max_pixels"],
        serde_json::json!({"value": 400000, "origin": "default"}),
        "{c}"
    );
    assert_eq!(
        c["min_dlt"],
        serde_json::json!({"value": 40, "origin": "model inference.json"}),
        "{c}"
    );
    assert_eq!(
        c["min_pixels"],
        serde_json::json!({"value": 200, "origin": "flag"}),
        "{c}"
    );
    assert_eq!(config["refine"]["chunking"]["min_pixels"], 200);
    assert_eq!(config["refine"]["chunking"]["chunk_size"], 0.25);
    let sparse = out.join("sparse/0");
    assert!(sparse.join("points3D.txt").is_file());
    let test = "demo_resolves_chunk_settings_from_model_folder_and_flags";
    if common::python_module_available(test, "pycolmap", "pycolmap==4.2.1", "the text COLMAP model")
    {
        let py = common::run_python_check("check_colmap_model.py", &sparse);
        let meta: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("meta.json")).unwrap()).unwrap();
        assert_eq!(py["ok"], true, "{py}");
        assert_eq!(py["num_images"], 3);
        assert_eq!(py["num_points3D"], meta["export"]["colmap_points"], "{py}");
        assert_eq!(py["num_observations"], 0);
    }
}

/// The COLMAP flags of `run`: `--colmap-points none` writes cameras and images only,
/// `--colmap-resolution WxH` rescales the cameras to the original images, and
/// `--colmap-simple-pinhole` writes one focal length; a malformed resolution is an error.
#[test]
fn run_colmap_flags_shape_the_model() {
    let dir = tempfile::tempdir().expect("tempdir");
    let w = dir.path().join("tiny.bpk");
    common::save_tiny_weights(&w);
    let scene = common::tiny_scene(4);
    let sdir = dir.path().join("scene");
    ggpt_core::io::scene_dir::write_scene(&sdir, &scene).unwrap();
    let run = |out: &std::path::Path, extra: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_ggpt-infer"))
            .args(["run", "--scene"])
            .arg(&sdir)
            .arg("--weights")
            .arg(&w)
            .args([
                "--preset",
                "tiny",
                "--device",
                "ndarray",
                "--quiet",
                "--no-error-maps",
                "--min-chunk-dlt",
                "40",
                "--min-chunk-pixels",
                "300",
                "--out",
            ])
            .arg(out)
            .args(extra)
            .output()
            .expect("runs")
    };
    let bad = run(&dir.path().join("bad"), &["--colmap-resolution", "112by84"]);
    let stderr = String::from_utf8_lossy(&bad.stderr);
    assert!(
        !bad.status.success()
            && stderr.contains("--colmap-resolution")
            && stderr.contains("112by84"),
        "{stderr}"
    );

    let out = dir.path().join("out");
    let o = run(
        &out,
        &[
            "--colmap-text",
            "--colmap-points",
            "none",
            "--colmap-resolution",
            "112x84",
            "--colmap-simple-pinhole",
        ],
    );
    assert!(
        o.status.success(),
        "ggpt-infer run failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let sparse = out.join("sparse/0");
    let cameras = std::fs::read_to_string(sparse.join("cameras.txt")).unwrap();
    let cam: Vec<&str> = cameras
        .lines()
        .find(|l| !l.starts_with('#'))
        .unwrap()
        .split_whitespace()
        .collect();
    assert_eq!(&cam[1..4], &["SIMPLE_PINHOLE", "112", "84"], "{cameras}");
    // Principal point at the centre of the original image: (W-1)/2, (H-1)/2 in the project's
    // pixel-centre convention, + 0.5 in COLMAP's (docs/conventions.md).
    assert_eq!(
        (
            cam[5].parse::<f64>().unwrap(),
            cam[6].parse::<f64>().unwrap()
        ),
        (56.0, 42.0),
        "{cameras}"
    );
    let points = std::fs::read_to_string(sparse.join("points3D.txt")).unwrap();
    assert_eq!(
        points.lines().filter(|l| !l.starts_with('#')).count(),
        0,
        "{points}"
    );
    let test = "run_colmap_flags_shape_the_model";
    if common::python_module_available(
        test,
        "pycolmap",
        "pycolmap==4.2.1",
        "the rescaled COLMAP model",
    ) {
        let py = common::run_python_check("check_colmap_model.py", &sparse);
        assert_eq!(py["ok"], true, "{py}");
        assert_eq!(py["num_images"], 3);
        assert_eq!(py["num_points3D"], 0, "{py}");
    }
}

/// A file that is not a chunk record given to `--input` is reported as the chunk input (not as
/// the model configuration), naming the file.
#[test]
fn chunk_input_that_is_not_a_chunk_record_is_named_as_the_input() {
    let dir = tempfile::tempdir().expect("tempdir");
    // A valid safetensors without chunk tensors: the fixture's weights-free outputs file.
    let not_chunks = small_dir().join("outputs.safetensors");
    let out = ggpt_infer(&[
        "chunk".as_ref(),
        "--model-config".as_ref(),
        small_dir().join("manifest.json").as_os_str(),
        "--weights".as_ref(),
        small_dir().join("weights.pth").as_os_str(),
        "--input".as_ref(),
        not_chunks.as_os_str(),
        "--output".as_ref(),
        dir.path().join("o.safetensors").as_os_str(),
        "--device".as_ref(),
        "ndarray".as_ref(),
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("chunk input")
            && err.contains("outputs.safetensors")
            && err.contains("ff_pts"),
        "{err}"
    );
    assert!(!err.contains("model config"), "{err}");
    assert!(!dir.path().join("o.safetensors").exists());
}
