//! End-to-end: tiny synthetic scene -> SfM -> tiny random-init network (weights saved to a
//! temporary burnpack and loaded back, chunk-sampler settings from the model folder's
//! `inference.json`) -> fusion -> export, on ndarray and on wgpu (lavapipe without a GPU; the
//! first wgpu run JIT-compiles its kernels, so the wgpu test is the slow one). The PLY is opened
//! with Python `plyfile` (`scripts/check_ply.py`) and the COLMAP model with `pycolmap`
//! (`scripts/check_colmap_model.py`); see `tests/common` for the missing-module convention.
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

mod common;

use std::path::Path;

use burn::nn::LinearConfig;
use ggpt_core::Scene;
use ggpt_infer::pipeline::{RunOptions, RunReport, run_scene};
use ggpt_infer::refiner::BurnRefiner;
use ggpt_infer::rss::StageLog;
use ggpt_model::device::device_from_name;
use ggpt_model::model_dir::{INFERENCE_SETTINGS_FILE, ModelSpec, load_model, resolve_model};
use ggpt_model::weights::save_burnpack;
use ggpt_model::{Ggpt, GgptConfig};
use ggpt_scene::chunk_settings::{ChunkingSettings, SettingOrigin, resolve_chunking};
use ggpt_scene::chunker::ChunkParams;
use ggpt_scene::export::select_points;
use ggpt_synth::{SynthConfig, generate};

const VIEWS: usize = 4;
const W: usize = 70;
const H: usize = 56;

/// Tiny random-init network (the last head layer, zero-initialised by `Ggpt::new`, randomised
/// too so that the network actually moves the points) saved as a burnpack in `dir`, with an `inference.json` next to it
/// holding the `sfm_small` chunk minimums (pipeline.md §5) so that chunks of this tiny scene are
/// accepted. Returns the resolved model.
fn tiny_model(dir: &Path) -> ModelSpec {
    let w = dir.join("tiny.bpk");
    let (cfg, device) = (GgptConfig::tiny(), device_from_name("ndarray").unwrap());
    let mut model = Ggpt::new(&cfg, &device);
    model.head.fc3 = LinearConfig::new(cfg.head_width, 4).init(&device);
    save_burnpack(&model, &w).unwrap();
    std::fs::write(
        dir.join(INFERENCE_SETTINGS_FILE),
        r#"{"chunking": {"max_pixels": 1200, "min_dlt": 40, "min_pixels": 300}}"#,
    )
    .unwrap();
    let spec = resolve_model(&w, None, Some("tiny")).unwrap();
    assert!(
        spec.inference.is_some(),
        "inference.json next to the weights was not picked up"
    );
    spec
}

fn tiny_scene() -> Scene {
    generate(&SynthConfig {
        views: VIEWS,
        width: W,
        height: H,
        seed: 42,
        matches: true,
        ..SynthConfig::default()
    })
    .unwrap()
    .scene
}

/// Run options with the chunk-sampler settings resolved from the model's `inference.json`.
fn options(spec: &ModelSpec) -> RunOptions {
    let mut opts = RunOptions::default();
    let chunking = resolve_chunking(
        &ChunkParams::default(),
        spec.chunking_layer(),
        &ChunkingSettings::default(),
        |f: &str| f.to_string(),
    )
    .unwrap();
    assert_eq!(
        (chunking.max_pixels.origin, chunking.chunk_size.origin),
        (SettingOrigin::Model, SettingOrigin::Default)
    );
    opts.refine.chunking = chunking.params.clone();
    assert_eq!(
        (
            opts.refine.chunking.max_pixels,
            opts.refine.chunking.min_dlt,
            opts.refine.chunking.min_pixels
        ),
        (1200, 40, 300)
    );
    opts
}

