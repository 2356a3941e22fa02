//! Argument definitions of the `ggpt-train` binary (binary-only code). The shared groups
//! (model, device, chunk sampler, progress) come from `ggpt-cli`, so every binary spells a
//! setting the same way; older spellings stay as hidden aliases (`docs/training.md`).

use std::path::PathBuf;

use anyhow::{Result, bail};
use clap::{Args, Parser, Subcommand, ValueEnum};
use ggpt_cli::{
    ChunkingArgs, DeviceArg, DeviceArgs, ModelArgs, ProgressArgs, RegimeArg, SceneKindArg,
};
use ggpt_train::scene_source::SynthSpec;
use ggpt_train::trainer::{LrSchedule, Recompute};
use serde::Serialize;

/// Train GGPT on curated chunk sets (synthetic or official per-sequence data).
#[derive(Parser, Debug)]
#[command(name = "ggpt-train", version, about, long_about = None)]
pub struct Cli {
    /// The command; without one, a small demonstration run (prepare + train the tiny
    /// configuration for a few steps).
    #[command(subcommand)]
    pub command: Option<Command>,
    /// Output directory of the no-argument demonstration run.
    #[arg(long, default_value = "ggpt-train-default")]
    pub out: PathBuf,
    #[command(flatten)]
    pub progress: ProgressArgs,
}

/// The commands.
#[derive(Subcommand, Debug)]
pub enum Command {
    /// Build a chunk set (sharded safetensors + manifest) from synthetic scenes and/or official
    /// per-sequence directories.
    Prepare(PrepareArgs),
    /// Train on a chunk set.
    Train(TrainArgs),
    /// Evaluate a model on the held-out (val) scenes of a chunk set: whole-scene refinement
    /// through the scene pipeline, AUC@5/10 cm of the feed-forward input vs the refined points.
    Eval(EvalArgs),
    /// Export a checkpoint as official `model.safetensors` + `model_config.json`.
    Export(ExportArgs),
    /// Plot `metrics.jsonl` as a PNG training curve.
    Plot(PlotArgs),
    /// One training step made visible, for verification against a reference: per input case
    /// (its own batch, from the loaded weights, train mode, drop path 0) the loss terms, the
    /// train-mode outputs, the gradient of every parameter under its official name and the
    /// BatchNorm running statistics after the forward; optionally the parameters after one
    /// Adam step from case 0. See docs/training.md.
    Grads(GradsArgs),
}

/// Synthetic scene options (`ggpt-synth`) shared by `prepare` and `eval`.
#[derive(Args, Debug, Clone, Serialize)]
pub struct SynthArgs {
    /// First synthetic seed (scene i gets first_seed + i).
    #[arg(long, default_value_t = 1000)]
    pub first_seed: u64,
    /// Views per synthetic scene; a list (`4,8`) is cycled over the scenes (after the kinds:
    /// scene `i` gets kind `i % kinds` and views `(i / kinds) % views`).
    #[arg(long, value_delimiter = ',', default_value = "4")]
    pub views: Vec<usize>,
    /// Synthetic ff width (multiple of 14).
    #[arg(long, default_value_t = 154)]
    pub width: usize,
    /// Synthetic ff height (multiple of 14).
    #[arg(long, default_value_t = 112)]
    pub height: usize,
    /// Synthetic scene kinds, alternated by seed.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "room,object")]
    pub kinds: Vec<SceneKindArg>,
    /// Simulation regime of the synthetic scenes: `benchmark` (matcher failure modes and
    /// structured feed-forward error, the paper's ranges) or `easy` (the first, dense and clean
    /// regime; docs/synthetic.md).
    #[arg(long, value_enum, default_value_t)]
    pub regime: RegimeArg,
}

