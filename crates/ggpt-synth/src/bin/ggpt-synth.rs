//! `ggpt-synth`: writes a procedural synthetic scene (GT, simulated feed-forward prediction,
//! simulated dense matches) as a project scene directory.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Parser;
use ggpt_cli::{ProgressArgs, RegimeArg, SceneKindArg, SyncStageBars};
use tracing::info;

use ggpt_synth::stats::{match_stats, point_accuracy};
use ggpt_synth::{PrincipalPoint, Regime, SceneKind, SynthConfig, generate_with_progress};

/// Generate a synthetic multi-view scene with exact ground truth.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Args {
    /// Seed of every random choice (same seed -> identical scene).
    #[arg(long, default_value_t = 42)]
    seed: u64,
    /// Number of views.
    #[arg(long, default_value_t = 8)]
    views: usize,
    /// Scene family: `room` (indoor) or `object` (object-centric orbit).
    #[arg(long, value_enum, default_value_t)]
    kind: SceneKindArg,
    /// Feed-forward width in pixels (multiple of 14).
    #[arg(long, default_value_t = 518)]
    width: usize,
    /// Feed-forward height in pixels (multiple of 14).
    #[arg(long, default_value_t = 392)]
    height: usize,
    /// Simulation regime: `benchmark` (matcher failure modes and structured feed-forward error
    /// calibrated to the paper's ranges) or `easy` (the first, dense and clean regime).
    #[arg(long, value_enum, default_value_t)]
    regime: RegimeArg,
    /// Room ceiling: `yes`, `no` or `random`.
    #[arg(long, value_enum, default_value_t = Ceiling::Random)]
    ceiling: Ceiling,
    /// Principal point of the feed-forward intrinsics: `vggt` = `(w/2, h/2)` (VGGT's native
    /// output, what real users feed) or `centre` = `((w-1)/2, (h-1)/2)`. The GT cameras keep
    /// the exact centre.
    #[arg(long, value_enum, default_value_t = PrincipalPointArg::Vggt)]
    principal_point: PrincipalPointArg,
    /// Output scene directory (project layout, `ggpt_core::io::scene_dir`).
    #[arg(long)]
    out: PathBuf,
    /// Also write the official `.bin` content (gt / ff_outputs / sfm_dlt_outputs keys) as one
    /// safetensors file.
    #[arg(long)]
    official_safetensors: Option<PathBuf>,
    /// Also write the feed-forward prediction as VGGT's `predictions.npz` into the scene folder
    /// (beside `images/` and `matches/`: the images-to-splats route's inputs,
    /// `docs/images-to-splats.md`).
    #[arg(long)]
    vggt_predictions: bool,
    /// Skip the dense matches.
    #[arg(long)]
    no_matches: bool,
    /// Compute and log diagnostics (ff AUC@5/10 cm, match pass rates); costs a few seconds.
    #[arg(long)]
    stats: bool,
    /// Log per-stage timings.
    #[arg(long)]
    timings: bool,
    #[command(flatten)]
    progress: ProgressArgs,
}

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum PrincipalPointArg {
    Vggt,
    Centre,
}

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum Ceiling {
    Yes,
    No,
    Random,
}

fn main() -> Result<()> {
    let args = Args::parse();
    ggpt_cli::init_logging(args.progress.bars());
    let cfg = SynthConfig {
        kind: SceneKind::parse(args.kind.name())?,
        views: args.views,
        width: args.width,
        height: args.height,
        seed: args.seed,
        matches: !args.no_matches,
        ceiling: match args.ceiling {
            Ceiling::Yes => Some(true),
            Ceiling::No => Some(false),
            Ceiling::Random => None,
        },
        principal_point: match args.principal_point {
            PrincipalPointArg::Vggt => PrincipalPoint::Vggt,
            PrincipalPointArg::Centre => PrincipalPoint::Centre,
        },
        ..SynthConfig::for_regime(Regime::parse(args.regime.name())?)
    };
    info!(name = %cfg.scene_name(), regime = %cfg.regime, views = cfg.views, w = cfg.width, h = cfg.height, "generating");
    let bars = SyncStageBars::new();
    let out = generate_with_progress(&cfg, &|p| bars.report(p))
        .context("generating the synthetic scene")?;
    bars.finish();
    let scene = &out.scene;
    let gt = scene.gt.as_ref().context("generator returned no GT")?;
    let valid = gt.mask.iter().filter(|m| **m).count();
    info!(
        pixels = scene.dims.pixels(),
        valid,
        valid_pct = 100.0 * valid as f64 / scene.dims.pixels() as f64,
        "ground truth"
    );
    if args.timings {
        for (stage, secs) in &out.timings {
            info!(stage = %stage, seconds = format!("{secs:.3}"), "timing");
        }
    }
    if args.stats {
        if let Some(ff) = &scene.ff
            && let Some(acc) = point_accuracy(&ff.points, &gt.points, &gt.mask)
        {
            info!(
                auc5 = format!("{:.1}", acc.auc5),
                auc10 = format!("{:.1}", acc.auc10),
                median_cm = format!("{:.2}", acc.median_cm),
                "ff points vs GT (trimmed LS Sim(3))"
            );
        }
        for ms in &scene.matches {
            let st = match_stats(ms, scene.dims);
            info!(matcher = %ms.matcher, score_gt_06 = format!("{:.3}", st.score_gt_06), ba_pass = format!("{:.3}", st.ba_pass), dlt_pass = format!("{:.3}", st.dlt_pass), "matches");
        }
    }
    ggpt_core::io::scene_dir::write_scene(&args.out, scene)
        .with_context(|| format!("writing scene directory {}", args.out.display()))?;
    if args.vggt_predictions {
        let ff = scene
            .ff
            .as_ref()
            .context("generator returned no feed-forward prediction")?;
        let path = args.out.join("predictions.npz");
        ggpt_core::io::feedforward::write_vggt_predictions(&path, ff, &scene.images, scene.dims)
            .with_context(|| format!("writing {}", path.display()))?;
        info!(path = %path.display(), "VGGT predictions written");
    }
    let meta = serde_json::json!({
        "generator": "ggpt-synth",
        "config": cfg,
        "ff_from_world_frame": (0..3).map(|r| (0..4).map(|c| out.ff_from_world[(r, c)]).collect::<Vec<f64>>()).collect::<Vec<_>>(),
        "gt_cam_from_world_ff_frame": out.gt_cameras_ff.cam_from_world.iter()
            .map(|m| (0..3).map(|r| (0..4).map(|c| m[(r, c)]).collect::<Vec<f64>>()).collect::<Vec<_>>()).collect::<Vec<_>>(),
    });
    let meta_path = args.out.join("synth.json");
    let text = serde_json::to_string_pretty(&meta).context("serialising synth.json")?;
    ggpt_core::io::atomic::write_atomic(&meta_path, |w| w.write_all(text.as_bytes()))
        .with_context(|| format!("writing {}", meta_path.display()))?;
    info!(dir = %args.out.display(), "scene written");
    if let Some(path) = &args.official_safetensors {
        ggpt_core::io::official::write_official_safetensors(path, scene)
            .with_context(|| format!("writing {}", path.display()))?;
        info!(file = %path.display(), "official-layout safetensors written");
    }
    Ok(())
}
