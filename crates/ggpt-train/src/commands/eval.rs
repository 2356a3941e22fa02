//! `ggpt-train eval`: whole-scene (or chunk-level) evaluation of a model on held-out scenes.

use anyhow::{Context, Result, bail};
use burn::module::Module;
use ggpt_cli::{Bar, ChunkingArgs, println_above};
use ggpt_scene::chunk_settings::resolve_chunking;
use ggpt_scene::chunker::ChunkParams;
use ggpt_scene::driver::RefineOptions;
use ggpt_train::chunkset::{ChunkSet, SceneEntry, Split};
use ggpt_train::evaluate::{HeldOutScene, HeldOutSummary, evaluate_scene, validate_chunks};
use ggpt_train::model_source::load_model_source;
use ggpt_train::scene_source::{SynthSpec, synthetic_scene};

use crate::cli::EvalArgs;

/// A scene to evaluate: a recorded chunk-set scene or a fresh synthetic one.
enum EvalScene {
    Recorded(SceneEntry),
    Synthetic(SynthSpec),
}

impl EvalScene {
    fn load(&self) -> Result<(ggpt_core::Scene, ggpt_core::SfmResult)> {
        Ok(match self {
            EvalScene::Synthetic(spec) => synthetic_scene(spec)?,
            EvalScene::Recorded(s) => s.source.load(&s.name)?,
        })
    }
}

/// Runs `eval`.
pub fn run(a: &EvalArgs) -> Result<()> {
    let device = ggpt_model::device::device_from_name(&a.device.device.to_string())?;
    let m = a.model.normalized();
    let path = m.require_weights()?;
    let loaded = load_model_source(path, m.model_config.as_deref(), m.preset_name(), &device)
        .with_context(|| format!("loading the model {}", path.display()))?;
    let (model, cfg) = (loaded.model, loaded.config);
    if let (Some(n), Some(dir)) = (a.chunk_level, &a.data) {
        let data = ChunkSet::open(dir)?;
        let mut val = data.load_split(Split::Val)?;
        val.truncate(n);
        if val.is_empty() {
            bail!("{}: no val chunk", dir.display());
        }
        let v = validate_chunks(
            &model,
            &cfg,
            &val,
            &data.manifest.scenes,
            &device,
            a.max_tokens_per_forward,
        )?;
        println!(
            "{} val chunks: AUC@5 input {:.1} -> refined {:.1} ({:+.1}); AUC@10 {:.1} -> {:.1} ({:+.1}); val loss {:.4}",
            v.chunks,
            v.input_auc5,
            v.refined_auc5,
            v.refined_auc5 - v.input_auc5,
            v.input_auc10,
            v.refined_auc10,
            v.refined_auc10 - v.input_auc10,
            v.loss
        );
        if let Some(out) = &a.out {
            let j = serde_json::json!({"chunk_level": v, "model": path, "data": dir});
            ggpt_core::io::atomic::write_json_atomic(out, &j)?;
        }
        return Ok(());
    }
    // flag > the model's training sampler (inference.json / chunk-set manifest) > default
    let layer = loaded
        .chunking
        .as_ref()
        .map(|c| (c.path.as_path(), c.settings.as_ref()));
    let resolved = resolve_chunking(
        &ChunkParams::default(),
        layer,
        &a.chunking.settings(),
        ChunkingArgs::flag,
    )?;
    tracing::info!("chunk sampler: {}", resolved.describe());
    let chunking = resolved.params;
    let mut refiner = ggpt_infer::refiner::BurnRefiner::new(
        model.valid().fork(&device),
        cfg.clone(),
        device.clone(),
    )?;
    let opts = RefineOptions {
        chunking: chunking.clone(),
        max_tokens_per_forward: a.max_tokens_per_forward,
        ..RefineOptions::default()
    };
    let scenes: Vec<EvalScene> = match (&a.data, a.synthetic_scenes) {
        (_, Some(n)) => (0..n)
            .map(|i| a.synth.spec(i).map(EvalScene::Synthetic))
            .collect::<Result<_>>()?,
        (Some(dir), None) => {
            let data = ChunkSet::open(dir)?;
            let val: Vec<EvalScene> = data
                .manifest
                .scenes
                .into_iter()
                .filter(|s| s.split == Split::Val)
                .map(EvalScene::Recorded)
                .collect();
            if val.is_empty() {
                bail!("{}: no val scene", dir.display());
            }
            val
        }
        (None, None) => bail!("give --data DIR or --synthetic-scenes N"),
    };
    if scenes.is_empty() {
        bail!("no scene to evaluate");
    }
    let bar = Bar::new("eval", scenes.len() as u64);
    let mut results: Vec<HeldOutScene> = Vec::new();
    for s in &scenes {
        let (scene, sfm) = s.load()?;
        let r = evaluate_scene(&scene, &sfm, &mut refiner, &opts)
            .with_context(|| format!("evaluating {}", scene.name))?;
        bar.inc(1);
        println_above(&r.describe());
        results.push(r);
    }
    bar.finish();
    let summary = HeldOutSummary::of(&results).context("no scene evaluated")?;
    println!("{}", summary.describe());
    if let Some(out) = &a.out {
        let v = serde_json::json!({"summary": summary, "scenes": results, "model": path, "data": a.data,
            "synthetic": a.synthetic_scenes.map(|n| serde_json::json!({"scenes": n, "first_seed": a.synth.first_seed, "views": a.synth.views,
                "width": a.synth.width, "height": a.synth.height, "kinds": a.synth.kinds, "regime": a.synth.regime})),
            "chunking": chunking});
        ggpt_core::io::atomic::write_json_atomic(out, &v)?;
    }
    Ok(())
}
