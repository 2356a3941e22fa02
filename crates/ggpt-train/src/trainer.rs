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

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor};
use ggpt_model::{Ggpt, GgptConfig};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

use crate::chunkset::{ChunkSet, SceneEntry, Split, TrainChunk};
use crate::error::{Result, TrainError, io_err};
use crate::evaluate::{ChunkValidation, validate_chunks};
use crate::loss::{HostTargets, loss};

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

/// One line of `metrics.jsonl`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MetricsLine {
    /// Step (1-based: after this many updates).
    pub step: u64,
    /// `train` or `val`.
    pub kind: String,
    /// Loss.
    pub loss: f64,
    /// `L_conf` part (train lines).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub loss_conf: Option<f64>,
    /// `L_id` part (train lines).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub loss_id: Option<f64>,
    /// Learning rate of the step.
    pub lr: f64,
    /// Gradient global norm (before clipping).
    pub grad_norm: f64,
    /// Chunks per second of this step.
    pub chunks_per_s: f64,
    /// Tokens per second of this step.
    pub tokens_per_s: f64,
    /// Seconds since the run (or resume) started.
    pub elapsed_s: f64,
    /// Validation result (val lines).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub val: Option<ChunkValidation>,
}

/// Mixes the run seed and a step into a 64-bit seed (SplitMix64 finaliser).
pub fn step_seed(seed: u64, step: u64, salt: u64) -> u64 {
    let mut z =
        seed ^ step.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ salt.wrapping_mul(0xD1B5_4A32_D192_ED03);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Indices of the chunks of step `step`: `batch_size` distinct scenes (random order), one random
/// chunk of each; scenes repeat only when there are fewer scenes than `batch_size`.
pub fn batch_indices(
    by_scene: &[Vec<usize>],
    batch_size: usize,
    seed: u64,
    step: u64,
) -> Vec<usize> {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(step_seed(seed, step, 1));
    let scenes: Vec<usize> = (0..by_scene.len())
        .filter(|&s| !by_scene[s].is_empty())
        .collect();
    let mut out = Vec::with_capacity(batch_size);
    while out.len() < batch_size && !scenes.is_empty() {
        let mut order = scenes.clone();
        order.shuffle(&mut rng);
        for s in order.into_iter().take(batch_size - out.len()) {
            let list = &by_scene[s];
            out.push(list[rng.random_range(0..list.len())]);
        }
    }
    out
}

/// Learning rate of step `step` (0-based).
pub fn learning_rate(o: &TrainOptions, step: u64) -> f64 {
    match o.lr_schedule {
        LrSchedule::Constant => o.lr,
        LrSchedule::Cosine => {
            if step < o.warmup_steps {
                o.lr * (step + 1) as f64 / o.warmup_steps as f64
            } else {
                let span = o.steps.saturating_sub(o.warmup_steps).max(1) as f64;
                let t = (step - o.warmup_steps) as f64 / span;
                0.5 * o.lr * (1.0 + (std::f64::consts::PI * t.min(1.0)).cos())
            }
        }
    }
}

/// Global L2 norm of the gradients of `model`'s parameters, and optional rescaling so that it
/// is at most `max_norm` (PyTorch `clip_grad_norm_` semantics: factor `max / (norm + 1e-6)`).
pub fn clip_global_norm(
    model: &Ggpt,
    grads: &mut GradientsParams,
    max_norm: Option<f64>,
) -> Result<f64> {
    struct Sq<'a> {
        grads: &'a GradientsParams,
        parts: Vec<Tensor<1>>,
    }
    impl ModuleVisitor for Sq<'_> {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            if let Some(g) = self.grads.get::<D>(param.id) {
                self.parts.push(g.square().sum());
            }
        }
    }
    struct Scale<'a> {
        grads: &'a mut GradientsParams,
        factor: f64,
    }
    impl ModuleVisitor for Scale<'_> {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            if let Some(g) = self.grads.remove::<D>(param.id) {
                self.grads
                    .register::<D>(param.id, g.mul_scalar(self.factor));
            }
        }
    }
    let mut sq = Sq {
        grads,
        parts: Vec::new(),
    };
    model.visit(&mut sq);
    if sq.parts.is_empty() {
        return Ok(0.0);
    }
    let total = Tensor::cat(sq.parts, 0).sum();
    let norm = (ggpt_model::readback::read_tensor_f32(&total, "grad norm")?
        .first()
        .copied()
        .unwrap_or(0.0) as f64)
        .sqrt();
    if let Some(max) = max_norm
        && norm > max
    {
        let mut s = Scale {
            grads,
            factor: max / (norm + 1e-6),
        };
        model.visit(&mut s);
    }
    Ok(norm)
}

/// The Adam optimiser of `pipeline.md` §11.4 (PyTorch defaults, no weight decay).
pub fn adam() -> ModuleOptimizer {
    AdamConfig::new()
        .with_beta_1(0.9)
        .with_beta_2(0.999)
        .with_epsilon(1e-8)
        .init()
}

/// Scalar values of the loss parts of one step.
#[derive(Debug, Clone, Copy)]
pub struct StepLoss {
    /// `L`.
    pub total: f64,
    /// `L_conf`.
    pub conf: f64,
    /// `L_id`.
    pub id: f64,
    /// Gradient norm before clipping.
    pub grad_norm: f64,
    /// Tokens of the forward.
    pub tokens: usize,
}

