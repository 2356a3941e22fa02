//! `ggpt-train train`: the training loop on a chunk set, with a progress bar, Ctrl-C and
//! resume.

use anyhow::{Context, Result, bail};
use burn::module::Module;
use ggpt_cli::Bar;
use ggpt_model::Ggpt;
use ggpt_train::chunkset::ChunkSet;
use ggpt_train::trainer::{self, MetricsLine, RunContext, TrainOptions};

use crate::cli::{RESUME_LATEST, TrainArgs};

/// Runs `train`.
pub fn run(a: &TrainArgs) -> Result<()> {
    if a.grad_accum == Some(0) {
        bail!("--grad-accum 0: must be at least 1");
    }
    let data = ChunkSet::open(&a.data)?;
    let device_names = a.device_names()?;
    let device = ggpt_model::device::device_from_name(&device_names[0])?;
    let ad = device.clone().autodiff();
    let resume_dir = match &a.resume {
        None => None,
        Some(p) if p.as_os_str() == RESUME_LATEST => {
            let list = trainer::list_checkpoints(&a.out)?;
            Some(
                list.last()
                    .map(|(_, d)| d.clone())
                    .with_context(|| format!("--resume: no checkpoint in {}", a.out.display()))?,
            )
        }
        Some(p) => Some(p.clone()),
    };
    let recompute = a.recompute.map(trainer::Recompute::from);
    let (model, optim, start, opts) = if let Some(dir) = resume_dir {
        let (m, o, st) = trainer::load_checkpoint(&dir, &ad)?;
        let mut opts = st.options.clone();
        opts.steps = a.steps; // allow extending a run
        if a.devices.is_some() && device_names != opts.devices {
            tracing::warn!(
                "--devices {} differs from the checkpoint's {:?}: the trajectory changes",
                device_names.join(","),
                opts.devices
            );
            opts.devices = device_names.clone();
        }
        if let Some(k) = a.grad_accum
            && k != opts.grad_accum
        {
            tracing::warn!(
                "--grad-accum {k} differs from the checkpoint's {}: the trajectory changes",
                opts.grad_accum
            );
            opts.grad_accum = k;
        }
        if let Some(r) = recompute
            && r != opts.recompute
        {
            tracing::info!(
                "--recompute {r:?} differs from the checkpoint's {:?}: gradients change only by float rounding",
                opts.recompute
            );
            opts.recompute = r;
        }
        tracing::info!("resumed from {} at step {}", dir.display(), st.step);
        (m, o, st.step, opts)
    } else {
        // Fine-tuning: `--weights` may be a model folder (its weights file), and without
        // `--model-config` / `--preset` the configuration next to the weights is the network's.
        let init = a
            .init_weights()
            .map(|w| super::resolve_init_weights(w, &a.model))
            .transpose()?;
        let mut cfg = match &init {
            Some((_, Some(cfg))) => cfg.clone(),
            _ => super::model_config(&a.model, Some("small"))?,
        };
        if let Some(dp) = a.drop_path {
            cfg.drop_path = dp;
        }
        if let Some(m) = a.bn_momentum {
            if !(m > 0.0 && m <= 1.0) {
                bail!("--bn-momentum {m}: must be in (0, 1]");
            }
            cfg.bn_momentum = m;
        }
        device.seed(a.seed);
        let mut m = Ggpt::new(&cfg, &device);
        if let Some((init, _)) = &init {
            m = ggpt_model::weights::load_checkpoint(m, init)
                .with_context(|| format!("--weights {}", init.display()))?;
        }
        let opts = TrainOptions {
            model: cfg,
            steps: a.steps,
            batch_size: a.batch_size.max(1),
            lr: a.lr,
            lr_schedule: a.lr_schedule.into(),
            warmup_steps: a.warmup_steps,
            clip_grad_norm: a.clip_grad_norm,
            seed: a.seed,
            save_every: a.save_every,
            val_every: a.val_every,
            val_chunks: a.val_chunks,
            val_max_tokens: a.val_max_tokens,
            keep_checkpoints: a.keep_checkpoints,
            grad_accum: a.grad_accum.unwrap_or(1),
            devices: if a.devices.is_some() {
                device_names.clone()
            } else {
                Vec::new()
            },
            recompute: recompute.unwrap_or_default(),
        };
        (m.fork(&ad).train(), trainer::adam(), 0, opts)
    };
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let cfg_path = a.out.join("config.json");
    // the replicas: the recorded devices (a resumed run keeps its own), else --device
    let replica_names: Vec<String> = if opts.devices.is_empty() {
        vec![a.device.device.to_string()]
    } else {
        opts.devices.clone()
    };
    let replicas: Vec<burn::tensor::Device> = replica_names
        .iter()
        .map(|n| ggpt_model::device::device_from_name(n).map(|d| d.autodiff()))
        .collect::<std::result::Result<_, _>>()?;
    let ad = replicas[0].clone();
    let parts = replicas.len() * opts.grad_accum.max(1);
    if opts.batch_size < parts {
        bail!(
            "--batch-size {} is smaller than {} replica(s) x --grad-accum {}: every micro-batch needs a chunk",
            opts.batch_size,
            replicas.len(),
            opts.grad_accum
        );
    }
    let batchnorm = if parts == 1 {
        "batch statistics over all chunks of one forward".to_string()
    } else {
        format!(
            "batch statistics per micro-batch: the batch of {} chunks is split into {} replica(s) x {} micro-batch(es) of about {} chunks; \
             running statistics updated sequentially within a replica and averaged over replicas",
            opts.batch_size,
            replicas.len(),
            opts.grad_accum,
            opts.batch_size / parts
        )
    };
    let run_cfg = serde_json::json!({"options": opts, "data": a.data, "device": replica_names[0], "replicas": replica_names,
        "threads": a.device.threads,
        "grad_accum": opts.grad_accum, "recompute": opts.recompute, "init_from": a.init_weights(),
        "parameters": ggpt_model::weights::num_trainable_params(&model),
        "batchnorm": batchnorm});
    ggpt_core::io::atomic::write_json_atomic(&cfg_path, &run_cfg)?;
    tracing::info!(
        "training {} parameters on {} ({} steps from {start})",
        ggpt_model::weights::num_trainable_params(&model),
        replica_names.join(","),
        opts.steps
    );
    let stop = ggpt_cli::signals::stop_flag()?;
    let bar = Bar::new("train", opts.steps);
    bar.set_position(start);
    let mut on_step = |l: &MetricsLine| {
        bar.set_position(l.step);
        bar.set_message(&format!(
            "loss {:.4} (conf {:.4}, id {:.4}) {:.2} chunks/s {:.0} tok/s",
            l.loss,
            l.loss_conf.unwrap_or(f64::NAN),
            l.loss_id.unwrap_or(f64::NAN),
            l.chunks_per_s,
            l.tokens_per_s
        ));
    };
    let res = trainer::run(
        &opts,
        RunContext {
            out: &a.out,
            data: &data,
            device: ad,
            replicas,
            model,
            optim,
            start_step: start,
            stop,
            on_step: &mut on_step,
        },
    )?;
    bar.finish();
    if res.interrupted {
        println!(
            "interrupted at step {}: checkpoint written to {}",
            res.steps,
            trainer::checkpoint_dir(&a.out, res.steps).display()
        );
    } else {
        println!(
            "trained {} steps; checkpoint {}",
            res.steps,
            trainer::checkpoint_dir(&a.out, res.steps).display()
        );
    }
    if let Some(v) = &res.validation {
        println!(
            "held-out chunks: AUC@5 input {:.1} -> refined {:.1}; AUC@10 {:.1} -> {:.1} (val loss {:.4})",
            v.input_auc5, v.refined_auc5, v.input_auc10, v.refined_auc10, v.loss
        );
    }
    if let Some(dir) = &a.export_to {
        let chunking = ggpt_train::export::training_chunking(&data.manifest.provenance);
        ggpt_train::export::export_model_dir(&res.model, res.steps, &opts.model, chunking, dir)?;
        println!("exported {}", dir.display());
    }
    Ok(())
}
