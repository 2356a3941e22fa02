//! Training-step benchmark: optimisation steps (forward in training mode + loss + backward +
//! Adam) on surface-like chunks shaped like the fixture's clouds (~30 % guidance, GT a small
//! perturbation of the dense points). Prints one table row per (config, tokens, batch):
//! seconds per step, chunks/s, tokens/s, peak RSS.
//!
//! ```text
//! cargo bench -p ggpt-train --bench train -- --config small --tokens 20000 --batch 4
//! ```
//!
//! Peak RSS is the process's `VmHWM`, reset before each row (Linux). With `--count` (or
//! `--kernel-times`, which also times every kernel and so serialises them) each timed step's
//! kernel launches and host readbacks are printed after the row (CubeCL devices: wgpu, cuda).

use std::time::Instant;

use anyhow::{Context, Result, bail};
use burn::module::Module;
use clap::Parser;
use ggpt_model::bench::{
    peak_rss_mib, pixels_for_tokens, print_device_counts, reset_peak_rss, surface_chunk,
};
use ggpt_model::device_stats::{KernelTiming, observe};
use ggpt_model::{Ggpt, GgptConfig};
use ggpt_train::chunkset::TrainChunk;
use ggpt_train::trainer::{Recompute, StepPlan, adam, parallel_step};

/// Benchmark of GGPT training steps.
#[derive(Parser, Debug)]
#[command(name = "train", about)]
struct Args {
    /// Model configurations (presets `released`, `small`, `tiny`).
    #[arg(long, value_delimiter = ',', default_value = "small")]
    config: Vec<String>,
    /// Tokens per chunk (dense + DLT), one row each.
    #[arg(long, value_delimiter = ',', default_value = "20000")]
    tokens: Vec<usize>,
    /// Chunks per step (one forward).
    #[arg(long, value_delimiter = ',', default_value = "4")]
    batch: Vec<usize>,
    /// Timed steps per row (after one untimed warm-up step).
    #[arg(long, default_value_t = 3)]
    steps: usize,
    /// Device: `cpu`, `ndarray`, `flex`, `wgpu`.
    #[arg(long, default_value = "cpu")]
    device: String,
    /// Data-parallel replicas, one per listed device (e.g. `cpu,cpu`), instead of --device:
    /// the batch is split across them as `ggpt-train train --devices` does.
    #[arg(long, value_delimiter = ',')]
    devices: Option<Vec<String>>,
    /// Micro-batches per replica (`ggpt-train train --grad-accum`).
    #[arg(long, default_value_t = 1)]
    grad_accum: usize,
    /// Gradient computation, one row each: `segments` (recomputation) and/or `off` (plain
    /// autodiff).
    #[arg(long, value_delimiter = ',', default_value = "segments")]
    recompute: Vec<String>,
    /// CPU threads (0: all cores).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Print, after each row, the wall time of the step's phases summed over its timed steps
    /// (`ggpt_model::profile`: recomputation forward / backward per segment kind, host attention
    /// core), to stderr. Eager CPU backends only.
    #[arg(long)]
    profile: bool,
    /// Count each timed step's kernel launches and host readbacks
    /// (`ggpt_model::device_stats`); the launches per kernel go to stderr.
    #[arg(long)]
    count: bool,
    /// As `--count`, and time every kernel (serialised: the step's wall time grows); the
    /// slowest kernels go to stderr.
    #[arg(long)]
    kernel_times: bool,
    /// Passed by `cargo bench`; ignored.
    #[arg(long, hide = true)]
    bench: bool,
}

/// A training chunk: the benchmark surface as input, GT 1 % off the dense points.
fn train_chunk(pixels: usize, seed: u64) -> TrainChunk {
    let c = surface_chunk(pixels, seed);
    let gt_pts = c
        .ff_pts
        .iter()
        .map(|p| [p[0] * 0.99, p[1] * 0.99 + 0.01, p[2] * 1.01])
        .collect();
    TrainChunk {
        scene: 0,
        center: [0.0; 3],
        radius: 1.0,
        pixels: (0..pixels as u32).collect(),
        gt_msk: vec![true; pixels],
        gt_pts,
        input: c,
    }
}