/// One optimisation step on `chunks` (one forward, one replica). `device` must be an
/// autodiff device. Drop-path masks come from the device RNG unless the calling thread seeded
/// its own ([`ggpt_model::drop_path::seed_drop_path`]).
pub fn train_step(
    model: Ggpt,
    optim: &mut ModuleOptimizer,
    cfg: &GgptConfig,
    chunks: &[&TrainChunk],
    lr: f64,
    clip: Option<f64>,
    device: &Device,
) -> Result<(Ggpt, StepLoss)> {
    let plan = StepPlan {
        devices: std::slice::from_ref(device),
        grad_accum: 1,
        drop_path_seed: None,
        recompute: Recompute::default(),
    };
    parallel_step(model, optim, cfg, chunks, lr, clip, &plan)
}

/// How a step is spread over replicas and micro-batches.
#[derive(Debug, Clone, Copy)]
pub struct StepPlan<'a> {
    /// Autodiff devices of the replicas, main device (where the optimiser steps) first. The
    /// same device may appear several times (replicas in threads).
    pub devices: &'a [Device],
    /// Micro-batches per replica (>= 1).
    pub grad_accum: usize,
    /// Base seed of the drop-path masks: part `p` of the step draws from
    /// `step_seed(base, p, 3)` on its own thread, so the step does not depend on thread timing.
    /// `None`: the device RNG (one replica only).
    pub drop_path_seed: Option<u64>,
    /// How each micro-batch's gradients are computed.
    pub recompute: Recompute,
}

/// The batch cut into `parts` contiguous parts of near-equal size (earlier parts one larger).
pub fn split_batch<'c, 'a>(
    chunks: &'a [&'c TrainChunk],
    parts: usize,
) -> Vec<&'a [&'c TrainChunk]> {
    let (q, r) = (chunks.len() / parts, chunks.len() % parts);
    let mut out = Vec::with_capacity(parts);
    let mut start = 0;
    for p in 0..parts {
        let len = q + usize::from(p < r);
        out.push(&chunks[start..start + len]);
        start += len;
    }
    out
}

/// What one replica returns: its summed, chunk-weighted gradients (on the main device), its
/// chunk-weighted loss terms, tokens, and its BatchNorm running statistics after its forwards.
struct ReplicaResult {
    grads: GradientsParams,
    loss: [f64; 3],
    tokens: usize,
    running: Vec<(Tensor<1>, Tensor<1>)>,
}

/// Runs the micro-batches `parts` (indices `first..`) on `replica`, sequentially.
fn run_replica(
    replica: Ggpt,
    cfg: &GgptConfig,
    parts: &[&[&TrainChunk]],
    first: usize,
    total_chunks: usize,
    plan: &StepPlan<'_>,
    main: &Device,
) -> Result<ReplicaResult> {
    let device = replica
        .devices()
        .first()
        .cloned()
        .ok_or_else(|| TrainError::Invalid("replica without a device".into()))?;
    let mut acc: Option<GradientsParams> = None;
    let (mut loss_sum, mut tokens) = ([0.0f64; 3], 0usize);
    for (j, part) in parts.iter().enumerate() {
        ggpt_model::drop_path::seed_drop_path(
            plan.drop_path_seed
                .map(|s| step_seed(s, (first + j) as u64, 3)),
        );
        // the chunks lend their arrays to the planner: nothing is copied per forward
        let batch = ggpt_model::profile::scope(
            || "step.prepare".to_string(),
            || ggpt_model::infer::prepare_chunks(cfg, part, &device),
        )?;
        // the part's mean loss weighted by its share of the batch: the sum over parts is the
        // batch's mean loss, whatever the split
        let w = part.len() as f64 / total_chunks as f64;
        let targets = HostTargets::new(part).upload(&device);
        let objective = |out: ggpt_model::GgptOutput| -> Result<(Tensor<1>, [f32; 3])> {
            let parts = loss(out.tokens_xyz, out.tokens_conf, &targets);
            let vals = ggpt_model::readback::read_tensor_f32(
                &Tensor::cat(vec![parts.total.clone(), parts.conf, parts.id], 0),
                "loss",
            )?;
            let v = |i: usize| vals.get(i).copied().unwrap_or(f32::NAN);
            if !v(0).is_finite() {
                return Err(TrainError::Invalid(format!(
                    "non-finite loss {} (L_conf {}, L_id {})",
                    v(0),
                    v(1),
                    v(2)
                )));
            }
            Ok((parts.total.mul_scalar(w), [v(0), v(1), v(2)]))
        };
        let (g, vals) = match plan.recompute {
            Recompute::Segments => {
                ggpt_model::recompute::recomputed_gradients(&replica, &batch, objective)?
            }
            Recompute::Off => {
                let (total, vals) = ggpt_model::profile::scope(
                    || "step.forward".to_string(),
                    || objective(replica.forward(&batch)),
                )?;
                let grads =
                    ggpt_model::profile::scope(|| "step.backward".to_string(), || total.backward());
                (GradientsParams::from_grads(grads, &replica), vals)
            }
        };
        for (s, v) in loss_sum.iter_mut().zip(vals) {
            *s += w * f64::from(v);
        }
        tokens += batch.num_tokens;
        acc = Some(match acc {
            None => g,
            Some(a) => add_gradients(&replica, a, g),
        });
    }
    ggpt_model::drop_path::seed_drop_path(None);
    let grads = acc
        .ok_or_else(|| TrainError::Invalid("replica without a micro-batch".into()))?
        .to_device(main, &replica);
    let synced = replica.valid();
    let running = synced
        .named_batch_norms()
        .into_iter()
        .map(|(_, bn)| {
            (
                bn.running_mean.value().to_device(main),
                bn.running_var.value().to_device(main),
            )
        })
        .collect();
    Ok(ReplicaResult {
        grads,
        loss: loss_sum,
        tokens,
        running,
    })
}

