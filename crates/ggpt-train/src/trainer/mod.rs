//! The training loop (`pipeline.md` §11.2-§11.4), hand-written on Burn autodiff.
//!
//! * Batch = `batch_size` chunks of distinct training scenes when available, all in one forward
//!   (BatchNorm statistics over the whole batch, drop path active).
//! * Adam with PyTorch's defaults (betas 0.9 / 0.999, eps 1e-8, no weight decay), constant
//!   learning rate 1e-4 by default; optional linear warm-up + cosine decay and global-norm
//!   gradient clipping.
//! * Determinism: the batch of step `t` and the backend RNG (drop path) are both seeded from
//!   `(seed, t)`, so a resumed run continues exactly (the "RNG state" is the step).
//! * Checkpoints `checkpoints/step-XXXXXXXX/{model.bpk, optim.bpk, state.json}` are written into
//!   a temporary directory and renamed (atomic); `--resume` picks the newest complete one.
//!
//! Files of this module (every public item is re-exported here, as `trainer::X`):
//! * `mod.rs`: the run options ([`TrainOptions`], [`Recompute`], [`LrSchedule`]), the checkpoint
//!   state [`TrainState`], and the training loop [`run`] ([`RunContext`], [`RunResult`]).
//! * `sampling.rs`: the per-step seeds and batches ([`step_seed`], [`batch_indices`],
//!   [`by_scene_of`]).
//! * `schedule.rs`: the learning-rate schedule ([`learning_rate`]).
//! * `step.rs`: one optimisation step on one device ([`train_step`], [`StepLoss`]), gradient
//!   clipping ([`clip_global_norm`]) and the optimiser ([`adam`]).
//! * `parallel.rs`: data-parallel replicas and micro-batches ([`parallel_step`], [`StepPlan`],
//!   [`split_batch`]).
//! * `batch_norm.rs`: re-estimation of the BatchNorm running statistics
//!   ([`recalibrate_batch_norm`]).
//! * `checkpoint.rs`: atomic checkpoints, their listing and loading, and the clean-up of the
//!   temporaries of dead processes ([`save_checkpoint`], [`load_checkpoint`], ...).
//! * `metrics.rs`: `metrics.jsonl` ([`MetricsLine`], [`truncate_metrics`]).
//! * `test_util.rs` (tests only): the toy chunk set, options and models the tests share.

mod batch_norm;
mod checkpoint;
mod metrics;
mod parallel;
mod sampling;
mod schedule;
mod step;
#[cfg(test)]
mod test_util;

pub use batch_norm::recalibrate_batch_norm;
pub use checkpoint::{
    checkpoint_dir, list_checkpoints, load_checkpoint, load_optimizer,
    remove_stale_checkpoint_temps, save_checkpoint,
};
pub use metrics::{MetricsLine, truncate_metrics};
pub use parallel::{StepPlan, parallel_step, split_batch};
pub use sampling::{batch_indices, by_scene_of, step_seed};
pub use schedule::learning_rate;
pub use step::{StepLoss, adam, clip_global_norm, train_step};

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use burn::optim::ModuleOptimizer;
use burn::tensor::Device;
use ggpt_model::{Ggpt, GgptConfig};
use serde::{Deserialize, Serialize};

use crate::chunkset::{ChunkSet, SceneEntry, Split, TrainChunk};
use crate::error::{Result, TrainError, io_err};
use crate::evaluate::{ChunkValidation, validate_chunks};
use metrics::append_metrics;

/// Learning-rate schedule.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LrSchedule {
    /// Constant learning rate (paper default).
    Constant,
    /// Linear warm-up, then cosine decay to 0 at the last step.
    Cosine,
}

/// How a training step obtains its gradients (`docs/training.md`, memory-efficient training).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Recompute {
    /// Segment recomputation ([`ggpt_model::recompute`]): one forward without a graph that
    /// keeps only the block-boundary tensors, then each segment re-run under autodiff in
    /// reverse. A few KB per token plus one segment's graph.
    #[default]
    Segments,
    /// Plain autodiff over the whole forward: every intermediate kept until the backward.
    Off,
}

impl std::str::FromStr for Recompute {
    type Err = TrainError;

    /// Parses `segments` or `off` (the serialised names).
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "segments" => Ok(Recompute::Segments),
            "off" => Ok(Recompute::Off),
            other => Err(TrainError::Invalid(format!(
                "unknown recompute mode {other:?} (segments, off)"
            ))),
        }
    }
}

