//! Whole-scene benchmark (`cargo bench -p ggpt-infer --bench infer -- [options]`):
//! for each view count, a synthetic room (`ggpt-synth`, 518 x 392 by default) goes through
//! SfM, pre-alignment + chunking, the network (released configuration, random weights unless
//! `--weights`), records + fusion, export and evaluation. Prints wall time and peak resident
//! memory per stage (peak RSS reset at every stage start, Linux `VmHWM`).
//!
//! The released network is slow on CPU; `--network-budget-s S` caps the network time per scene:
//! once the budget is spent, the remaining chunks bypass the network (their input points are
//! passed through) and the table reports the measured network time *and* an extrapolation to
//! all tokens (measured seconds per token × total tokens), clearly marked.
//!
//! Logs go to stderr at `RUST_LOG` level (default `info`); `RUST_LOG=warn cargo bench ...` keeps
//! only the table and warnings.

use std::time::Instant;

use anyhow::{Context, Result};
use clap::Parser;
use ggpt_infer::pipeline::{MeasuredRefiner, RunOptions, run_scene};
use ggpt_infer::refiner::{BurnRefiner, RefinerStats};
use ggpt_infer::rss::StageLog;
use ggpt_model::device::device_from_name;
use ggpt_model::{Ggpt, GgptConfig};
use ggpt_scene::driver::RefinedChunk;
use ggpt_scene::{ChunkRecord, ChunkRefiner, SceneError};
use ggpt_synth::{SynthConfig, generate};

/// Benchmark options.
#[derive(Parser, Debug)]
#[command(name = "infer", about)]
struct Args {
    /// View counts to run.
    #[arg(long, value_delimiter = ',', default_value = "4,8,16")]
    views: Vec<usize>,
    /// Feed-forward width.
    #[arg(long, default_value_t = 518)]
    width: usize,
    /// Feed-forward height.
    #[arg(long, default_value_t = 392)]
    height: usize,
    /// Model preset (random weights): `released`, `small`, `tiny`.
    #[arg(long, default_value = "released")]
    preset: String,
    /// Device: `cpu`, `ndarray`, `flex`, `wgpu`.
    #[arg(long, default_value = "cpu")]
    device: String,
    /// Token budget of one forward.
    #[arg(long, default_value_t = ggpt_scene::driver::DEFAULT_MAX_TOKENS_PER_FORWARD)]
    max_tokens_per_forward: usize,
    /// Network time budget per scene in seconds (0 = unlimited); see the module docs.
    #[arg(long, default_value_t = 0.0)]
    network_budget_s: f64,
    /// Seed.
    #[arg(long, default_value_t = 42)]
    seed: u64,
    /// Output folder for the exports (a temporary folder when absent).
    #[arg(long)]
    out: Option<std::path::PathBuf>,
    /// Passed by `cargo bench`; ignored.
    #[arg(long, hide = true)]
    bench: bool,
}

/// Runs the real network until the budget is spent, then passes inputs through.
struct Budgeted {
    inner: BurnRefiner,
    budget_s: f64,
    spent_s: f64,
    skipped_tokens: usize,
    skipped_chunks: usize,
}

impl ChunkRefiner for Budgeted {
    fn refine(&mut self, chunks: &[ChunkRecord]) -> Result<Vec<RefinedChunk>, SceneError> {
        if self.budget_s > 0.0 && self.spent_s >= self.budget_s {
            self.skipped_tokens += chunks.iter().map(ChunkRecord::num_tokens).sum::<usize>();
            self.skipped_chunks += chunks.len();
            return Ok(chunks
                .iter()
                .map(|c| RefinedChunk {
                    points: c.ff_pts.clone(),
                    conf: vec![1.0; c.len()],
                })
                .collect());
        }
        let t = Instant::now();
        let out = self.inner.refine(chunks);
        self.spent_s += t.elapsed().as_secs_f64();
        out
    }
}

impl MeasuredRefiner for Budgeted {
    fn take_stats(&mut self) -> RefinerStats {
        self.inner.take_stats()
    }
}

fn main() -> Result<()> {
    ggpt_model::device::tune_allocator();
    ggpt_cli::init_logging(false);
    let args = Args::parse();
    let cfg = GgptConfig::preset(&args.preset)?;
    let device = device_from_name(&args.device)?;
    let model = Ggpt::new(&cfg, &device);
    let inner = BurnRefiner::new(model, cfg, device)?.with_rss_stages(true);
    let mut refiner = Budgeted {
        inner,
        budget_s: args.network_budget_s,
        spent_s: 0.0,
        skipped_tokens: 0,
        skipped_chunks: 0,
    };
    let tmp = tempfile::tempdir()?;
    let base = args.out.clone().unwrap_or_else(|| tmp.path().to_path_buf());
    println!(
        "infer bench: preset {} (random weights), device {}, {}x{}, max {} tokens/forward, network budget {}",
        args.preset,
        args.device,
        args.width,
        args.height,
        args.max_tokens_per_forward,
        if args.network_budget_s > 0.0 {
            format!("{} s/scene", args.network_budget_s)
        } else {
            "none".into()
        }
    );
    for &views in &args.views {
        refiner.spent_s = 0.0;
        refiner.skipped_tokens = 0;
        refiner.skipped_chunks = 0;
        let mut log = StageLog::new();
        log.start("synth");
        let synth = generate(&SynthConfig {
            views,
            width: args.width,
            height: args.height,
            seed: args.seed,
            matches: true,
            ..SynthConfig::default()
        })
        .context("synthesising")?;
        let mut scene = synth.scene;
        log.finish();
        let mut opts = RunOptions::default();
        opts.refine.seed = args.seed;
        opts.refine.max_tokens_per_forward = args.max_tokens_per_forward;
        opts.export.seed = args.seed;
        let out = base.join(format!("views{views}"));
        let report = run_scene(
            &mut scene,
            &mut refiner,
            &opts,
            &out,
            &serde_json::json!({"bench": true}),
            serde_json::json!({}),
            &mut log,
            &mut ggpt_core::progress::ignore,
        )?;
        let net = &report.network;
        println!(
            "\n{views} views: {} chunks, {} tokens, {} forwards run ({} tokens through the network, {} chunks / {} tokens bypassed)",
            report.refined.chunks.len(),
            report.refined.total_tokens,
            net.forwards,
            net.tokens,
            refiner.skipped_chunks,
            refiner.skipped_tokens
        );
        println!("{:<20} {:>10} {:>14}", "stage", "seconds", "peak RSS MiB");
        for s in &report.stages {
            let m = s
                .peak_rss_mib
                .map_or("-".to_string(), |m| format!("{m:.0}"));
            println!("{:<20} {:>10.3} {:>14}", s.stage, s.seconds, m);
        }
        if refiner.skipped_tokens > 0 && net.tokens > 0 {
            let per_token = net.network_seconds() / net.tokens as f64;
            println!(
                "network (extrapolated to all {} tokens at {:.3} ms/token): {:.0} s",
                report.refined.total_tokens,
                1e3 * per_token,
                per_token * report.refined.total_tokens as f64
            );
        }
        if let Some(e) = &report.evaluation {
            println!(
                "AUC@5 cm: ff {:.2}, refined {:.2} (random weights: not meaningful)",
                e.ff.auc_5, e.refined.auc_5
            );
        }
    }
    Ok(())
}