/// `a + b` for every parameter of `model` (a missing side counts as 0). Summation order is
/// fixed (replica / micro-batch order), so steps are reproducible.
fn add_gradients(model: &Ggpt, a: GradientsParams, b: GradientsParams) -> GradientsParams {
    struct Add {
        a: GradientsParams,
        b: GradientsParams,
    }
    impl ModuleVisitor for Add {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let sum = match (self.a.remove::<D>(param.id), self.b.remove::<D>(param.id)) {
                (Some(x), Some(y)) => {
                    let device = x.device();
                    Some(x + y.to_device(&device))
                }
                (x, y) => x.or(y),
            };
            if let Some(g) = sum {
                self.a.register::<D>(param.id, g);
            }
        }
    }
    let mut add = Add { a, b };
    model.visit(&mut add);
    add.a
}

/// One data-parallel optimisation step (`docs/training.md`, data parallelism): the global
/// batch `chunks` is cut into `devices.len() x grad_accum` contiguous parts; replica `r` (a copy
/// of `model` forked onto `devices[r]`, in its own thread when there are several) runs parts
/// `r K .. (r+1) K` one after the other, each in train mode with its own BatchNorm batch
/// statistics. Each part's loss is weighted by its share of the chunks, so the summed
/// gradients are those of the batch's mean loss. The gradients are moved to the main device and
/// added in replica order; one optimiser step follows (after optional clipping), and the
/// running statistics become the mean of the replicas' (Burn's `RunningState` rule).
pub fn parallel_step(
    model: Ggpt,
    optim: &mut ModuleOptimizer,
    cfg: &GgptConfig,
    chunks: &[&TrainChunk],
    lr: f64,
    clip: Option<f64>,
    plan: &StepPlan<'_>,
) -> Result<(Ggpt, StepLoss)> {
    let replicas = plan.devices.len();
    let k = plan.grad_accum.max(1);
    if replicas == 0 {
        return Err(TrainError::Invalid("no training device".into()));
    }
    if chunks.len() < replicas * k {
        return Err(TrainError::Invalid(format!(
            "batch of {} chunks cannot feed {replicas} replica(s) x {k} micro-batch(es): raise --batch-size to at least {}",
            chunks.len(),
            replicas * k
        )));
    }
    if replicas > 1 && plan.drop_path_seed.is_none() {
        return Err(TrainError::Invalid(
            "several replicas need a drop-path seed (reproducible masks per thread)".into(),
        ));
    }
    let main = plan.devices[0].clone();
    let parts = split_batch(chunks, replicas * k);
    // Replicas are independent copies (`valid` gives fresh running-statistics cells) with the
    // main model's training flags (a test may switch BatchNorm to eval mode).
    let mut copies: Vec<Ggpt> = ggpt_model::profile::scope(
        || "step.replica_copies".to_string(),
        || {
            plan.devices
                .iter()
                .map(|d| model.valid().fork(d).train())
                .collect()
        },
    );
    let flags: Vec<Param<burn::module::Flag>> = model
        .named_batch_norms()
        .into_iter()
        .map(|(_, bn)| bn.training.clone())
        .collect();
    for copy in &mut copies {
        for (bn, flag) in copy.batch_norms_mut().into_iter().zip(&flags) {
            bn.training = flag.clone();
        }
    }
    let total = chunks.len();
    let results: Vec<Result<ReplicaResult>> = if replicas == 1 {
        let copy = copies
            .pop()
            .ok_or_else(|| TrainError::Invalid("no replica".into()))?;
        vec![run_replica(copy, cfg, &parts, 0, total, plan, &main)]
    } else {
        std::thread::scope(|scope| {
            let handles: Vec<_> = copies
                .into_iter()
                .enumerate()
                .map(|(r, copy)| {
                    let my_parts = &parts[r * k..(r + 1) * k];
                    let main = main.clone();
                    scope.spawn(move || run_replica(copy, cfg, my_parts, r * k, total, plan, &main))
                })
                .collect();
            handles
                .into_iter()
                .map(|h| {
                    h.join().unwrap_or_else(|_| {
                        Err(TrainError::Invalid("a replica thread panicked".into()))
                    })
                })
                .collect()
        })
    };
    let mut grads: Option<GradientsParams> = None;
    let (mut loss_sum, mut tokens) = ([0.0f64; 3], 0usize);
    let mut running: Vec<Vec<(Tensor<1>, Tensor<1>)>> = Vec::new();
    for r in results {
        let r = r?;
        for (s, v) in loss_sum.iter_mut().zip(r.loss) {
            *s += v;
        }
        tokens += r.tokens;
        running.push(r.running);
        grads = Some(match grads {
            None => r.grads,
            Some(a) => add_gradients(&model, a, r.grads),
        });
    }
    let mut grads = grads.ok_or_else(|| TrainError::Invalid("no gradients".into()))?;
    let grad_norm = ggpt_model::profile::scope(
        || "step.clip".to_string(),
        || clip_global_norm(&model, &mut grads, clip),
    )?;
    let mut model =
        ggpt_model::profile::scope(|| "step.adam".to_string(), || optim.step(lr, model, grads));
    // running statistics: the mean over replicas, in replica order
    let n = running.len() as f64;
    for (i, bn) in model.batch_norms_mut().into_iter().enumerate() {
        let (mut mean, mut var) = (None::<Tensor<1>>, None::<Tensor<1>>);
        for rep in &running {
            let (m, v) = rep[i].clone();
            mean = Some(match mean {
                None => m,
                Some(a) => a + m,
            });
            var = Some(match var {
                None => v,
                Some(a) => a + v,
            });
        }
        if let (Some(m), Some(v)) = (mean, var) {
            let dev = bn.running_mean.value().device();
            bn.running_mean = burn::module::RunningState::new(m.div_scalar(n).to_device(&dev));
            bn.running_var = burn::module::RunningState::new(v.div_scalar(n).to_device(&dev));
        }
    }
    Ok((
        model,
        StepLoss {
            total: loss_sum[0],
            conf: loss_sum[1],
            id: loss_sum[2],
            grad_norm,
            tokens,
        },
    ))
}