impl SynthArgs {
    /// The spec of synthetic scene `i`.
    pub fn spec(&self, i: usize) -> Result<SynthSpec> {
        if self.kinds.is_empty() {
            bail!("--kinds is empty");
        }
        if self.views.is_empty() || self.views.iter().any(|&v| v < 2) {
            bail!(
                "--views {:?}: every entry must be at least 2 (SfM needs two views)",
                self.views
            );
        }
        let kind = ggpt_synth::SceneKind::parse(self.kinds[i % self.kinds.len()].name())?;
        let views = self.views[(i / self.kinds.len()) % self.views.len()];
        Ok(SynthSpec {
            kind,
            views,
            width: self.width,
            height: self.height,
            seed: self.first_seed + i as u64,
            regime: ggpt_synth::Regime::parse(self.regime.name())?,
        })
    }
}

/// Options of `ggpt-train prepare`.
#[derive(Args, Debug)]
pub struct PrepareArgs {
    /// Output chunk-set directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Synthetic training scenes to generate (seeds first_seed, first_seed + 1, ...).
    #[arg(long, default_value_t = 0)]
    pub synthetic_train: usize,
    /// Synthetic validation (held-out) scenes, seeds following the training seeds.
    #[arg(long, default_value_t = 0)]
    pub synthetic_val: usize,
    #[command(flatten)]
    pub synth: SynthArgs,
    /// Official per-sequence directories (gt.bin, ff_outputs.bin, sfm_dlt_outputs.bin).
    #[arg(long, num_args = 1..)]
    pub official: Vec<PathBuf>,
    /// Fraction of the official directories held out for validation (split by scene, the last
    /// ones).
    #[arg(long, default_value_t = 0.1)]
    pub val_fraction: f64,
    /// Chunks drawn per scene.
    #[arg(long, default_value_t = 16)]
    pub chunks_per_scene: usize,
    /// Chunks per shard.
    #[arg(long, default_value_t = 64)]
    pub shard_chunks: usize,
    /// Seed of the RANSAC and chunk draws (combined with each scene name).
    #[arg(long, default_value_t = 42)]
    pub seed: u64,
    /// Chunk sampler flags (unset ones take the official defaults).
    #[command(flatten)]
    pub chunking: ChunkingArgs,
}

/// `--lr-schedule` ([`LrSchedule`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum LrScheduleArg {
    /// Constant learning rate (paper default).
    Constant,
    /// Linear warm-up, then cosine decay to 0 at the last step.
    Cosine,
}

impl From<LrScheduleArg> for LrSchedule {
    fn from(a: LrScheduleArg) -> Self {
        match a {
            LrScheduleArg::Constant => LrSchedule::Constant,
            LrScheduleArg::Cosine => LrSchedule::Cosine,
        }
    }
}

/// `--recompute` ([`Recompute`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum RecomputeArg {
    /// Segment recomputation: keeps only block-boundary tensors (a few KB per token).
    Segments,
    /// Plain autodiff: every intermediate kept (~1.4 MB per token, released configuration).
    Off,
}

impl From<RecomputeArg> for Recompute {
    fn from(a: RecomputeArg) -> Self {
        match a {
            RecomputeArg::Segments => Recompute::Segments,
            RecomputeArg::Off => Recompute::Off,
        }
    }
}

/// Value of a bare `--resume`: the newest complete checkpoint in `--out`.
pub const RESUME_LATEST: &str = "latest";

