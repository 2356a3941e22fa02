//! Forward benchmark of the released configuration with random weights on surface-like chunks
//! (~30 % guidance). Prints one table row per run: tokens, device, threads, plan / upload /
//! forward seconds, peak RSS.
//!
//! ```text
//! cargo bench -p ggpt-model --bench forward -- --tokens 26000 --device flex --threads 1
//! ```
//! Peak RSS is per process: run one size per invocation for a clean memory figure.
//! `--chunks N` splits the tokens of a row over `N` chunks (different seeds) in one forward, as
//! the scene pipeline batches chunks. `--count` adds the kernel launches (wgpu, CUDA) and host
//! readbacks of every forward; `--kernel-times` also times each kernel (serialised).

use std::time::Instant;

use clap::Parser;
use ggpt_model::bench::{peak_rss_mib, pixels_for_tokens, print_device_counts, surface_chunk};
use ggpt_model::device::device_from_name;
use ggpt_model::device_stats::{KernelTiming, observe};
use ggpt_model::infer::plan_config;
use ggpt_model::plan::plan_batch;
use ggpt_model::{Ggpt, GgptConfig, PreparedBatch};

/// Forward benchmark of the GGPT network (random weights).
#[derive(Parser, Debug)]
#[command(name = "forward")]
struct Args {
    /// Level-0 tokens per row (comma separated).
    #[arg(long, value_delimiter = ',', default_value = "26000")]
    tokens: Vec<usize>,
    /// Device: `cpu`, `ndarray`, `flex`, `wgpu` (`cuda[:N]` with the `cuda` feature).
    #[arg(long, default_value = "cpu")]
    device: String,
    /// CPU threads (0: all cores).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Model preset: `released`, `small`, `tiny`.
    #[arg(long, default_value = "released")]
    preset: String,
    /// Runs per size (one row each).
    #[arg(long, default_value_t = 1)]
    repeat: usize,
    /// Chunks the tokens of a row are split over (one forward).
    #[arg(long, default_value_t = 1,
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    chunks: usize,
    /// Print the wall time per stage (`ggpt_model::profile`) to stderr after each run.
    #[arg(long)]
    profile: bool,
    /// Count the kernel launches (CubeCL backends) and host readbacks of each forward and
    /// print them after its row, with the launches per kernel to stderr.
    #[arg(long)]
    count: bool,
    /// Like `--count`, and time every kernel (runs them one at a time: the forward time of
    /// that row is not the pipelined time).
    #[arg(long)]
    kernel_times: bool,
    /// Keep the system allocator settings (no `device::tune_allocator`).
    #[arg(long)]
    default_allocator: bool,
    /// Passed by `cargo bench`; ignored.
    #[arg(long, hide = true)]
    bench: bool,
}

fn main() {
    let Args {
        tokens,
        device: device_name,
        threads,
        preset,
        repeat,
        chunks,
        profile,
        count,
        kernel_times,
        default_allocator,
        bench: _,
    } = Args::parse();
    if !default_allocator {
        ggpt_model::device::tune_allocator();
    }
    if threads > 0 {
        // SAFETY: no other thread exists yet.
        unsafe { std::env::set_var("MATMUL_NUM_THREADS", threads.to_string()) };
        if let Err(e) = ggpt_model::device::init_cpu_threads(threads) {
            eprintln!("{e}");
        }
    }
    let cfg = GgptConfig::preset(&preset).unwrap_or_else(|e| {
        eprintln!("{e}");
        std::process::exit(2)
    });
    let device = device_from_name(&device_name).unwrap_or_else(|e| {
        eprintln!("{e}");
        std::process::exit(2)
    });
    ggpt_model::profile::set_enabled(profile);
    let model = Ggpt::new(&cfg, &device);
    println!(
        "| tokens | chunks | pixels | device | threads | plan s | upload s | forward s | peak RSS MiB |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for &n in &tokens {
        let k = pixels_for_tokens(n);
        let inputs: Vec<_> = (0..chunks)
            .map(|i| surface_chunk(k / chunks, 7 + i as u64))
            .collect();
        for _ in 0..repeat {
            let t0 = Instant::now();
            let plan = match plan_batch(&inputs, &plan_config(&cfg)) {
                Ok(p) => p,
                Err(e) => {
                    eprintln!("plan: {e}");
                    std::process::exit(1)
                }
            };
            let t_plan = t0.elapsed().as_secs_f64();
            let t1 = Instant::now();
            let batch = PreparedBatch::new(&plan, &cfg, &device).unwrap_or_else(|e| {
                eprintln!("{e}");
                std::process::exit(1)
            });
            let t_up = t1.elapsed().as_secs_f64();
            let t2 = Instant::now();
            let timing = if kernel_times {
                KernelTiming::Resolved
            } else {
                KernelTiming::CountOnly
            };
            let (conf, counts) = observe(timing, || {
                let out = model.forward(&batch);
                ggpt_model::readback::read_tensor_f32(&out.tokens_conf, "tokens_conf")
            });
            let conf = conf.unwrap_or_else(|e| {
                eprintln!("forward of {n} tokens failed: {e}");
                std::process::exit(1)
            });
            let t_fwd = t2.elapsed().as_secs_f64();
            drop(conf);
            if profile {
                for e in ggpt_model::profile::take_report() {
                    eprintln!(
                        "profile {:<24} {:>8.3} s {:>5} calls",
                        e.name, e.seconds, e.calls
                    );
                }
            }
            println!(
                "| {} | {chunks} | {k} | {device_name} | {} | {t_plan:.2} | {t_up:.2} | {t_fwd:.2} | {:.0} |",
                batch.num_tokens,
                if threads == 0 {
                    "all".to_string()
                } else {
                    threads.to_string()
                },
                peak_rss_mib()
            );
            if count || kernel_times {
                print_device_counts(&counts, kernel_times);
            }
        }
    }
}
