//! `ggpt-eval demo`: generate a synthetic scene with `ggpt-synth`, write it as a project scene
//! directory, evaluate its feed-forward prediction (and GT against itself as a sanity line).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use ggpt_cli::SyncStageBars;
use ggpt_core::io::read_scene;
use ggpt_core::io::scene_dir::write_scene;
use ggpt_synth::{Regime, SceneKind, SynthConfig, generate_with_progress};

use ggpt_core::io::atomic::write_json_atomic;
use ggpt_eval::report::{CameraSource, EvalReport, PredSource, evaluate_scene, format_table};

/// Options of the demo.
#[derive(Debug, Clone)]
pub struct DemoOptions {
    /// Output directory.
    pub out: PathBuf,
    /// Seed of the scene generator and of the RANSAC alignment.
    pub seed: u64,
    /// Number of views.
    pub views: usize,
    /// Feed-forward width (multiple of 14).
    pub width: usize,
    /// Feed-forward height (multiple of 14).
    pub height: usize,
    /// Also simulate dense matches (slower; needed to run the SfM stage on the scene later).
    pub with_matches: bool,
    /// Scene family.
    pub kind: SceneKind,
    /// Simulation regime (`docs/synthetic.md`).
    pub regime: Regime,
}

/// What the demo produced.
#[derive(Debug)]
pub struct DemoOutput {
    /// The written scene directory.
    pub scene_dir: PathBuf,
    /// Report files written.
    pub reports: Vec<(PathBuf, EvalReport)>,
}

/// Runs the demo: generate, write, read back, evaluate ff and GT, write the JSON reports.
pub fn run_demo(opts: &DemoOptions) -> Result<DemoOutput> {
    let cfg = SynthConfig {
        kind: opts.kind,
        views: opts.views,
        width: opts.width,
        height: opts.height,
        seed: opts.seed,
        matches: opts.with_matches,
        ..SynthConfig::for_regime(opts.regime)
    };
    let bars = SyncStageBars::new();
    let synth = generate_with_progress(&cfg, &|p| bars.report(p))
        .context("generating the synthetic scene")?;
    bars.finish();
    tracing::info!(
        "generated {} ({} views, {}x{})",
        synth.scene.name,
        opts.views,
        opts.width,
        opts.height
    );

    let scene_dir = opts.out.join("scene");
    write_scene(&scene_dir, &synth.scene)
        .with_context(|| format!("writing {}", scene_dir.display()))?;
    // Evaluate what is on disk (exercises the reader as a user would).
    let scene =
        read_scene(&scene_dir).with_context(|| format!("reading back {}", scene_dir.display()))?;

    let mut reports = Vec::new();
    for (pred, cams, file) in [
        (PredSource::Ff, CameraSource::Ff, "eval_ff.json"),
        (PredSource::Gt, CameraSource::Gt, "eval_gt.json"),
    ] {
        let report = evaluate_scene(&scene, &pred, cams, opts.seed)?;
        let path = opts.out.join(file);
        write_json_atomic(&path, &report)?;
        reports.push((path, report));
    }
    Ok(DemoOutput { scene_dir, reports })
}

/// Prints the demo's table and file locations to stdout.
pub fn print_demo(out: &DemoOutput, out_dir: &Path) {
    let reports: Vec<EvalReport> = out.reports.iter().map(|(_, r)| r.clone()).collect();
    println!("{}", format_table(&reports));
    println!("scene directory : {}", out.scene_dir.display());
    for (p, _) in &out.reports {
        println!("report          : {}", p.display());
    }
    println!(
        "re-run          : ggpt-eval --scene {} --pred ff --json {}",
        out.scene_dir.display(),
        out_dir.join("eval_ff.json").display()
    );
}