/// Options of `ggpt-train train`.
#[derive(Args, Debug, Clone)]
pub struct TrainArgs {
    /// Chunk-set directory (from `prepare`).
    #[arg(long)]
    pub data: PathBuf,
    /// Output directory (metrics.jsonl, config.json, checkpoints/).
    #[arg(long)]
    pub out: PathBuf,
    /// The network: `--preset` (default `small`) or `--model-config FILE`; `--weights` an
    /// official checkpoint (.pth / .safetensors / .bpk) or model folder to fine-tune from.
    #[command(flatten)]
    pub model: ModelArgs,
    /// Old spelling of `--weights` for fine-tuning.
    #[arg(long, hide = true, conflicts_with = "weights")]
    pub init_from: Option<PathBuf>,
    /// Maximum drop-path rate (network.md §11.3; overrides the config's 0.3).
    #[arg(long)]
    pub drop_path: Option<f64>,
    /// BatchNorm momentum of the running statistics (PyTorch convention; overrides the
    /// config's 0.01). Short runs want a larger value (e.g. 0.1): with 0.01 the running
    /// statistics that evaluation uses need several hundred steps to follow the weights.
    #[arg(long)]
    pub bn_momentum: Option<f64>,
    /// Total optimisation steps.
    #[arg(long, default_value_t = 1000)]
    pub steps: u64,
    /// Chunks per forward (paper: 24).
    #[arg(long, default_value_t = 4)]
    pub batch_size: usize,
    /// Adam learning rate (paper: 1e-4).
    #[arg(long, default_value_t = 1e-4)]
    pub lr: f64,
    /// Learning-rate schedule.
    #[arg(long, value_enum, default_value_t = LrScheduleArg::Constant)]
    pub lr_schedule: LrScheduleArg,
    /// Linear warm-up steps of the cosine schedule.
    #[arg(long, default_value_t = 0)]
    pub warmup_steps: u64,
    /// Clip the global gradient norm to this value (off by default).
    #[arg(long)]
    pub clip_grad_norm: Option<f64>,
    /// Seed of initialisation, batches and drop path.
    #[arg(long, default_value_t = 42)]
    pub seed: u64,
    /// Write a checkpoint every N steps (and always at exit).
    #[arg(long, default_value_t = 100)]
    pub save_every: u64,
    /// Validate on held-out chunks every N steps (0: only at the end).
    #[arg(long, default_value_t = 100)]
    pub val_every: u64,
    /// Validation chunks used (at most).
    #[arg(long, default_value_t = 64)]
    pub val_chunks: usize,
    /// Token budget of one validation forward.
    #[arg(long, default_value_t = 200_000)]
    pub val_max_tokens: usize,
    /// Checkpoints kept on disk.
    #[arg(long, default_value_t = 3)]
    pub keep_checkpoints: usize,
    #[command(flatten)]
    pub device: DeviceArgs,
    /// Data-parallel replicas, one per listed device, main device first (e.g. `cpu,cpu` or
    /// `wgpu:0,wgpu:1`): the batch is split across them, gradients are averaged on the main
    /// device (docs/training.md). Overrides --device. Default: one replica on --device (on
    /// resume: the devices recorded in the checkpoint).
    #[arg(long, value_delimiter = ',')]
    pub devices: Option<Vec<DeviceArg>>,
    /// Gradient accumulation: micro-batches per replica and step (the batch is split into
    /// replicas x K parts; BatchNorm sees each part's statistics). Default 1 (on resume: the
    /// checkpoint's).
    #[arg(long)]
    pub grad_accum: Option<usize>,
    /// Gradient computation: `segments` (default) re-runs each block segment in the backward
    /// and keeps only block-boundary tensors (a few KB per token: the released configuration
    /// trains 100k-token chunks in ~10 GB); `off` keeps every intermediate (plain autodiff,
    /// ~1.4 MB per token released). Same gradients up to float rounding (docs/training.md).
    /// Default `segments` (on resume: the checkpoint's).
    #[arg(long, value_enum)]
    pub recompute: Option<RecomputeArg>,
    /// Resume: a bare `--resume` (or `--resume latest`) takes the newest complete checkpoint in
    /// `--out`; `--resume DIR` that checkpoint directory.
    #[arg(long, num_args = 0..=1, default_missing_value = RESUME_LATEST, value_name = "DIR|latest")]
    pub resume: Option<PathBuf>,
    /// Write `model.safetensors` + `model_config.json` of the final model into this directory.
    #[arg(long)]
    pub export_to: Option<PathBuf>,
}

impl TrainArgs {
    /// The weights to fine-tune from (`--weights`, or its old spelling `--init-from`).
    pub fn init_weights(&self) -> Option<&PathBuf> {
        self.model.weights.as_ref().or(self.init_from.as_ref())
    }

    /// The replica devices as given (`--devices`, else `--device`).
    pub fn device_names(&self) -> Result<Vec<String>> {
        match &self.devices {
            Some(list) if list.is_empty() => bail!("--devices: empty list"),
            Some(list) => Ok(list.iter().map(ToString::to_string).collect()),
            None => Ok(vec![self.device.device.to_string()]),
        }
    }
}