/// Options of a training run (everything recorded in checkpoints and `config.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainOptions {
    /// Network configuration.
    pub model: GgptConfig,
    /// Total optimisation steps.
    pub steps: u64,
    /// Chunks per forward.
    pub batch_size: usize,
    /// Adam learning rate.
    pub lr: f64,
    /// Schedule.
    pub lr_schedule: LrSchedule,
    /// Warm-up steps (cosine schedule).
    pub warmup_steps: u64,
    /// Global-norm gradient clipping threshold.
    pub clip_grad_norm: Option<f64>,
    /// Seed of batches, drop path and initialisation.
    pub seed: u64,
    /// Checkpoint period (steps).
    pub save_every: u64,
    /// Validation period (steps, 0 = only at the end).
    pub val_every: u64,
    /// Validation chunks used (at most).
    pub val_chunks: usize,
    /// Token budget of a validation forward.
    pub val_max_tokens: usize,
    /// Checkpoints kept.
    pub keep_checkpoints: usize,
    /// Micro-batches per replica and step (gradient accumulation, `--grad-accum`), >= 1.
    #[serde(default = "one")]
    pub grad_accum: usize,
    /// Devices of the data-parallel replicas, main device first (`--devices`; empty: one
    /// replica on the training device). Recorded so that a resume runs the same replicas.
    #[serde(default)]
    pub devices: Vec<String>,
    /// Gradient computation (`--recompute`); runs recorded before the option existed used plain
    /// autodiff and resume with it.
    #[serde(default = "recompute_off")]
    pub recompute: Recompute,
}

fn recompute_off() -> Recompute {
    Recompute::Off
}

fn one() -> usize {
    1
}

/// `state.json` of a checkpoint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainState {
    /// Completed optimisation steps.
    pub step: u64,
    /// Run options.
    pub options: TrainOptions,
    /// Description of the RNG state (batches and drop path are seeded per step from `seed`).
    pub rng: String,
    /// Chunk set the run trains on.
    pub data: PathBuf,
    /// Last validation.
    pub last_validation: Option<ChunkValidation>,
}

/// Everything [`run`] needs besides the options.
pub struct RunContext<'a> {
    /// Output directory (metrics, checkpoints).
    pub out: &'a Path,
    /// Chunk set.
    pub data: &'a ChunkSet,
    /// Autodiff training device (the main device).
    pub device: Device,
    /// Autodiff devices of the data-parallel replicas, main device first (empty: one replica
    /// on `device`).
    pub replicas: Vec<Device>,
    /// Initial model (fresh, fine-tuning, or resumed), training mode on `device`.
    pub model: Ggpt,
    /// Optimizer (fresh or resumed).
    pub optim: ModuleOptimizer,
    /// First step (0, or the resumed step).
    pub start_step: u64,
    /// Set to stop gracefully (Ctrl-C): a checkpoint is written and the loop returns.
    pub stop: Arc<AtomicBool>,
    /// Called after every step with the metrics line (progress bar).
    pub on_step: &'a mut dyn FnMut(&MetricsLine),
}

/// Result of [`run`].
pub struct RunResult {
    /// Final model.
    pub model: Ggpt,
    /// Completed steps.
    pub steps: u64,
    /// Last validation.
    pub validation: Option<ChunkValidation>,
    /// Interrupted by the stop flag.
    pub interrupted: bool,
}