/// Chunk indices grouped by `TrainChunk::scene` (index = scene).
pub fn by_scene_of(chunks: &[TrainChunk]) -> Vec<Vec<usize>> {
    let num_scenes = chunks.iter().map(|c| c.scene + 1).max().unwrap_or(0);
    let mut by_scene = vec![Vec::new(); num_scenes];
    for (i, c) in chunks.iter().enumerate() {
        by_scene[c.scene].push(i);
    }
    by_scene
}

/// Re-estimates the BatchNorm running statistics of a trained model ("precise BN"): `batches`
/// forwards in training mode over batches drawn as in training (`batch_indices` with its own
/// seed stream), no parameter update, drop path off, with momentum `1 / (k + 1)` at the `k`-th
/// forward, so that each running mean / variance ends as the plain average of the per-batch
/// statistics instead of an exponential average of the last ~1/momentum steps. The momentum is
/// reset to `cfg.bn_momentum` afterwards. `device` must be an autodiff device. The returned
/// model is meant for evaluation and export (its drop path is off).
pub fn recalibrate_batch_norm(
    model: Ggpt,
    cfg: &GgptConfig,
    chunks: &[TrainChunk],
    batch_size: usize,
    batches: usize,
    seed: u64,
    device: &Device,
) -> Result<Ggpt> {
    if chunks.is_empty() || batches == 0 {
        return Ok(model);
    }
    let by_scene = by_scene_of(chunks);
    // Training mode on the autodiff device selects BatchNorm's batch-statistics path; without
    // gradients no graph is recorded, so a forward costs inference memory.
    let mut model = model.fork(device).train().no_grad();
    model.set_drop_path(0.0);
    for k in 0..batches {
        for bn in model.batch_norms_mut() {
            bn.momentum = 1.0 / (k as f64 + 1.0);
        }
        let idx = batch_indices(
            &by_scene,
            batch_size.max(1),
            step_seed(seed, k as u64, 3),
            k as u64,
        );
        let group: Vec<&TrainChunk> = idx.iter().filter_map(|&i| chunks.get(i)).collect();
        let batch = ggpt_model::infer::prepare_chunks(cfg, &group, device)?;
        // the forward updates the running statistics; its outputs are not needed
        let out = model.forward(&batch);
        drop(out);
    }
    for bn in model.batch_norms_mut() {
        bn.momentum = cfg.bn_momentum;
    }
    Ok(model)
}

/// Directory of the checkpoint of `step`.
pub fn checkpoint_dir(out: &Path, step: u64) -> PathBuf {
    out.join("checkpoints").join(format!("step-{step:08}"))
}

/// Writes a checkpoint atomically (temporary directory + rename) and prunes old ones.
pub fn save_checkpoint(
    out: &Path,
    model: &Ggpt,
    optim: &ModuleOptimizer,
    state: &TrainState,
) -> Result<PathBuf> {
    let root = out.join("checkpoints");
    std::fs::create_dir_all(&root).map_err(io_err(&root))?;
    let final_dir = checkpoint_dir(out, state.step);
    let tmp = root.join(format!(
        "{CHECKPOINT_TMP_PREFIX}{:08}-{}",
        state.step,
        std::process::id()
    ));
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).map_err(io_err(&tmp))?;
    }
    std::fs::create_dir_all(&tmp).map_err(io_err(&tmp))?;
    let ck = |message: String| TrainError::Checkpoint {
        path: tmp.clone(),
        message,
    };
    ggpt_model::weights::save_burnpack(&model.valid(), &tmp.join("model.bpk"))?;
    optim
        .save(tmp.join("optim.bpk"))
        .map_err(|e| ck(format!("optimizer: {e:?}")))?;
    let text = serde_json::to_string_pretty(state).map_err(|e| ck(e.to_string()))?;
    std::fs::write(tmp.join("state.json"), text).map_err(io_err(tmp.join("state.json")))?;
    if final_dir.exists() {
        std::fs::remove_dir_all(&final_dir).map_err(io_err(&final_dir))?;
    }
    std::fs::rename(&tmp, &final_dir).map_err(io_err(&final_dir))?;
    // prune
    let mut all = list_checkpoints(out)?;
    let keep = state.options.keep_checkpoints.max(1);
    while all.len() > keep {
        let (_, old) = all.remove(0);
        let _ = std::fs::remove_dir_all(old);
    }
    Ok(final_dir)
}

/// Complete checkpoints of a run, oldest first.
pub fn list_checkpoints(out: &Path) -> Result<Vec<(u64, PathBuf)>> {
    let root = out.join("checkpoints");
    let mut v = Vec::new();
    if !root.is_dir() {
        return Ok(v);
    }
    for e in std::fs::read_dir(&root).map_err(io_err(&root))? {
        let e = e.map_err(io_err(&root))?;
        let name = e.file_name().to_string_lossy().into_owned();
        if let Some(n) = name
            .strip_prefix("step-")
            .and_then(|s| s.parse::<u64>().ok())
            && e.path().join("state.json").is_file()
        {
            v.push((n, e.path()));
        }
    }
    v.sort();
    Ok(v)
}