/// Options of `ggpt-train eval`.
#[derive(Args, Debug)]
pub struct EvalArgs {
    /// Chunk-set directory whose val scenes are evaluated (synthetic scenes are regenerated
    /// from their recorded spec, official ones read from their directory).
    #[arg(
        long,
        required_unless_present = "synthetic_scenes",
        conflicts_with = "synthetic_scenes"
    )]
    pub data: Option<PathBuf>,
    /// Evaluate on this many freshly generated synthetic scenes instead (seeds `--first-seed`,
    /// `+1`, ...; choose seeds no training set used).
    #[arg(long)]
    pub synthetic_scenes: Option<usize>,
    #[command(flatten)]
    pub synth: SynthArgs,
    /// The model: `--weights` a model folder (model.safetensors + model_config.json [+
    /// inference.json]), a run or checkpoint directory (state.json + model.bpk), or a weight
    /// file with `--model-config` / `--preset`. `--model` is the old spelling of `--weights`.
    #[command(flatten)]
    pub model: ModelArgs,
    #[command(flatten)]
    pub device: DeviceArgs,
    /// Token budget of one forward.
    #[arg(long, default_value_t = 200_000)]
    pub max_tokens_per_forward: usize,
    /// Write the per-scene results here (JSON).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Chunk-level validation instead of whole scenes: the network on the first N recorded
    /// val chunks of `--data` (as during training; fast), AUC@5/10 cm of input vs refined.
    #[arg(long, requires = "data")]
    pub chunk_level: Option<usize>,
    /// Chunk sampler flags; a flag that is not given comes from the model's training sampler
    /// (inference.json or the checkpoint's chunk set), else the official default.
    #[command(flatten)]
    pub chunking: ChunkingArgs,
}

/// Options of `ggpt-train export`.
#[derive(Args, Debug)]
pub struct ExportArgs {
    /// Checkpoint directory (state.json + model.bpk), or a run directory (newest checkpoint).
    #[arg(long)]
    pub checkpoint: PathBuf,
    /// Output model folder: model.safetensors (official keys), model_config.json and, when the
    /// training chunk set is readable, inference.json with its chunk sampler settings.
    #[arg(long)]
    pub out_dir: PathBuf,
    /// Re-estimate the BatchNorm running statistics before exporting: this many training-mode
    /// forwards (no update, drop path off) over batches of the training split, averaged
    /// ("precise BN"; 0 = keep the checkpoint's running statistics).
    #[arg(long, default_value_t = 0)]
    pub bn_recalibrate_batches: usize,
    /// Chunks per recalibration forward (default: the run's batch size).
    #[arg(long)]
    pub bn_recalibrate_batch_size: Option<usize>,
}

/// Options of `ggpt-train grads`.
#[derive(Args, Debug)]
pub struct GradsArgs {
    /// The network: `--weights` (official `.pth` / `.safetensors` or a project `.bpk`) with
    /// `--model-config FILE` or `--preset NAME`.
    #[command(flatten)]
    pub model: ModelArgs,
    /// Input cases (safetensors): `case{K}/ff_pts`, `ff_pts_conf`, `geo_pts`, `geo_msks`,
    /// `gt_pts`, `gt_msks`, normalised chunk coordinates.
    #[arg(long)]
    pub input: PathBuf,
    /// Output (safetensors, written atomically): `case{K}/loss`, `l_conf`, `l_id`,
    /// `ff_pts_out`, `ff_pts_conf_out`, `grad/<name>`, `bn_after/<name>.running_mean|running_var`
    /// and, with --adam-step-lr, `case0/after_adam/<name>`.
    #[arg(long)]
    pub output: PathBuf,
    #[command(flatten)]
    pub device: DeviceArgs,
    /// After the case-0 backward, take one Adam step (betas 0.9 / 0.999, eps 1e-8, PyTorch
    /// semantics, the trainer's optimiser) with this learning rate.
    #[arg(long)]
    pub adam_step_lr: Option<f64>,
}

