//! `ggpt-infer demo`: synthetic scene -> SfM -> GGPT refinement with the shipped model ->
//! before / after AUC table.

use std::path::PathBuf;

use ggpt_core::io::scene_dir::write_scene;
use ggpt_model::device::device_from_name;
use ggpt_synth::{Regime, SceneKind, SynthConfig, generate};

use ggpt_model::ModelError;
use ggpt_model::model_dir::{ModelSpec, load_model, resolve_model, shipped_model_dir};
use ggpt_scene::chunk_settings::{ChunkingSettings, resolve_chunking};

use crate::pipeline::{RunOptions, RunReport, run_scene};
use crate::refiner::BurnRefiner;
use crate::rss::StageLog;
use crate::{InferError, Result};

/// Options of [`run_demo`].
#[derive(Debug, Clone)]
pub struct DemoOptions {
    /// Number of views (default 8).
    pub views: usize,
    /// Seed of the generator, RANSAC and export (default 42).
    pub seed: u64,
    /// Scene family.
    pub kind: SceneKind,
    /// Simulation regime (`docs/synthetic.md`).
    pub regime: Regime,
    /// Feed-forward width (multiple of 14).
    pub width: usize,
    /// Feed-forward height (multiple of 14).
    pub height: usize,
    /// Output folder (scene in `<out>/scene`, results in `<out>`).
    pub out: PathBuf,
    /// Weights file or model folder (`None`: the shipped model,
    /// [`ggpt_model::model_dir::shipped_model_dir`]).
    pub weights: Option<PathBuf>,
    /// Model configuration file (default: `model_config.json` next to the weights).
    pub model_config: Option<PathBuf>,
    /// Built-in configuration instead of a file.
    pub preset: Option<String>,
    /// Device name (`cpu`, `ndarray`, `flex`, `wgpu`).
    pub device: String,
    /// Explicit chunk-sampler settings (`--chunk-size` etc.); they win over the model's
    /// `inference.json`, which wins over `run.refine.chunking`.
    pub chunking: ChunkingSettings,
    /// Everything after the synthesis (`run.refine.chunking` is the base of the chunk-sampler
    /// resolution, see [`ggpt_scene::chunk_settings::resolve_chunking`]).
    pub run: RunOptions,
}

/// What [`run_demo`] produced.
#[derive(Debug, Clone)]
pub struct DemoReport {
    /// The generated scene, written as a project scene directory.
    pub scene_dir: PathBuf,
    /// The model used.
    pub weights: PathBuf,
    /// The inference run.
    pub run: RunReport,
}

/// Resolves the model (the shipped one by default), with a clear message when a file is
/// missing.
fn demo_model(opts: &DemoOptions) -> Result<ModelSpec> {
    let weights = match &opts.weights {
        Some(w) => w.clone(),
        None => shipped_model_dir()?,
    };
    resolve_model(&weights, opts.model_config.as_deref(), opts.preset.as_deref()).map_err(|e| match e {
        ModelError::Missing { what, path } => InferError::Model(ModelError::Missing {
            what: format!(
                "{what} of the demo model (the shipped model lives in models/ggpt-synth-small/ with model.safetensors and model_config.json; pass --weights FILE [--model-config FILE] to use another)"
            ),
            path,
        }),
        e => e.into(),
    })
}

/// Generates a synthetic scene (`ggpt-synth`, with simulated feed-forward prediction and dense
/// matches), writes it to `<out>/scene`, runs SfM and refinement and writes every output of
/// `ggpt-infer run` into `<out>`. `progress` receives the SfM and refinement reports (see
/// [`run_scene`]).
pub fn run_demo(
    opts: &DemoOptions,
    log: &mut StageLog,
    progress: &mut dyn FnMut(ggpt_core::Progress),
) -> Result<DemoReport> {
    let spec = demo_model(opts)?;
    let mut run_opts = opts.run.clone();
    // the caller validated the flags under their own names ([`ChunkingSettings::validate`])
    let chunking = resolve_chunking(
        &run_opts.refine.chunking,
        spec.chunking_layer(),
        &opts.chunking,
        |f| format!("chunking.{f}"),
    )?;
    tracing::info!("chunk sampler: {}", chunking.describe());
    run_opts.refine.chunking = chunking.params.clone();
    let device = device_from_name(&opts.device)?;
    log.start("load model");
    let model = load_model(&spec, &device)?;
    let mut refiner = BurnRefiner::new(model, spec.config.clone(), device)?.with_rss_stages(true);

    log.start("synth");
    let cfg = SynthConfig {
        kind: opts.kind,
        views: opts.views,
        width: opts.width,
        height: opts.height,
        seed: opts.seed,
        matches: true,
        ..SynthConfig::for_regime(opts.regime)
    };
    let synth = generate(&cfg)?;
    let mut scene = synth.scene;
    let scene_dir = opts.out.join("scene");
    write_scene(&scene_dir, &scene)?;
    log.finish();
    tracing::info!(
        "synthetic scene {} ({} views, {}x{}) written to {}",
        scene.name,
        opts.views,
        opts.width,
        opts.height,
        scene_dir.display()
    );

    let config = serde_json::json!({
        "command": "demo",
        "synth": cfg,
        "weights": spec.weights,
        "model_config_origin": spec.origin,
        "model_config": spec.config,
        "device": opts.device,
        "chunking": chunking,
        "refine": run_opts.refine,
        "export": run_opts.export,
        "sfm_preset": format!("{:?}", run_opts.sfm_preset),
    });
    let meta = serde_json::json!({
        "ggpt_infer_version": env!("CARGO_PKG_VERSION"),
        "backend": opts.device,
        "dtype": "f32",
        "seed": opts.seed,
    });
    let run = run_scene(
        &mut scene,
        &mut refiner,
        &run_opts,
        &opts.out,
        &config,
        meta,
        log,
        progress,
    )?;
    Ok(DemoReport {
        scene_dir,
        weights: spec.weights,
        run,
    })
}