/// Loads a checkpoint directory: model (on `device`, training mode), optimizer, state.
pub fn load_checkpoint(dir: &Path, device: &Device) -> Result<(Ggpt, ModuleOptimizer, TrainState)> {
    let state_path = dir.join("state.json");
    let text = std::fs::read_to_string(&state_path).map_err(io_err(&state_path))?;
    let state: TrainState = serde_json::from_str(&text).map_err(|e| TrainError::Format {
        path: state_path.clone(),
        message: e.to_string(),
    })?;
    state
        .options
        .model
        .validate()
        .map_err(|m| TrainError::Format {
            path: state_path.clone(),
            message: format!("options.model: {m}"),
        })?;
    let plain = device.clone().without_autodiff();
    let model = Ggpt::new(&state.options.model, &plain);
    let weights = dir.join("model.bpk");
    // The architecture comes from state.json: a mismatch is in either file, so both are named.
    let model = ggpt_model::weights::load_burnpack(model, &weights).map_err(|e| {
        TrainError::Checkpoint {
            path: weights.clone(),
            message: format!(
                "{e} (the network architecture is the one recorded in {})",
                state_path.display()
            ),
        }
    })?;
    let optim = load_optimizer(&dir.join("optim.bpk"), &model, &weights, state.step)?;
    Ok((model.fork(device).train(), optim, state))
}

/// Key suffix of the per-parameter rank scalar in Burn 0.22.1's optimizer records
/// (`burn-optim` `module_optimizer.rs`, `RANK_KEY`).
const OPTIM_RANK_SUFFIX: &str = ".__rank";

/// Reads the Adam state `optim.bpk` of a checkpoint of `model` after `step` steps, checking it
/// before Burn sees it: Burn 0.22.1's `ModuleOptimizer::load_record` panics on a state tensor
/// without a parameter id, and silently drops the state of a parameter it cannot rebuild (a
/// corrupt file would crash, or quietly restart Adam's moments and break exact resume). Here
/// every state tensor must carry the id its name starts with, every recorded parameter must be
/// one of the model's (some, after the first step), and every tensor must survive the load.
/// `model_origin` is the file `model` was loaded from (named in a mismatch).
pub fn load_optimizer(
    path: &Path,
    model: &Ggpt,
    model_origin: &Path,
    step: u64,
) -> Result<ModuleOptimizer> {
    let err = |message: String| TrainError::Checkpoint {
        path: path.to_path_buf(),
        message,
    };
    let bytes = std::fs::read(path).map_err(io_err(path))?;
    let reader = burn_pack::Reader::from_bytes(burn_pack::Bytes::from_bytes_vec(bytes.clone()))
        .map_err(|e| err(format!("not an optimizer record: {e}")))?;
    let ranked: BTreeSet<u64> = reader
        .scalars()
        .keys()
        .filter_map(|k| k.strip_suffix(OPTIM_RANK_SUFFIX)?.parse().ok())
        .collect();
    let tensors = reader
        .into_tensors()
        .map_err(|e| err(format!("corrupt optimizer record: {e}")))?;
    for t in &tensors {
        let id = t
            .param_id
            .ok_or_else(|| err(format!("state tensor {} carries no parameter id", t.name)))?;
        if !t.name.starts_with(&format!("{id}.")) || !ranked.contains(&id) {
            return Err(err(format!(
                "state tensor {} does not belong to a recorded parameter (id {id})",
                t.name
            )));
        }
    }
    struct Ids(BTreeSet<u64>);
    impl ModuleVisitor for Ids {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            self.0.insert(param.id.val());
        }
    }
    let mut ids = Ids(BTreeSet::new());
    model.visit(&mut ids);
    // Parameters that never received a gradient have no state; a state of a parameter the
    // network does not have would be ignored by Burn, and after a step there is some state.
    let foreign = ranked.difference(&ids.0).count();
    if foreign > 0 || (step > 0 && ranked.is_empty()) {
        return Err(err(format!(
            "state of {} parameters, {foreign} of them not parameters of the network loaded from {} (step {step}; the parameter ids of the two files must match)",
            ranked.len(),
            model_origin.display()
        )));
    }
    let optim = adam()
        .from_bytes(burn_pack::Bytes::from_bytes_vec(bytes))
        .map_err(|e| err(format!("{e:?}")))?;
    let kept = optim.to_record().len();
    if kept != tensors.len() {
        return Err(err(format!(
            "{} of {} state tensors could not be restored (wrong shape or dtype)",
            tensors.len() - kept,
            tensors.len()
        )));
    }
    Ok(optim)
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

fn append_metrics(path: &Path, line: &MetricsLine) -> Result<()> {
    use std::io::Write;
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .map_err(io_err(path))?;
    let text = serde_json::to_string(line).map_err(|e| TrainError::Invalid(e.to_string()))?;
    writeln!(f, "{text}").map_err(io_err(path))
}

/// Prefix of the temporary directory a checkpoint is written into before its rename
/// (`.tmp-step-<step>-<pid>`).
const CHECKPOINT_TMP_PREFIX: &str = ".tmp-step-";

/// Whether process `pid` is alive (`kill(pid, 0)` succeeds or fails for lack of permission).
fn process_alive(pid: u32) -> bool {
    let Ok(pid) = libc::pid_t::try_from(pid) else {
        return false;
    };
    if pid <= 0 {
        return false;
    }
    // SAFETY: signal 0 sends nothing; it only checks that the process exists.
    let r = unsafe { libc::kill(pid, 0) };
    r == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM)
}