fn main() -> Result<()> {
    ggpt_model::device::tune_allocator();
    let args = Args::parse();
    if args.steps == 0 {
        bail!("--steps must be at least 1");
    }
    if args.threads > 0 {
        // SAFETY: no other thread exists yet.
        unsafe { std::env::set_var("MATMUL_NUM_THREADS", args.threads.to_string()) };
        ggpt_model::device::init_cpu_threads(args.threads)?;
    }
    let names = args
        .devices
        .clone()
        .unwrap_or_else(|| vec![args.device.clone()]);
    if names.is_empty() || args.grad_accum == 0 {
        bail!("--devices needs at least one device and --grad-accum at least 1");
    }
    let replicas: Vec<burn::tensor::Device> = names
        .iter()
        .map(|n| ggpt_model::device::device_from_name(n).map(|d| d.autodiff()))
        .collect::<std::result::Result<_, _>>()?;
    let device = replicas[0].clone().without_autodiff();
    let ad = replicas[0].clone();
    let device_label = if names.len() > 1 || args.grad_accum > 1 {
        format!("{} x{}", names.join(","), args.grad_accum)
    } else {
        names[0].clone()
    };
    let timing = if args.kernel_times {
        KernelTiming::Resolved
    } else {
        KernelTiming::CountOnly
    };
    let modes: Vec<Recompute> = args
        .recompute
        .iter()
        .map(|m| {
            m.parse::<Recompute>()
                .map_err(|e| anyhow::anyhow!("--recompute {m}: {e}"))
        })
        .collect::<Result<_>>()?;
    println!(
        "| config | parameters | tokens / chunk | batch | device | threads | recompute | s / step | chunks / s | tokens / s | peak RSS MiB | KB / token above 1 GB |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    for name in &args.config {
        let cfg = GgptConfig::preset(name)?;
        for &tokens in &args.tokens {
            for &batch in &args.batch {
                for &mode in &modes {
                    let chunks: Vec<TrainChunk> = (0..batch)
                        .map(|b| train_chunk(pixels_for_tokens(tokens), 7 + b as u64))
                        .collect();
                    let refs: Vec<&TrainChunk> = chunks.iter().collect();
                    let n_tokens: usize = chunks.iter().map(TrainChunk::num_tokens).sum();
                    reset_peak_rss();
                    device.seed(42);
                    let mut model = Ggpt::new(&cfg, &device).fork(&ad).train();
                    let params = ggpt_model::weights::num_trainable_params(&model);
                    let mut optim = adam();
                    let mut secs = Vec::with_capacity(args.steps);
                    let mut step_counts = Vec::with_capacity(args.steps);
                    for s in 0..=args.steps {
                        // the warm-up step is not profiled
                        ggpt_model::profile::set_enabled(args.profile && s > 0);
                        let t = Instant::now();
                        let plan = StepPlan {
                            devices: &replicas,
                            grad_accum: args.grad_accum,
                            drop_path_seed: Some(s as u64),
                            recompute: mode,
                        };
                        let (step, counts) = observe(timing, || {
                            parallel_step(model, &mut optim, &cfg, &refs, 1e-4, None, &plan)
                        });
                        let (m, loss) = step.with_context(|| format!("{name}: step {s}"))?;
                        model = m;
                        if s > 0 {
                            secs.push(t.elapsed().as_secs_f64());
                            step_counts.push(counts);
                        }
                        tracing::debug!("step {s}: loss {:.4}", loss.total);
                    }
                    ggpt_model::profile::set_enabled(false);
                    if args.profile {
                        for e in ggpt_model::profile::take_report() {
                            eprintln!(
                                "profile {name} {tokens} {mode:?} {:<32} {:>9.3} s {:>6} calls",
                                e.name, e.seconds, e.calls
                            );
                        }
                    }
                    let mean = secs.iter().sum::<f64>() / secs.len() as f64;
                    let peak = peak_rss_mib();
                    println!(
                        "| {name} | {params} | {} | {batch} | {} | {} | {} | {mean:.2} | {:.2} | {:.0} | {peak:.0} | {:.0} |",
                        n_tokens / batch,
                        device_label,
                        if args.threads == 0 {
                            "all".to_string()
                        } else {
                            args.threads.to_string()
                        },
                        format!("{mode:?}").to_lowercase(),
                        batch as f64 / mean,
                        n_tokens as f64 / mean,
                        ((peak - 1024.0) * 1024.0 / n_tokens as f64).max(0.0)
                    );
                    if args.count || args.kernel_times {
                        for c in &step_counts {
                            print_device_counts(c, args.kernel_times);
                        }
                    }
                }
            }
        }
    }
    Ok(())
}