/// Loads the model on `device` and runs the whole pipeline (SfM first when the scene has none).
fn run_on(
    device: &str,
    spec: &ModelSpec,
    scene: &mut Scene,
    opts: &RunOptions,
    out: &Path,
) -> RunReport {
    let device = device_from_name(device).unwrap();
    let model = load_model(spec, &device).unwrap();
    let mut refiner = BurnRefiner::new(model, spec.config.clone(), device).unwrap();
    let config = serde_json::json!({"chunking": resolve_chunking(&ChunkParams::default(), spec.chunking_layer(), &ChunkingSettings::default(), |f: &str| f.to_string()).unwrap()});
    run_scene(
        scene,
        &mut refiner,
        opts,
        out,
        &config,
        serde_json::json!({}),
        &mut StageLog::new(),
        &mut ggpt_core::progress::ignore,
    )
    .unwrap()
}

fn read_json(path: &Path) -> serde_json::Value {
    serde_json::from_slice(
        &std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())),
    )
    .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The invariants of one run: shapes, uncovered pixels = aligned input with confidence 0, the
/// output files, and the PLY / COLMAP files opened by real readers.
fn check_run(test: &str, report: &RunReport, opts: &RunOptions, out: &Path) {
    let r = &report.refined;
    assert_eq!(r.points.len(), 3 * VIEWS * H * W);
    assert_eq!(
        (r.conf.len(), r.covered.len()),
        (VIEWS * H * W, VIEWS * H * W)
    );
    assert!(
        !r.no_chunk_fallback && !r.chunks.is_empty(),
        "no chunk accepted"
    );
    eprintln!(
        "{test}: chunks {}, dlt {}, covered {}",
        r.chunks.len(),
        r.dlt_pixels,
        r.covered.iter().filter(|&&c| c).count()
    );
    assert!(r.points.iter().all(|v| v.is_finite()) && r.conf.iter().all(|v| v.is_finite()));
    let moved = (0..r.covered.len())
        .filter(|&p| r.covered[p])
        .map(|p| {
            (0..3)
                .map(|a| (r.points[3 * p + a] - r.aligned_ff[3 * p + a]).abs())
                .fold(0.0f32, f32::max)
        })
        .fold(0.0f32, f32::max);
    assert!(
        moved > 1e-3,
        "the network moved no covered point by more than {moved:e}: the run would not test the network"
    );
    for p in 0..r.covered.len() {
        if !r.covered[p] {
            // Uncovered: the aligned input, confidence 0.
            assert_eq!(r.conf[p], 0.0, "pixel {p}");
            assert_eq!(
                r.points[3 * p..3 * p + 3],
                r.aligned_ff[3 * p..3 * p + 3],
                "pixel {p}"
            );
        }
    }
    for f in [
        "ggpt_points.ply",
        "ff_points.ply",
        "sfm_points.ply",
        "points.npy",
        "refined.safetensors",
        "config.json",
        "meta.json",
        "evaluation.json",
        "error_maps/view_000.png",
        "sparse/0/cameras.bin",
        "sparse/0/images.bin",
        "sparse/0/points3D.bin",
        "images/000000.png",
        "transforms.json",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    // refined.safetensors shapes.
    let bytes = std::fs::read(out.join("refined.safetensors")).unwrap();
    let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    for (name, shape) in [
        ("points", vec![VIEWS, H, W, 3]),
        ("confidence", vec![VIEWS, H, W]),
        ("covered", vec![VIEWS, H, W]),
        ("aligned_ff_points", vec![VIEWS, H, W, 3]),
        ("cam_from_world", vec![VIEWS, 3, 4]),
        ("K", vec![VIEWS, 3, 3]),
    ] {
        assert_eq!(st.tensor(name).unwrap().shape(), &shape[..], "{name}");
    }
    // config.json records the resolved chunking with its origin.
    let config = read_json(&out.join("config.json"));
    assert_eq!(
        config["chunking"]["max_pixels"],
        serde_json::json!({"value": 1200, "origin": "model inference.json"}),
        "{config}"
    );
    // meta.json's export summary = what the Rust side selected.
    let meta = read_json(&out.join("meta.json"));
    let (tau, keep) = select_points(
        &r.conf,
        opts.export.conf_quantile,
        opts.export.max_points,
        opts.export.seed,
    )
    .unwrap();
    assert_eq!(report.export.ply_points, keep.len());
    assert_eq!(meta["export"]["ply_points"], keep.len());
    assert!(!keep.is_empty());

    if common::python_module_available(test, "plyfile", "plyfile==1.1.5", "ggpt_points.ply") {
        let py = common::run_python_check("check_ply.py", &out.join("ggpt_points.ply"));
        assert_eq!(py["ok"], true, "{py}");
        eprintln!(
            "{test}: plyfile {} read {} vertices, bbox {} .. {}",
            py["plyfile_version"], py["vertex_count"], py["xyz_min"], py["xyz_max"]
        );
        assert_eq!(py["format"], "binary_little_endian");
        assert_eq!(py["vertex_count"], meta["export"]["ply_points"], "{py}");
        let props: Vec<(String, String)> = py["properties"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| {
                (
                    p["name"].as_str().unwrap().to_string(),
                    p["type"].as_str().unwrap().to_string(),
                )
            })
            .collect();
        let want: Vec<(String, String)> = [
            ("x", "f4"),
            ("y", "f4"),
            ("z", "f4"),
            ("red", "u1"),
            ("green", "u1"),
            ("blue", "u1"),
            ("confidence", "f4"),
        ]
        .map(|(a, b)| (a.to_string(), b.to_string()))
        .to_vec();
        assert_eq!(props, want);
        // Bounding box of the refined points that passed the filter (f32 values, exact).
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for &p in &keep {
            for a in 0..3 {
                lo[a] = lo[a].min(r.points[3 * p as usize + a]);
                hi[a] = hi[a].max(r.points[3 * p as usize + a]);
            }
        }
        let f32s = |k: &str| -> Vec<f32> {
            py[k]
                .as_array()
                .unwrap_or_else(|| panic!("{k} missing: {py}"))
                .iter()
                .map(|v| v.as_f64().unwrap() as f32)
                .collect()
        };
        assert_eq!(f32s("xyz_min"), lo.to_vec(), "{py}");
        assert_eq!(f32s("xyz_max"), hi.to_vec(), "{py}");
        let conf_min = py["confidence_min"].as_f64().unwrap() as f32;
        assert!(
            conf_min >= tau,
            "PLY confidence {conf_min} below the threshold {tau}"
        );
        let kept_max = keep
            .iter()
            .map(|&p| r.conf[p as usize])
            .fold(f32::NEG_INFINITY, f32::max);
        assert_eq!(py["confidence_max"].as_f64().unwrap() as f32, kept_max);
    }

    if common::python_module_available(
        test,
        "pycolmap",
        "pycolmap==4.2.1",
        "the COLMAP model sparse/0",
    ) {
        let sparse = out.join("sparse/0");
        let py = common::run_python_check("check_colmap_model.py", &sparse);
        assert_eq!(py["ok"], true, "{py}");
        eprintln!(
            "{test}: pycolmap {} read {} cameras, {} images, {} points",
            py["pycolmap_version"], py["num_cameras"], py["num_images"], py["num_points3D"]
        );
        assert_eq!(
            (py["num_images"].as_u64(), py["num_reg_images"].as_u64()),
            (Some(VIEWS as u64), Some(VIEWS as u64))
        );
        assert_eq!(py["num_points3D"], report.export.colmap_points, "{py}");
        assert_eq!(
            report.export.colmap_points,
            keep.len()
                .min(ggpt_scene::export::DEFAULT_COLMAP_MAX_POINTS)
        );
        // Refined points without tracks (docs/inference.md): no observation, no stored error.
        assert_eq!(py["num_observations"], 0);
        assert_eq!(py["short_tracks"], report.export.colmap_points);
        // Shared camera at the ff resolution: the SfM intrinsics, COLMAP corner convention.
        let k = &report.sfm.cameras.intrinsics[0];
        assert_eq!(py["num_cameras"], 1);
        let cam = &py["cameras"][0];
        assert_eq!(
            (cam["width"].as_u64(), cam["height"].as_u64()),
            (Some(W as u64), Some(H as u64))
        );
        let params: Vec<f64> = cam["params"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        let want = if cam["model"] == "SIMPLE_PINHOLE" {
            vec![k[(0, 0)], W as f64 / 2.0, H as f64 / 2.0]
        } else {
            vec![k[(0, 0)], k[(1, 1)], W as f64 / 2.0, H as f64 / 2.0]
        };
        assert_eq!(params.len(), want.len(), "{cam}");
        for (a, b) in params.iter().zip(&want) {
            assert!(
                (a - b).abs() <= 1e-9 * b.abs().max(1.0),
                "camera params {params:?} vs {want:?}"
            );
        }
        // pycolmap's poses = the refined (SfM) cameras.
        let poses = python_poses(&sparse);
        assert_eq!(poses.len(), VIEWS);
        for (i, pose) in poses.iter().enumerate() {
            let c = &report.sfm.cameras.cam_from_world[i];
            for (j, v) in pose.iter().enumerate() {
                assert!(
                    (v - c[(j / 4, j % 4)]).abs() <= 1e-6,
                    "image {}: pycolmap pose {pose:?} vs {c}",
                    i + 1
                );
            }
        }
    }
}

/// `cam_from_world` (row-major 3x4) of every image of a COLMAP model, in image-id order, as
/// pycolmap reads it.
fn python_poses(dir: &Path) -> Vec<Vec<f64>> {
    let code = "import json, sys, pycolmap\nr = pycolmap.Reconstruction(sys.argv[1])\nprint(json.dumps([sum(im.cam_from_world().matrix().tolist(), []) for _, im in sorted(r.images.items())]))";
    let out = std::process::Command::new("python3")
        .args(["-c", code])
        .arg(dir)
        .output()
        .expect("running python3");
    assert!(
        out.status.success(),
        "pycolmap pose read failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

#[test]
fn tiny_scene_end_to_end_ndarray() {
    let dir = tempfile::tempdir().unwrap();
    let spec = tiny_model(dir.path());
    let opts = options(&spec);
    let mut scene = tiny_scene();
    let out = dir.path().join("out");
    let report = run_on("ndarray", &spec, &mut scene, &opts, &out);
    assert!(report.sfm_summary.is_some(), "the SfM stage did not run");
    check_run("tiny_scene_end_to_end_ndarray", &report, &opts, &out);
}

/// The same run on wgpu: same invariants, and the refined points agree with ndarray's (same
/// scene and SfM result, same weights file, same seeds) to 1e-4.
#[cfg(feature = "wgpu")]
#[test]
fn tiny_scene_end_to_end_wgpu_matches_ndarray() {
    let dir = tempfile::tempdir().unwrap();
    let spec = tiny_model(dir.path());
    let opts = options(&spec);
    let mut scene = tiny_scene();
    let nd = run_on(
        "ndarray",
        &spec,
        &mut scene,
        &opts,
        &dir.path().join("ndarray"),
    );
    // The run moved the SfM result out of the scene: the wgpu run gets the same guidance.
    assert!(scene.sfm.is_none());
    let mut scene_w = scene.clone();
    scene_w.sfm = Some(nd.sfm.clone());
    let out = dir.path().join("wgpu");
    let wg = run_on("wgpu", &spec, &mut scene_w, &opts, &out);
    assert!(
        wg.sfm_summary.is_none(),
        "the wgpu run re-ran the SfM stage"
    );
    check_run(
        "tiny_scene_end_to_end_wgpu_matches_ndarray",
        &wg,
        &opts,
        &out,
    );
    let (a, b) = (&nd.refined, &wg.refined);
    assert_eq!(
        a.covered, b.covered,
        "chunk coverage differs between backends"
    );
    assert_eq!(a.chunks.len(), b.chunks.len());
    let dp = a
        .points
        .iter()
        .zip(&b.points)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max);
    let dc = a
        .conf
        .iter()
        .zip(&b.conf)
        .map(|(x, y)| (x - y).abs() / x.abs().max(1.0))
        .fold(0.0f32, f32::max);
    eprintln!("wgpu vs ndarray: max |Δ point| = {dp:e}, max relative |Δ conf| = {dc:e}");
    assert!(dp <= 1e-4, "refined points differ by {dp:e} (> 1e-4)");
    assert!(
        dc <= 1e-4,
        "refined confidences differ by {dc:e} (relative, > 1e-4)"
    );
}

fn tiny_refiner() -> BurnRefiner {
    let device = device_from_name("ndarray").unwrap();
    BurnRefiner::new(
        Ggpt::new(&GgptConfig::tiny(), &device),
        GgptConfig::tiny(),
        device,
    )
    .unwrap()
}

fn tiny_scene_with_sfm() -> ggpt_core::Scene {
    let mut scene = generate(&SynthConfig {
        views: 4,
        width: 70,
        height: 56,
        seed: 7,
        matches: true,
        ..SynthConfig::default()
    })
    .unwrap()
    .scene;
    let (sfm, _) = ggpt_infer::pipeline::ensure_sfm(
        &mut scene,
        ggpt_sfm::masks::Preset::Demo,
        42,
        &ggpt_core::Cancel::default(),
        &mut ggpt_core::progress::ignore,
    )
    .unwrap();
    scene.sfm = Some(sfm);
    scene
}

#[test]
fn bad_inputs_give_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let run = |scene: &mut ggpt_core::Scene, opts: &RunOptions| {
        run_scene(
            scene,
            &mut tiny_refiner(),
            opts,
            &dir.path().join("o"),
            &serde_json::json!({}),
            serde_json::json!({}),
            &mut StageLog::new(),
            &mut ggpt_core::progress::ignore,
        )
    };
    let base = tiny_scene_with_sfm();
    // Empty guidance: no DLT point at all.
    let mut s = base.clone();
    if let Some(sfm) = s.sfm.as_mut() {
        sfm.mask.iter_mut().for_each(|m| *m = false);
        sfm.points.iter_mut().for_each(|v| *v = 0.0);
        sfm.points_success = false;
    }
    let e = run(&mut s.clone(), &RunOptions::default())
        .unwrap_err()
        .to_string();
    assert!(e.contains("no DLT point"), "{e}");
    let mut opts = RunOptions::default();
    opts.refine.allow_unrefined = true;
    let r = run(&mut s, &opts).unwrap();
    assert!(r.refined.unrefined && r.refined.conf.iter().all(|&c| c == 0.0));
    assert_eq!(r.refined.points, s.ff.as_ref().unwrap().points);
    // Mismatched view counts.
    let mut s = base.clone();
    if let Some(sfm) = s.sfm.as_mut() {
        sfm.cameras.cam_from_world.pop();
    }
    let e = run(&mut s, &RunOptions::default()).unwrap_err().to_string();
    assert!(e.contains("mismatched view counts"), "{e}");
    // NaN in the feed-forward points.
    let mut s = base.clone();
    if let Some(ff) = s.ff.as_mut() {
        ff.points[7] = f32::NAN;
    }
    let e = run(&mut s, &RunOptions::default()).unwrap_err().to_string();
    assert!(
        e.contains("non-finite") && e.contains("ff.points") && e.contains("index 7"),
        "{e}"
    );
    // Neither SfM nor matches.
    let mut s = base.clone();
    s.sfm = None;
    s.matches.clear();
    let e = run(&mut s, &RunOptions::default()).unwrap_err().to_string();
    assert!(e.contains("neither an SfM result nor dense matches"), "{e}");
    // Missing weights.
    let e = resolve_model(&dir.path().join("missing.safetensors"), None, Some("tiny"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("weights not found") && e.contains("missing.safetensors"),
        "{e}"
    );
}
