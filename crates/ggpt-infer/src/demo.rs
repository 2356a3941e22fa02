//! `ggpt-infer demo`: synthetic scene -> SfM -> GGPT refinement with the shipped model ->
//! before / after AUC table.

use std::path::PathBuf;

use ggpt_core::io::scene_dir::write_scene;
use ggpt_synth::{Regime, SceneKind, SynthConfig, generate};

use ggpt_model::ModelError;
use ggpt_model::model_dir::{ModelSpec, resolve_model};

use crate::engine::Refiner;
use crate::pipeline::{RunOptions, RunReport, save_run};
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
    /// Weights file or model folder (`None`: the shipped model embedded in the binary,
    /// [`ModelSpec::shipped`]).
    pub weights: Option<PathBuf>,
    /// Model configuration file (default: `model_config.json` next to the weights).
    pub model_config: Option<PathBuf>,
    /// Built-in configuration instead of a file.
    pub preset: Option<String>,
    /// Device name (`cpu`, `ndarray`, `flex`, `wgpu`).
    pub device: String,
    /// Everything after the synthesis (chunk sampler: `run.chunking` over the model's
    /// `inference.json` over `run.refine.chunking`, [`Refiner::resolve_chunking`]).
    pub run: RunOptions,
}

/// What [`run_demo`] produced.
#[derive(Debug, Clone)]
pub struct DemoReport {
    /// The generated scene, written as a project scene directory.
    pub scene_dir: PathBuf,
    /// The model used (`<embedded>/...` for the shipped model).
    pub weights: PathBuf,
    /// Whether that is the shipped model embedded in the binary (`--weights shipped`).
    pub shipped: bool,
    /// The inference run.
    pub run: RunReport,
}

/// Resolves the model (the embedded shipped one by default), with a clear message when a file
/// is missing.
fn demo_model(opts: &DemoOptions) -> Result<ModelSpec> {
    let Some(weights) = &opts.weights else {
        if opts.model_config.is_some() || opts.preset.is_some() {
            return Err(InferError::Invalid(
                "a model configuration or preset needs --weights (the shipped model has its own configuration)".into(),
            ));
        }
        return Ok(ModelSpec::shipped()?);
    };
    resolve_model(weights, opts.model_config.as_deref(), opts.preset.as_deref()).map_err(|e| match e {
        ModelError::Missing { what, path } => InferError::Model(ModelError::Missing {
            what: format!(
                "{what} of the demo model (pass --weights FILE [--model-config FILE], or leave --weights out for the shipped model)"
            ),
            path,
        }),
        e => e.into(),
    })
}

/// Generates a synthetic scene (`ggpt-synth`, with simulated feed-forward prediction and dense
/// matches), writes it to `<out>/scene`, runs SfM and refinement and writes every output of
/// `ggpt-infer run` into `<out>`. `progress` receives the SfM and refinement reports (see
/// [`Refiner::refine`]).
pub fn run_demo(
    opts: &DemoOptions,
    log: &mut StageLog,
    progress: &mut (dyn FnMut(ggpt_core::Progress) + Send),
) -> Result<DemoReport> {
    let spec = demo_model(opts)?;
    let (weights, shipped) = (spec.weights.clone(), spec.is_embedded());
    log.start("load model");
    let mut refiner = Refiner::load(spec, &opts.device, 0)?;
    // the chunk settings fail now rather than after the synthesis
    refiner.resolve_chunking(&opts.run)?;

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

    let run = refiner.refine(&mut scene, &opts.run, log, progress)?;
    let mut config = refiner.run_config("demo", serde_json::json!(scene_dir), &opts.run, &run);
    config["synth"] = serde_json::json!(cfg);
    let meta = refiner.run_meta(&opts.run);
    let run = save_run(run, &scene, &opts.run, &opts.out, &config, meta, log)?;
    Ok(DemoReport {
        scene_dir,
        weights,
        shipped,
        run,
    })
}
