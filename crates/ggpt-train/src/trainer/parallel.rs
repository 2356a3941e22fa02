//! Data-parallel steps: the batch cut into parts, replicas on their devices (one thread each),
//! micro-batches per replica (gradient accumulation), gradients added in a fixed order.

use burn::module::{Module, Param};
use burn::optim::{GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor};
use ggpt_model::{Ggpt, GgptConfig};

use super::{Recompute, StepLoss, clip_global_norm, step_seed};
use crate::chunkset::TrainChunk;
use crate::error::{Result, TrainError};
use crate::loss::{HostTargets, loss};

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
            // summed in micro-batch order: steps are reproducible
            Some(a) => ggpt_model::grads::add(&replica, a, g),
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
            // summed in replica order: steps are reproducible
            Some(a) => ggpt_model::grads::add(&model, a, r.grads),
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::trainer::adam;
    use crate::trainer::test_util::{
        cpu, fresh, options, rel_to_max, rng_lock, toy_batch, weights,
    };

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
}
