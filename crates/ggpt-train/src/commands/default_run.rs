//! `ggpt-train` without a command: a small synthetic chunk set and a few steps of the tiny
//! configuration (a demonstration of the whole loop, seconds to a few minutes on CPU).

use std::path::Path;
use std::time::Instant;

use anyhow::Result;
use ggpt_cli::{ChunkingArgs, DeviceArgs, ModelArgs, ModelPreset, RegimeArg, SceneKindArg};

use crate::cli::{LrScheduleArg, PrepareArgs, SynthArgs, TrainArgs};

/// Runs the demonstration into `out` (`chunkset/` and `run/`).
pub fn run(out: &Path) -> Result<()> {
    println!(
        "ggpt-train without arguments: building a small synthetic chunk set and training the tiny configuration"
    );
    println!("(see `ggpt-train --help` for the real commands)");
    let data = out.join("chunkset");
    let prep = PrepareArgs {
        out: data.clone(),
        synthetic_train: 3,
        synthetic_val: 1,
        synth: SynthArgs {
            first_seed: 1,
            views: vec![3],
            width: 98,
            height: 70,
            kinds: vec![SceneKindArg::Room, SceneKindArg::Object],
            regime: RegimeArg::default(),
        },
        official: Vec::new(),
        val_fraction: 0.0,
        chunks_per_scene: 4,
        shard_chunks: 64,
        seed: 42,
        chunking: ChunkingArgs {
            chunk_size: None,
            max_chunk_pixels: Some(1500),
            min_chunk_dlt: Some(20),
            min_chunk_pixels: Some(200),
        },
    };
    let t = Instant::now();
    super::prepare::run(&prep)?;
    tracing::info!("prepared in {:.1} s", t.elapsed().as_secs_f64());
    super::train::run(&TrainArgs {
        data,
        out: out.join("run"),
        model: ModelArgs {
            preset: Some(ModelPreset::Tiny),
            ..ModelArgs::default()
        },
        init_from: None,
        drop_path: None,
        bn_momentum: None,
        steps: 20,
        batch_size: 2,
        lr: 1e-3,
        lr_schedule: LrScheduleArg::Constant,
        warmup_steps: 0,
        clip_grad_norm: None,
        seed: 42,
        save_every: 10,
        val_every: 10,
        val_chunks: 8,
        val_max_tokens: 200_000,
        keep_checkpoints: 2,
        device: DeviceArgs::default(),
        devices: None,
        grad_accum: None,
        recompute: None,
        resume: None,
        export_to: None,
    })
}
