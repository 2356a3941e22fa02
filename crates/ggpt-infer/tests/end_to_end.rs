//! End-to-end: tiny synthetic scene -> SfM -> tiny random-init network (weights saved to a
//! temporary burnpack and loaded back) -> fusion -> export, on ndarray.

use ggpt_infer::model_load::{load_model, resolve_model};
use ggpt_infer::pipeline::{RunOptions, run_scene};
use ggpt_infer::refiner::BurnRefiner;
use ggpt_infer::rss::StageLog;
use ggpt_model::device::device_from_name;
use ggpt_model::weights::save_burnpack;
use ggpt_model::{Ggpt, GgptConfig};
use ggpt_synth::{SynthConfig, generate};

#[test]
fn tiny_scene_end_to_end_ndarray() {
    let dir = tempfile::tempdir().unwrap();
    let device = device_from_name("ndarray").unwrap();
    let w = dir.path().join("tiny.bpk");
    save_burnpack(&Ggpt::new(&GgptConfig::tiny(), &device), &w).unwrap();
    let spec = resolve_model(&w, None, Some("tiny")).unwrap();
    let model = load_model(&spec, &device).unwrap();
    let mut refiner = BurnRefiner::new(model, spec.config.clone(), device).unwrap();
    let synth = generate(&SynthConfig { views: 4, width: 70, height: 56, seed: 42, matches: true, ..SynthConfig::default() }).unwrap();
    let mut scene = synth.scene;
    let out = dir.path().join("out");
    let mut opts = RunOptions::default();
    // Tiny scene: the sfm_small chunk minimums (pipeline.md §5) so that chunks are accepted.
    opts.refine.chunking.max_pixels = 1200;
    opts.refine.chunking.min_dlt = 40;
    opts.refine.chunking.min_pixels = 300;
    let report = run_scene(&mut scene, &mut refiner, &opts, &out, &serde_json::json!({}), serde_json::json!({}), &mut StageLog::new()).unwrap();
    let r = &report.refined;
    assert_eq!(r.points.len(), 3 * 4 * 56 * 70);
    assert!(report.sfm_summary.is_some());
    assert!(!r.no_chunk_fallback && !r.chunks.is_empty());
    eprintln!("chunks {}, fallback {}, dlt {}", r.chunks.len(), r.no_chunk_fallback, r.dlt_pixels);
    let ff_conf = &scene.ff.as_ref().unwrap().conf;
    for p in 0..r.covered.len() {
        if !r.covered[p] {
            // Uncovered: the aligned input, confidence 0 (or the ff confidence when no chunk
            // was accepted at all, pipeline.md §8).
            assert_eq!(r.conf[p], if r.no_chunk_fallback { ff_conf[p] } else { 0.0 });
            assert_eq!(r.points[3 * p..3 * p + 3], r.aligned_ff[3 * p..3 * p + 3]);
        }
    }
    for f in ["ggpt_points.ply", "points.npy", "refined.safetensors", "config.json", "meta.json", "evaluation.json", "error_maps/view_000.png", "sparse/0/cameras.bin"] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
}

fn tiny_refiner() -> BurnRefiner {
    let device = device_from_name("ndarray").unwrap();
    BurnRefiner::new(Ggpt::new(&GgptConfig::tiny(), &device), GgptConfig::tiny(), device).unwrap()
}

fn tiny_scene_with_sfm() -> ggpt_core::Scene {
    let mut scene = generate(&SynthConfig { views: 4, width: 70, height: 56, seed: 7, matches: true, ..SynthConfig::default() }).unwrap().scene;
    ggpt_infer::pipeline::ensure_sfm(&mut scene, ggpt_sfm::masks::Preset::Demo, 42, false).unwrap();
    scene
}

#[test]
fn bad_inputs_give_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let run = |scene: &mut ggpt_core::Scene, opts: &RunOptions| {
        run_scene(scene, &mut tiny_refiner(), opts, &dir.path().join("o"), &serde_json::json!({}), serde_json::json!({}), &mut StageLog::new())
    };
    let base = tiny_scene_with_sfm();
    // Empty guidance: no DLT point at all.
    let mut s = base.clone();
    if let Some(sfm) = s.sfm.as_mut() {
        sfm.mask.iter_mut().for_each(|m| *m = false);
        sfm.points.iter_mut().for_each(|v| *v = 0.0);
        sfm.points_success = false;
    }
    let e = run(&mut s.clone(), &RunOptions::default()).unwrap_err().to_string();
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
    assert!(e.contains("non-finite") && e.contains("ff.points") && e.contains("index 7"), "{e}");
    // Neither SfM nor matches.
    let mut s = base.clone();
    s.sfm = None;
    s.matches.clear();
    let e = run(&mut s, &RunOptions::default()).unwrap_err().to_string();
    assert!(e.contains("neither an SfM result nor dense matches"), "{e}");
    // Missing weights.
    let e = resolve_model(&dir.path().join("missing.safetensors"), None, Some("tiny")).unwrap_err().to_string();
    assert!(e.contains("weights not found") && e.contains("missing.safetensors"), "{e}");
}