/// Options of `ggpt-train plot`.
#[derive(Args, Debug)]
pub struct PlotArgs {
    /// metrics.jsonl of a run.
    #[arg(long)]
    pub metrics: PathBuf,
    /// Output PNG: one figure, training loss on top and (when the run has val lines)
    /// held-out chunk AUC@5/AUC@10 below, on a shared step axis.
    #[arg(long)]
    pub out: PathBuf,
    /// Moving-average window of the training loss.
    #[arg(long, default_value_t = 25)]
    pub smooth: usize,
    /// Image width in pixels.
    #[arg(long, default_value_t = 1000)]
    pub width: u32,
    /// Height of each panel in pixels (the image is one or two panels high).
    #[arg(long, default_value_t = 400)]
    pub panel_height: u32,
}

impl Cli {
    /// The device the command runs its first replica on (pins Burn's default device).
    pub fn main_device(&self) -> String {
        match &self.command {
            Some(Command::Train(a)) => a
                .devices
                .as_ref()
                .and_then(|d| d.first())
                .unwrap_or(&a.device.device)
                .to_string(),
            Some(Command::Eval(a)) => a.device.device.to_string(),
            Some(Command::Grads(a)) => a.device.device.to_string(),
            _ => "cpu".into(),
        }
    }

    /// The CPU threads asked for (0: all cores).
    pub fn threads(&self) -> usize {
        match &self.command {
            Some(Command::Train(a)) => a.device.threads,
            Some(Command::Eval(a)) => a.device.threads,
            Some(Command::Grads(a)) => a.device.threads,
            _ => 0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(args: &[&str]) -> Cli {
        Cli::try_parse_from(std::iter::once("ggpt-train").chain(args.iter().copied()))
            .unwrap_or_else(|e| panic!("{e}"))
    }

    #[test]
    fn old_spellings_still_parse() {
        let c = parse(&[
            "train",
            "--data",
            "d",
            "--out",
            "o",
            "--config",
            "tiny",
            "--init-from",
            "w.pth",
        ]);
        let Some(Command::Train(a)) = &c.command else {
            panic!("not train")
        };
        assert_eq!(a.model.normalized().preset_name(), Some("tiny"));
        assert_eq!(a.init_weights(), Some(&PathBuf::from("w.pth")));
        let c = parse(&[
            "eval",
            "--data",
            "d",
            "--model",
            "m",
            "--max-pixels",
            "9",
            "--min-dlt",
            "2",
        ]);
        let Some(Command::Eval(a)) = &c.command else {
            panic!("not eval")
        };
        assert_eq!(a.model.weights, Some(PathBuf::from("m")));
        assert_eq!(a.chunking.max_chunk_pixels, Some(9));
        assert_eq!(a.chunking.min_chunk_dlt, Some(2));
    }

    #[test]
    fn devices_are_typed() {
        let c = parse(&[
            "train",
            "--data",
            "d",
            "--out",
            "o",
            "--devices",
            "cpu,wgpu:1",
        ]);
        let Some(Command::Train(a)) = &c.command else {
            panic!("not train")
        };
        assert_eq!(a.device_names().unwrap(), vec!["cpu", "wgpu:1"]);
        assert_eq!(c.main_device(), "cpu");
        assert!(
            Cli::try_parse_from([
                "ggpt-train",
                "train",
                "--data",
                "d",
                "--out",
                "o",
                "--devices",
                "tpu"
            ])
            .is_err()
        );
    }

    #[test]
    fn synthetic_specs_cycle_kinds_then_views() {
        let s = SynthArgs {
            first_seed: 10,
            views: vec![4, 8],
            width: 56,
            height: 42,
            kinds: vec![SceneKindArg::Room, SceneKindArg::Object],
            regime: RegimeArg::Benchmark,
        };
        let k: Vec<(ggpt_synth::SceneKind, usize, u64)> = (0..4)
            .map(|i| s.spec(i).map(|p| (p.kind, p.views, p.seed)).unwrap())
            .collect();
        use ggpt_synth::SceneKind::{Object, Room};
        assert_eq!(
            k,
            vec![
                (Room, 4, 10),
                (Object, 4, 11),
                (Room, 8, 12),
                (Object, 8, 13)
            ]
        );
        let bad = SynthArgs {
            views: vec![1],
            ..s
        };
        assert!(bad.spec(0).is_err());
    }
}
