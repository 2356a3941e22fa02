//! `ggpt-infer`: run the GGPT network.
//!
//! Subcommands:
//! * `chunk` — run the network on prepared chunk records (safetensors in, safetensors out).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand};
use ggpt_model::chunk_io::{chunk_outputs_to_bytes, read_chunk_inputs};
use ggpt_model::device::device_from_name;
use ggpt_model::infer::prepare_chunks;
use ggpt_model::weights::load_checkpoint;
use ggpt_model::{Ggpt, GgptConfig};
use tracing::info;

/// GGPT inference.
#[derive(Parser, Debug)]
#[command(name = "ggpt-infer", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run the network on chunk records: reads `chunk{c}/ff_pts`, `ff_pts_conf`, `geo_pts`,
    /// `geo_msks` (normalised chunk coordinates) and writes `chunk{c}/ff_pts_out`,
    /// `ff_pts_conf_out`, `geo_pts_out`, `geo_pts_conf_out`, `tokens_xyz_out`, `tokens_conf_out`.
    /// Each chunk is one forward (batch size 1, as the official inference); timing per chunk
    /// goes to stderr.
    Chunk(ChunkArgs),
}

/// Options of `ggpt-infer chunk`.
#[derive(Args, Debug)]
struct ChunkArgs {
    /// Model configuration JSON (the official `model_config` object, or a file with a
    /// `model_config` key such as a fixture manifest). Conflicts with `--preset`.
    #[arg(long, conflicts_with = "preset")]
    model_config: Option<PathBuf>,
    /// Built-in configuration: `released` (53.4 M parameters), `small` (fixture) or `tiny`.
    #[arg(long)]
    preset: Option<String>,
    /// Weights: official `.pth` / `.safetensors`, or a burnpack `.bpk` of this project.
    #[arg(long)]
    weights: PathBuf,
    /// Input chunk records (safetensors).
    #[arg(long)]
    input: PathBuf,
    /// Output file (safetensors), written atomically.
    #[arg(long)]
    output: PathBuf,
    /// Compute device: `cpu` (fastest CPU backend), `ndarray`, `flex` or `wgpu`.
    #[arg(long, default_value = "cpu")]
    device: String,
    /// CPU threads for the backends (0 = all cores).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Run all chunks in one batched forward instead of one forward per chunk.
    #[arg(long)]
    batched: bool,
}

fn main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .init();
    let cli = Cli::parse();
    match cli.command {
        Command::Chunk(args) => run_chunk(args),
    }
}

fn run_chunk(args: ChunkArgs) -> Result<()> {
    if args.threads > 0 {
        // SAFETY: called before any other thread of this process exists (the thread pools of
        // the backends are created lazily afterwards); matrixmultiply reads it once.
        unsafe { std::env::set_var("MATMUL_NUM_THREADS", args.threads.to_string()) };
        rayon::ThreadPoolBuilder::new()
            .num_threads(args.threads)
            .build_global()
            .context("configuring the thread pool")?;
    }
    let cfg = match (&args.model_config, &args.preset) {
        (Some(path), _) => GgptConfig::from_json_file(path)?,
        (None, Some(name)) => GgptConfig::preset(name)?,
        (None, None) => bail!("give --model-config FILE or --preset released|small|tiny"),
    };
    let device = device_from_name(&args.device)?;
    let t0 = Instant::now();
    let model = load_checkpoint(Ggpt::new(&cfg, &device), &args.weights)
        .with_context(|| format!("loading weights {}", args.weights.display()))?;
    info!("loaded {} in {:.2} s", args.weights.display(), t0.elapsed().as_secs_f64());
    let chunks = read_chunk_inputs(&args.input).with_context(|| format!("reading {}", args.input.display()))?;
    info!("{} chunk(s) from {}", chunks.len(), args.input.display());
    let mut outputs = Vec::with_capacity(chunks.len());
    let groups: Vec<&[ggpt_model::plan::ChunkInput]> =
        if args.batched { vec![&chunks[..]] } else { chunks.chunks(1).collect() };
    let mut first = 0;
    for group in groups {
        let t = Instant::now();
        let batch = prepare_chunks(&cfg, group, &device).with_context(|| format!("planning chunk {first}"))?;
        let t_plan = t.elapsed().as_secs_f64();
        let out = model.forward(&batch).to_chunks(&batch)?;
        let total = t.elapsed().as_secs_f64();
        let tokens: usize = batch.num_tokens;
        eprintln!(
            "chunk {first}{}: {tokens} tokens, plan {t_plan:.3} s, total {total:.3} s",
            if group.len() > 1 { format!("..{}", first + group.len() - 1) } else { String::new() }
        );
        first += group.len();
        outputs.extend(out);
    }
    let bytes = chunk_outputs_to_bytes(&outputs)?;
    ggpt_core::io::atomic::write_bytes_atomic(&args.output, &bytes)
        .with_context(|| format!("writing {}", args.output.display()))?;
    info!("wrote {}", args.output.display());
    Ok(())
}