/// Removes the checkpoint temporary directories `checkpoints/.tmp-step-<step>-<pid>` left by
/// processes that died while writing a checkpoint (kill -9, power loss). A directory of a live
/// process other than this one (another run writing into the same folder) is left alone.
/// Returns the removed directories.
pub fn remove_stale_checkpoint_temps(out: &Path) -> Result<Vec<PathBuf>> {
    let root = out.join("checkpoints");
    let mut removed = Vec::new();
    if !root.is_dir() {
        return Ok(removed);
    }
    let me = std::process::id();
    for e in std::fs::read_dir(&root).map_err(io_err(&root))? {
        let e = e.map_err(io_err(&root))?;
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(rest) = name.strip_prefix(CHECKPOINT_TMP_PREFIX) else {
            continue;
        };
        let Some(pid) = rest.rsplit('-').next().and_then(|p| p.parse::<u32>().ok()) else {
            continue;
        };
        if pid != me && process_alive(pid) {
            continue;
        }
        let path = e.path();
        std::fs::remove_dir_all(&path).map_err(io_err(&path))?;
        tracing::info!(
            "removed the stale checkpoint temporary {} (process {pid} is gone)",
            path.display()
        );
        removed.push(path);
    }
    Ok(removed)
}

/// Makes `metrics.jsonl` consistent with a run that continues after `step`: drops every line
/// past `step` (steps re-run after a crash would otherwise appear twice) and any torn line a
/// crash left, atomically (temporary file + rename). Returns the number of lines dropped.
pub fn truncate_metrics(path: &Path, step: u64) -> Result<usize> {
    let text = match std::fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(0),
        Err(e) => return Err(io_err(path)(e)),
    };
    let mut kept = String::with_capacity(text.len());
    let mut dropped = 0;
    for line in text.lines().filter(|l| !l.trim().is_empty()) {
        match serde_json::from_str::<MetricsLine>(line) {
            Ok(m) if m.step <= step => {
                kept.push_str(line);
                kept.push('\n');
            }
            _ => dropped += 1,
        }
    }
    if dropped > 0 {
        ggpt_core::io::atomic::write_bytes_atomic(path, kept.as_bytes())?;
        tracing::info!(
            "{}: dropped {dropped} line(s) past step {step}",
            path.display()
        );
    }
    Ok(dropped)
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
    use crate::chunkset::ChunkSetWriter;
    use crate::chunkset::tests::toy_chunk;

    #[allow(deprecated)]
    fn cpu() -> Device {
        Device::ndarray()
    }

    /// The backend RNG (initialisation, drop path) is one per backend and process: tests that
    /// seed it and depend on its sequence must not interleave.
    static BACKEND_RNG: std::sync::Mutex<()> = std::sync::Mutex::new(());

    fn rng_lock() -> std::sync::MutexGuard<'static, ()> {
        BACKEND_RNG.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn toy_set(dir: &Path) -> ChunkSet {
        let mut w = ChunkSetWriter::new(dir, 4, serde_json::json!({"test": true})).unwrap();
        for s in 0..3 {
            let idx = w.add_scene(SceneEntry {
                name: format!("train{s}"),
                split: Split::Train,
                views: 2,
                height: 14,
                width: 14,
                metres_per_unit: 1.0,
                source: "test".into(),
            });
            for k in 0..3 {
                w.add_chunk(toy_chunk(idx, 60 + 7 * k, (s * 3 + k) as u32))
                    .unwrap();
            }
        }
        let v = w.add_scene(SceneEntry {
            name: "val".into(),
            split: Split::Val,
            views: 2,
            height: 14,
            width: 14,
            metres_per_unit: 1.0,
            source: "test".into(),
        });
        w.add_chunk(toy_chunk(v, 50, 99)).unwrap();
        w.finish().unwrap();
        ChunkSet::open(dir).unwrap()
    }

    fn options(steps: u64) -> TrainOptions {
        TrainOptions {
            model: GgptConfig::tiny(),
            steps,
            batch_size: 2,
            lr: 1e-3,
            lr_schedule: LrSchedule::Cosine,
            warmup_steps: 2,
            clip_grad_norm: Some(1.0),
            seed: 7,
            save_every: 2,
            val_every: 0,
            val_chunks: 4,
            val_max_tokens: 100_000,
            keep_checkpoints: 10,
            grad_accum: 1,
            devices: Vec::new(),
            recompute: Recompute::default(),
        }
    }

    fn fresh(o: &TrainOptions, device: &Device) -> Ggpt {
        let plain = device.clone().without_autodiff();
        plain.seed(o.seed);
        Ggpt::new(&o.model, &plain).fork(device).train()
    }

    /// Every float parameter and buffer of the model, flattened in visiting order.
    fn weights(model: &Ggpt) -> Vec<f32> {
        struct Collect(Vec<f32>);
        impl ModuleVisitor for Collect {
            fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
                self.0.extend(
                    param
                        .val()
                        .into_data()
                        .convert::<f32>()
                        .try_to_vec::<f32>()
                        .unwrap(),
                );
            }
        }
        let mut c = Collect(Vec::new());
        model.valid().visit(&mut c);
        c.0
    }

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

    fn rel_to_max(a: &[f32], b: &[f32]) -> f32 {
        assert_eq!(a.len(), b.len());
        let max = a.iter().fold(0.0f32, |m, x| m.max(x.abs())).max(1e-30);
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max)
            / max
    }

    fn toy_batch(n: usize) -> Vec<TrainChunk> {
        (0..n)
            .map(|i| toy_chunk(i % 3, 40 + 7 * i, i as u32 + 1))
            .collect()
    }

    /// `--devices cpu,cpu` on a batch of 2B equals one device with `--grad-accum 2`: same parts,
    /// each normalised with its own BatchNorm statistics, same updated weights and statistics.
    #[test]
    fn data_parallel_step_equals_gradient_accumulation() {
        let _rng = rng_lock();
        let o = options(1);
        let ad = cpu().autodiff();
        let batch = toy_batch(4);
        let chunks: Vec<&TrainChunk> = batch.iter().collect();
        let two = [ad.clone(), ad.clone()];
        let step = |devices: &[Device], k: usize| {
            let plan = StepPlan {
                devices,
                grad_accum: k,
                drop_path_seed: Some(99),
                recompute: Recompute::default(),
            };
            let mut optim = adam();
            let (m, l) = parallel_step(
                fresh(&o, &ad),
                &mut optim,
                &o.model,
                &chunks,
                1e-3,
                None,
                &plan,
            )
            .unwrap();
            // trainable parameters only: the running statistics follow different rules (mean
            // over replicas vs sequential updates within one)
            let params: Vec<f32> = crate::grads::named_parameters(&m.valid())
                .unwrap()
                .into_iter()
                .flat_map(|t| t.values)
                .collect();
            (params, l)
        };
        let (w_dp, l_dp) = step(&two, 1);
        let (w_acc, l_acc) = step(std::slice::from_ref(&ad), 2);
        let d = rel_to_max(&w_acc, &w_dp);
        assert!(d <= 1e-6, "data parallel vs accumulation: {d:e}");
        assert!(
            (l_dp.total - l_acc.total).abs() <= 1e-6 * l_acc.total.abs(),
            "{} vs {}",
            l_dp.total,
            l_acc.total
        );
        // and it is not the one-forward step (BatchNorm statistics of the whole batch differ)
        let (w_one, _) = step(std::slice::from_ref(&ad), 1);
        assert!(rel_to_max(&w_one, &w_acc) > 0.0);
        // too small a batch is an error, not a silent empty replica
        let mut optim = adam();
        let plan = StepPlan {
            devices: &two,
            grad_accum: 3,
            drop_path_seed: Some(1),
            recompute: Recompute::default(),
        };
        let e = parallel_step(
            fresh(&o, &ad),
            &mut optim,
            &o.model,
            &chunks,
            1e-3,
            None,
            &plan,
        )
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default();
        assert!(e.contains("batch-size"), "{e}");
    }

    /// Without BatchNorm effects (eval-mode BatchNorm, drop path 0) two replicas give the
    /// gradients of one device on the whole batch (a plain SGD step with lr 1 exposes them).
    #[test]
    fn data_parallel_gradients_equal_the_whole_batch_without_batch_norm_effects() {
        let _rng = rng_lock();
        let mut o = options(1);
        o.model.drop_path = 0.0;
        let ad = cpu().autodiff();
        let batch = toy_batch(4);
        let chunks: Vec<&TrainChunk> = batch.iter().collect();
        let model = || {
            let mut m = fresh(&o, &ad);
            // test hook: BatchNorm in eval mode (running statistics) while the rest trains
            for bn in m.batch_norms_mut() {
                bn.training = Param::from_bool(false);
            }
            m
        };
        let sgd_step = |devices: &[Device]| {
            let plan = StepPlan {
                devices,
                grad_accum: 1,
                drop_path_seed: Some(5),
                recompute: Recompute::default(),
            };
            let mut optim = burn::optim::SgdConfig::new().init();
            let (m, _) =
                parallel_step(model(), &mut optim, &o.model, &chunks, 1.0, None, &plan).unwrap();
            weights(&m)
        };
        let w0 = weights(&model());
        let grad = |w: Vec<f32>| w0.iter().zip(&w).map(|(a, b)| a - b).collect::<Vec<f32>>();
        let g_one = grad(sgd_step(std::slice::from_ref(&ad)));
        let g_two = grad(sgd_step(&[ad.clone(), ad.clone()]));
        assert!(g_one.iter().any(|g| *g != 0.0));
        let d = rel_to_max(&g_one, &g_two);
        assert!(
            d <= 1e-5,
            "two replicas vs one device on the whole batch: {d:e}"
        );
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

    #[test]
    fn batch_norm_recalibration_replaces_the_running_statistics_deterministically() {
        let _rng = rng_lock();
        let dir = tempfile::tempdir().unwrap();
        let data = toy_set(dir.path());
        let chunks = data.load_split(Split::Train).unwrap();
        let o = options(1);
        let ad = cpu().autodiff();
        let stats = |m: &mut Ggpt| -> Vec<f32> {
            m.batch_norms_mut()
                .iter()
                .flat_map(|bn| {
                    let mut v = bn
                        .running_mean
                        .value()
                        .into_data()
                        .convert::<f32>()
                        .try_to_vec::<f32>()
                        .unwrap();
                    v.extend(
                        bn.running_var
                            .value()
                            .into_data()
                            .convert::<f32>()
                            .try_to_vec::<f32>()
                            .unwrap(),
                    );
                    v
                })
                .collect()
        };
        let mut before = fresh(&o, &ad);
        let s0 = stats(&mut before);
        let mut a =
            recalibrate_batch_norm(fresh(&o, &ad), &o.model, &chunks, 2, 3, 11, &ad).unwrap();
        let mut b =
            recalibrate_batch_norm(fresh(&o, &ad), &o.model, &chunks, 2, 3, 11, &ad).unwrap();
        let (sa, sb) = (stats(&mut a), stats(&mut b));
        assert_eq!(sa, sb, "same seed, same statistics");
        assert_eq!(sa.len(), s0.len());
        assert!(
            sa.iter().zip(&s0).filter(|(x, y)| x != y).count() > sa.len() / 2,
            "running statistics replaced"
        );
        assert!(
            a.batch_norms_mut()
                .iter()
                .all(|bn| bn.momentum == o.model.bn_momentum),
            "momentum restored"
        );
        // one batch with momentum 1 equals a plain training-mode forward with momentum 1
        let mut c =
            recalibrate_batch_norm(fresh(&o, &ad), &o.model, &chunks, 2, 1, 11, &ad).unwrap();
        let mut d = fresh(&o, &ad);
        d.set_drop_path(0.0);
        for bn in d.batch_norms_mut() {
            bn.momentum = 1.0;
        }
        let idx = batch_indices(&by_scene_of(&chunks), 2, step_seed(11, 0, 3), 0);
        let inputs: Vec<_> = idx.iter().map(|&i| chunks[i].to_input()).collect();
        let _ = d.forward(&ggpt_model::infer::prepare_chunks(&o.model, &inputs, &ad).unwrap());
        let (sc, sd) = (stats(&mut c), stats(&mut d));
        let max = sc
            .iter()
            .zip(&sd)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        assert!(max < 1e-6, "max |difference| {max:e}");
    }

    #[test]
    fn batches_draw_distinct_scenes_and_are_deterministic() {
        let by_scene = vec![vec![0, 1], vec![2], vec![], vec![3, 4, 5]];
        let b = batch_indices(&by_scene, 3, 42, 5);
        assert_eq!(b, batch_indices(&by_scene, 3, 42, 5));
        let scene_of = |i: usize| by_scene.iter().position(|l| l.contains(&i)).unwrap();
        let mut scenes: Vec<usize> = b.iter().map(|&i| scene_of(i)).collect();
        scenes.sort();
        assert_eq!(scenes, vec![0, 1, 3]);
        // more chunks than scenes: scenes repeat only then
        assert_eq!(batch_indices(&by_scene, 5, 42, 5).len(), 5);
        // the draw changes with the step
        assert!((0..20).any(|t| batch_indices(&by_scene, 3, 42, t) != b));
    }

    #[test]
    fn cosine_schedule_warms_up_and_decays_to_zero() {
        let o = TrainOptions {
            steps: 10,
            warmup_steps: 2,
            lr: 1.0,
            ..options(10)
        };
        assert!((learning_rate(&o, 0) - 0.5).abs() < 1e-12);
        assert!((learning_rate(&o, 1) - 1.0).abs() < 1e-12);
        assert!((learning_rate(&o, 2) - 1.0).abs() < 1e-12);
        assert!(learning_rate(&o, 6) < 1.0 && learning_rate(&o, 6) > 0.0);
        assert!(learning_rate(&o, 10).abs() < 1e-12);
        let c = TrainOptions {
            lr_schedule: LrSchedule::Constant,
            ..o
        };
        assert_eq!(learning_rate(&c, 7), 1.0);
    }

    fn metrics_line(step: u64, kind: &str) -> String {
        let l = MetricsLine {
            step,
            kind: kind.into(),
            loss: 1.0 / step as f64,
            loss_conf: None,
            loss_id: None,
            lr: 1e-4,
            grad_norm: 1.0,
            chunks_per_s: 1.0,
            tokens_per_s: 1.0,
            elapsed_s: 0.0,
            val: None,
        };
        serde_json::to_string(&l).unwrap()
    }

    /// Lines past the resume step and a torn last line are dropped; the rest is kept verbatim.
    #[test]
    fn truncate_metrics_drops_lines_past_the_step_and_torn_lines() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.jsonl");
        assert_eq!(
            truncate_metrics(&path, 3).unwrap(),
            0,
            "a missing file is fine"
        );
        let kept: Vec<String> = vec![
            metrics_line(1, "train"),
            metrics_line(2, "train"),
            metrics_line(2, "val"),
            metrics_line(3, "train"),
        ];
        let mut text = kept.join("\n") + "\n";
        text += &(metrics_line(4, "train") + "\n" + &metrics_line(5, "train") + "\n");
        text += &metrics_line(6, "train")[..20]; // torn by a crash
        std::fs::write(&path, &text).unwrap();
        assert_eq!(truncate_metrics(&path, 3).unwrap(), 3);
        assert_eq!(
            std::fs::read_to_string(&path).unwrap(),
            kept.join("\n") + "\n"
        );
        assert_eq!(truncate_metrics(&path, 3).unwrap(), 0, "idempotent");
        assert_eq!(
            truncate_metrics(&path, 0).unwrap(),
            4,
            "a fresh run starts a new file"
        );
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "");
    }

    /// Temporaries of dead processes go, a live process's stays, other entries are untouched.
    #[test]
    fn stale_checkpoint_temporaries_of_dead_processes_are_removed() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("checkpoints");
        let mut gone = std::process::Command::new("true").spawn().unwrap();
        let dead = gone.id();
        gone.wait().unwrap();
        // A live process that is not this one: a sleeping child.
        let mut live_child = std::process::Command::new("sleep")
            .arg("30")
            .spawn()
            .unwrap();
        let stale = root.join(format!(".tmp-step-00000007-{dead}"));
        let mine = root.join(format!(".tmp-step-00000008-{}", std::process::id()));
        let live = root.join(format!(".tmp-step-00000009-{}", live_child.id()));
        let other = root.join("step-00000006");
        for d in [&stale, &mine, &live, &other] {
            std::fs::create_dir_all(d).unwrap();
        }
        let removed = remove_stale_checkpoint_temps(dir.path()).unwrap();
        live_child.kill().unwrap();
        live_child.wait().unwrap();
        assert_eq!(removed.len(), 2, "{removed:?}");
        assert!(
            !stale.exists() && !mine.exists(),
            "this process has not started writing: its own name is stale too"
        );
        assert!(live.exists() && other.exists());
    }
}
