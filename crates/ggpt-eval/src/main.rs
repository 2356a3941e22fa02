//! `ggpt-eval`: evaluate a point map and cameras of a scene against its ground truth
//! (`pipeline.md` §10), or run a self-contained synthetic demo (`ggpt-eval demo`).
//!
//! Results: a table on stdout and, with `--json`, a JSON report (written atomically); logs go to
//! stderr (`RUST_LOG=debug` for more).

mod commands;

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand, ValueEnum};
use ggpt_cli::{ProgressArgs, RegimeArg, SceneKindArg};
use ggpt_core::io::read_scene;

use ggpt_core::io::atomic::write_json_atomic;
use ggpt_eval::report::{CameraSource, PredSource, evaluate_scene, format_table, load_sfm_outputs};

use crate::commands::demo;

/// Evaluate point maps and cameras against ground truth.
///
/// Point accuracy: the prediction is aligned to the GT points with a robust Sim(3) (LO-RANSAC,
/// 3 cm threshold, retry schedule 3/9/27/81 cm), then the per-pixel error (cm) gives Recall@1..10,
/// AUC@1/3/5/10 cm, mean and median. Camera accuracy: relative poses over all view pairs, AUC@1/3/5/10
/// degrees of max(rotation error, translation-direction error), FoV error. Depth: Rel and δ<τ of the
/// aligned prediction in the GT cameras. Definitions: docs/evaluation.md.
#[derive(Debug, Parser)]
#[command(name = "ggpt-eval", version, args_conflicts_with_subcommands = true)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    eval: EvalArgs,
    #[command(flatten)]
    progress: ProgressArgs,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Generate a synthetic scene (ggpt-synth), write it, and evaluate its feed-forward prediction
    /// and the GT against itself.
    Demo(DemoArgs),
}

#[derive(Debug, Args)]
struct EvalArgs {
    /// Scene directory with ground truth: project layout (scene.json), official layout (gt.bin,
    /// ff_outputs.bin, sfm_dlt_outputs.bin) or the formats.md §5.1 folder.
    #[arg(long, value_name = "DIR")]
    scene: Option<PathBuf>,
    /// Point map to evaluate: `ff` (feed-forward points), `sfm` (DLT points, on the SfM mask, with
    /// the ratio), `gt` (sanity check), `FILE.npy` ([N,h,w,3] or [N*h*w,3], f32/f64), or
    /// `FILE.safetensors[:KEY]` (KEY defaults to the only tensor, or `points`).
    #[arg(long, default_value = "ff", value_name = "SOURCE")]
    pred: String,
    /// Cameras to evaluate: `auto` (same source as --pred when it is ff/sfm/gt, else ff), `ff`,
    /// `sfm`, `gt` or `none`.
    #[arg(long, value_enum, default_value_t = CamerasArg::Auto)]
    cameras: CamerasArg,
    /// Evaluate this SfM result instead of the scene's own: the `sfm_dlt_outputs.safetensors`
    /// written by `ggpt-sfm run`, its `--out` directory, or an official `sfm_dlt_outputs.bin`
    /// (used by `--pred sfm` and `--cameras sfm`).
    #[arg(long, value_name = "FILE|DIR")]
    sfm: Option<PathBuf>,
    /// Write the JSON report here (atomically).
    #[arg(long, value_name = "OUT.json")]
    json: Option<PathBuf>,
    /// Seed of the RANSAC generator of the Sim(3) alignment.
    #[arg(long, default_value_t = 42)]
    seed: u64,
}

/// `--cameras` (the CLI face of [`CameraSource`]).
#[derive(Debug, Clone, Copy, ValueEnum)]
enum CamerasArg {
    /// `ff`/`sfm`/`gt` as `--pred` when it names one, else `ff` when present.
    Auto,
    /// Feed-forward cameras.
    Ff,
    /// Bundle-adjusted SfM cameras.
    Sfm,
    /// GT cameras (sanity check).
    Gt,
    /// No camera evaluation.
    None,
}

impl From<CamerasArg> for CameraSource {
    fn from(a: CamerasArg) -> Self {
        match a {
            CamerasArg::Auto => CameraSource::Auto,
            CamerasArg::Ff => CameraSource::Ff,
            CamerasArg::Sfm => CameraSource::Sfm,
            CamerasArg::Gt => CameraSource::Gt,
            CamerasArg::None => CameraSource::None,
        }
    }
}

#[derive(Debug, Args)]
struct DemoArgs {
    /// Output directory (receives `scene/`, `eval_ff.json`, `eval_gt.json`).
    #[arg(long, default_value = "out/demo", value_name = "DIR")]
    out: PathBuf,
    /// Seed of the synthetic scene and of the RANSAC alignment.
    #[arg(long, default_value_t = 42)]
    seed: u64,
    /// Number of views (2..=64).
    #[arg(long, default_value_t = 8)]
    views: usize,
    /// Feed-forward width in pixels (multiple of 14).
    #[arg(long, default_value_t = 518)]
    width: usize,
    /// Feed-forward height in pixels (multiple of 14).
    #[arg(long, default_value_t = 392)]
    height: usize,
    /// Scene family.
    #[arg(long, value_enum, default_value_t)]
    kind: SceneKindArg,
    /// Simulation regime: `benchmark` (matcher failure modes, structured feed-forward error,
    /// the paper's ranges) or `easy` (the first, dense and clean regime; docs/synthetic.md).
    #[arg(long, value_enum, default_value_t)]
    regime: RegimeArg,
    /// Also simulate dense matches (slower; lets the SfM stage run on the written scene).
    #[arg(long)]
    with_matches: bool,
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    ggpt_cli::init_logging(cli.progress.bars());
    match cli.command {
        Some(Command::Demo(a)) => run_demo(a),
        None => run_eval(cli.eval),
    }
}

fn run_eval(a: EvalArgs) -> Result<()> {
    let Some(scene_dir) = a.scene else {
        bail!("--scene DIR is required (or use `ggpt-eval demo`); see --help");
    };
    let pred = PredSource::parse(&a.pred)?;
    let mut scene =
        read_scene(&scene_dir).with_context(|| format!("reading scene {}", scene_dir.display()))?;
    if let Some(p) = &a.sfm {
        scene.sfm = Some(
            load_sfm_outputs(p, scene.dims).with_context(|| format!("--sfm {}", p.display()))?,
        );
    }
    tracing::info!(
        "scene {} ({} views, {}x{})",
        scene.name,
        scene.dims.n,
        scene.dims.w,
        scene.dims.h
    );
    let report = evaluate_scene(&scene, &pred, a.cameras.into(), a.seed)?;
    if let Some(path) = &a.json {
        write_json_atomic(path, &report)?;
        tracing::info!("report written to {}", path.display());
    }
    println!("scene {}", scene.name);
    print!("{}", format_table(std::slice::from_ref(&report)));
    Ok(())
}

fn run_demo(a: DemoArgs) -> Result<()> {
    let opts = demo::DemoOptions {
        out: a.out.clone(),
        seed: a.seed,
        views: a.views,
        width: a.width,
        height: a.height,
        with_matches: a.with_matches,
        kind: ggpt_synth::SceneKind::parse(a.kind.name())?,
        regime: ggpt_synth::Regime::parse(a.regime.name())?,
    };
    let out = demo::run_demo(&opts)?;
    demo::print_demo(&out, &a.out);
    Ok(())
}
