//! The shipped model (`models/ggpt-synth-small/`) loads strictly with its own configuration and
//! sampler settings, and refines chunks of a synthetic scene that neither its training nor its
//! validation set contains: a regression guard on the committed weights (a corrupted, retrained
//! or mis-exported model that no longer refines fails here).
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

use ggpt_model::model_dir::{load_model, resolve_model, shipped_model_dir};
use ggpt_scene::chunk_settings::{ChunkingSettings, resolve_chunking};
use ggpt_scene::chunker::ChunkParams;
use ggpt_train::chunkset::{SceneEntry, Split};
use ggpt_train::evaluate::validate_chunks;
use ggpt_train::prepare::{PrepareParams, prepare_scene};
use ggpt_train::scene_source::{SynthSpec, synthetic_scene};

/// Parameters of the shipped `small` configuration (its model card).
const SHIPPED_PARAMETERS: usize = 623_772;
/// The improvement the shipped model must bring (issue: at least +10 points AUC@5).
const MIN_AUC5_GAIN: f64 = 10.0;
/// A seed outside the training (3000-3063; the first model: 2000-2063), validation (3064-3069;
/// 2064-2069) and documented held-out (9100-9105; 9000-9005) scenes.
const FRESH_SEED: u64 = 9_317;

#[test]
fn shipped_model_loads_strictly_and_refines_fresh_chunks() {
    let spec = resolve_model(
        &shipped_model_dir().expect("shipped model folder"),
        None,
        None,
    )
    .expect("shipped model folder");
    let device = ggpt_model::device::device_from_name("ndarray").unwrap();
    let model = load_model(&spec, &device).expect("strict load of the shipped weights");
    assert_eq!(
        ggpt_model::weights::num_trainable_params(&model),
        SHIPPED_PARAMETERS
    );

    let chunking = resolve_chunking(
        &ChunkParams::default(),
        spec.chunking_layer(),
        &ChunkingSettings::default(),
        |f: &str| f.to_string(),
    )
    .unwrap();
    assert!(
        spec.inference.is_some(),
        "inference.json missing from the shipped model"
    );
    assert_eq!(chunking.max_pixels.value, 10_000);

    let synth = SynthSpec {
        kind: ggpt_synth::SceneKind::Room,
        views: 4,
        width: 518,
        height: 392,
        seed: FRESH_SEED,
        regime: ggpt_synth::Regime::Benchmark,
    };
    let (scene, sfm) = synthetic_scene(&synth).unwrap();
    let params = PrepareParams {
        chunks_per_scene: 6,
        chunking: chunking.params,
        ..PrepareParams::default()
    };
    let prepared = prepare_scene(&scene, &sfm, &params).unwrap();
    assert_eq!(prepared.chunks.len(), 6);
    let entry = SceneEntry {
        name: scene.name.clone(),
        split: Split::Val,
        views: synth.views,
        height: synth.height,
        width: synth.width,
        metres_per_unit: prepared.metres_per_unit,
        source: "test".into(),
    };
    let v = validate_chunks(
        &model,
        &spec.config,
        &prepared.chunks,
        &[entry],
        &device,
        40_000,
    )
    .unwrap();
    eprintln!(
        "shipped model on fresh chunks: AUC@5 {:.1} -> {:.1}, AUC@10 {:.1} -> {:.1}",
        v.input_auc5, v.refined_auc5, v.input_auc10, v.refined_auc10
    );
    assert!(v.refined_auc5 >= v.input_auc5 + MIN_AUC5_GAIN, "{v:?}");
    assert!(v.refined_auc10 > v.input_auc10, "{v:?}");
}