/// Runs the training loop from `ctx.start_step` to `o.steps`. Before the first step it removes
/// the checkpoint temporaries of dead processes and the `metrics.jsonl` lines past
/// `ctx.start_step` ([`remove_stale_checkpoint_temps`], [`truncate_metrics`]).
pub fn run(o: &TrainOptions, ctx: RunContext<'_>) -> Result<RunResult> {
    std::fs::create_dir_all(ctx.out).map_err(io_err(ctx.out))?;
    remove_stale_checkpoint_temps(ctx.out)?;
    truncate_metrics(&ctx.out.join("metrics.jsonl"), ctx.start_step)?;
    let train = ctx.data.load_split(Split::Train)?;
    if train.is_empty() {
        return Err(TrainError::Invalid(format!(
            "{}: no training chunk",
            ctx.data.dir.display()
        )));
    }
    let mut val = ctx.data.load_split(Split::Val)?;
    val.truncate(o.val_chunks);
    let scenes: &[SceneEntry] = &ctx.data.manifest.scenes;
    // (shards are parsed against the manifest: every chunk's scene index is < scenes.len())
    let by_scene = by_scene_of(&train);
    let metrics_path = ctx.out.join("metrics.jsonl");
    let plain = ctx.device.clone().without_autodiff();
    let t0 = Instant::now();
    let mut model = ctx.model;
    let mut optim = ctx.optim;
    let mut last_val: Option<ChunkValidation> = None;
    let mut step = ctx.start_step;
    let mut interrupted = false;
    let make_state = |step: u64, last_val: &Option<ChunkValidation>| TrainState {
        step,
        options: o.clone(),
        rng: format!(
            "pcg64 batches and backend RNG reseeded per step from seed {} (no state to store)",
            o.seed
        ),
        data: ctx.data.dir.clone(),
        last_validation: last_val.clone(),
    };
    while step < o.steps {
        if ctx.stop.load(Ordering::SeqCst) {
            interrupted = true;
            break;
        }
        let idx = batch_indices(&by_scene, o.batch_size, o.seed, step);
        let chunks: Vec<&TrainChunk> = idx.iter().filter_map(|&i| train.get(i)).collect();
        ctx.device.seed(step_seed(o.seed, step, 2));
        let lr = learning_rate(o, step);
        let ts = Instant::now();
        let devices = if ctx.replicas.is_empty() {
            std::slice::from_ref(&ctx.device)
        } else {
            &ctx.replicas[..]
        };
        let plan = StepPlan {
            devices,
            grad_accum: o.grad_accum.max(1),
            drop_path_seed: Some(step_seed(o.seed, step, 4)),
            recompute: o.recompute,
        };
        let (m, sl) = parallel_step(
            model,
            &mut optim,
            &o.model,
            &chunks,
            lr,
            o.clip_grad_norm,
            &plan,
        )?;
        model = m;
        let dt = ts.elapsed().as_secs_f64().max(1e-9);
        step += 1;
        let line = MetricsLine {
            step,
            kind: "train".into(),
            loss: sl.total,
            loss_conf: Some(sl.conf),
            loss_id: Some(sl.id),
            lr,
            grad_norm: sl.grad_norm,
            chunks_per_s: chunks.len() as f64 / dt,
            tokens_per_s: sl.tokens as f64 / dt,
            elapsed_s: t0.elapsed().as_secs_f64(),
            val: None,
        };
        append_metrics(&metrics_path, &line)?;
        (ctx.on_step)(&line);
        let do_val = !val.is_empty()
            && ((o.val_every > 0 && step.is_multiple_of(o.val_every)) || step == o.steps);
        if do_val {
            let v = validate_chunks(&model, &o.model, &val, scenes, &plain, o.val_max_tokens)?;
            tracing::info!(
                "step {step}: val loss {:.4}, chunk AUC@5 input {:.1} -> refined {:.1}, AUC@10 {:.1} -> {:.1}",
                v.loss,
                v.input_auc5,
                v.refined_auc5,
                v.input_auc10,
                v.refined_auc10
            );
            let vl = MetricsLine {
                kind: "val".into(),
                loss: v.loss,
                loss_conf: None,
                loss_id: None,
                val: Some(v.clone()),
                ..line.clone()
            };
            append_metrics(&metrics_path, &vl)?;
            last_val = Some(v);
        }
        if o.save_every > 0 && step.is_multiple_of(o.save_every) {
            save_checkpoint(ctx.out, &model, &optim, &make_state(step, &last_val))?;
        }
    }
    save_checkpoint(ctx.out, &model, &optim, &make_state(step, &last_val))?;
    Ok(RunResult {
        model,
        steps: step,
        validation: last_val,
        interrupted,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::trainer::test_util::{cpu, fresh, options, rng_lock, toy_set, weights};

    #[allow(clippy::too_many_arguments)]
    fn train(
        o: &TrainOptions,
        out: &Path,
        data: &ChunkSet,
        model: Ggpt,
        optim: ModuleOptimizer,
        start: u64,
        stop_after: Option<u64>,
        losses: &mut Vec<(u64, f64)>,
    ) -> RunResult {
        train_on(
            Vec::new(),
            o,
            out,
            data,
            model,
            optim,
            start,
            stop_after,
            losses,
        )
    }

    /// [`train`] with data-parallel `replicas` (empty: one device).
    #[allow(clippy::too_many_arguments)]
    fn train_on(
        replicas: Vec<Device>,
        o: &TrainOptions,
        out: &Path,
        data: &ChunkSet,
        model: Ggpt,
        optim: ModuleOptimizer,
        start: u64,
        stop_after: Option<u64>,
        losses: &mut Vec<(u64, f64)>,
    ) -> RunResult {
        let stop = Arc::new(AtomicBool::new(false));
        let flag = stop.clone();
        let mut on_step = |l: &MetricsLine| {
            losses.push((l.step, l.loss));
            if Some(l.step) == stop_after {
                flag.store(true, Ordering::SeqCst);
            }
        };
        let device = cpu().autodiff();
        run(
            o,
            RunContext {
                out,
                data,
                device,
                replicas,
                model,
                optim,
                start_step: start,
                stop,
                on_step: &mut on_step,
            },
        )
        .unwrap()
    }

    /// An interrupted and resumed two-replica run is bit-identical to an uninterrupted one.
    #[test]
    fn interrupted_and_resumed_two_replica_run_equals_uninterrupted_run() {
        let dir = tempfile::tempdir().unwrap();
        let data = toy_set(&dir.path().join("set"));
        let o = TrainOptions {
            devices: vec!["ndarray".into(), "ndarray".into()],
            batch_size: 2,
            ..options(4)
        };
        let ad = cpu().autodiff();
        let two = || vec![ad.clone(), ad.clone()];
        let init = || {
            let _rng = rng_lock();
            fresh(&o, &ad)
        };
        let mut la = Vec::new();
        let a = train_on(
            two(),
            &o,
            &dir.path().join("a"),
            &data,
            init(),
            adam(),
            0,
            None,
            &mut la,
        );
        let out_b = dir.path().join("b");
        let mut lb = Vec::new();
        let b1 = train_on(
            two(),
            &o,
            &out_b,
            &data,
            init(),
            adam(),
            0,
            Some(2),
            &mut lb,
        );
        assert!(b1.interrupted);
        let (model, optim, state) = load_checkpoint(&checkpoint_dir(&out_b, 2), &ad).unwrap();
        assert_eq!(state.options.devices, o.devices);
        let b2 = train_on(
            two(),
            &o,
            &out_b,
            &data,
            model,
            optim,
            state.step,
            None,
            &mut lb,
        );
        assert_eq!(la, lb, "per-step losses");
        let (wa, wb) = (weights(&a.model), weights(&b2.model));
        assert_eq!(
            wa, wb,
            "weights and BatchNorm statistics of the resumed run"
        );
    }

    /// A run stopped after step 3 (the Ctrl-C path: checkpoint at exit) and resumed from its
    /// checkpoint ends with exactly the weights and losses of an uninterrupted run.
    #[test]
    fn interrupted_and_resumed_run_equals_uninterrupted_run() {
        let _rng = rng_lock();
        let dir = tempfile::tempdir().unwrap();
        let data = toy_set(&dir.path().join("set"));
        let o = options(6);
        let ad = cpu().autodiff();

        let mut losses_a = Vec::new();
        let a = train(
            &o,
            &dir.path().join("a"),
            &data,
            fresh(&o, &ad),
            adam(),
            0,
            None,
            &mut losses_a,
        );
        assert_eq!((a.steps, a.interrupted), (6, false));
        assert!(a.validation.is_some(), "validation at the last step");

        let out_b = dir.path().join("b");
        let mut losses_b = Vec::new();
        let b1 = train(
            &o,
            &out_b,
            &data,
            fresh(&o, &ad),
            adam(),
            0,
            Some(3),
            &mut losses_b,
        );
        assert_eq!((b1.steps, b1.interrupted), (3, true));
        let steps: Vec<u64> = list_checkpoints(&out_b)
            .unwrap()
            .iter()
            .map(|(s, _)| *s)
            .collect();
        assert_eq!(
            steps,
            vec![2, 3],
            "periodic checkpoint at 2, exit checkpoint at 3"
        );
        let (model, optim, state) = load_checkpoint(&checkpoint_dir(&out_b, 3), &ad).unwrap();
        assert_eq!(state.step, 3);
        assert_eq!(state.options, o);
        let b2 = train(
            &o,
            &out_b,
            &data,
            model,
            optim,
            state.step,
            None,
            &mut losses_b,
        );
        assert_eq!((b2.steps, b2.interrupted), (6, false));

        assert_eq!(losses_a, losses_b, "per-step losses of the resumed run");
        let (wa, wb) = (weights(&a.model), weights(&b2.model));
        assert_eq!(wa.len(), wb.len());
        let max = wa
            .iter()
            .zip(&wb)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        assert_eq!(max, 0.0, "max |w_uninterrupted - w_resumed| = {max:e}");
        // the weights did change
        let w0 = weights(&fresh(&o, &ad));
        assert!(w0.iter().zip(&wa).any(|(x, y)| x != y));
        // metrics.jsonl of the resumed run holds steps 1..=6 once each (plus the final val line)
        let text = std::fs::read_to_string(out_b.join("metrics.jsonl")).unwrap();
        let train_steps: Vec<u64> = text
            .lines()
            .map(|l| serde_json::from_str::<MetricsLine>(l).unwrap())
            .filter(|l| l.kind == "train")
            .map(|l| l.step)
            .collect();
        assert_eq!(train_steps, (1..=6).collect::<Vec<_>>());
    }
}
