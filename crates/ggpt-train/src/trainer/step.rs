//! One optimisation step on one device, global-norm gradient clipping, and the optimiser.

use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::Device;
use ggpt_model::{Ggpt, GgptConfig};

use super::{Recompute, StepPlan, parallel_step};
use crate::chunkset::TrainChunk;
use crate::error::Result;

/// Global L2 norm of the gradients of `model`'s parameters, and optional rescaling so that it
/// is at most `max_norm` (PyTorch `clip_grad_norm_` semantics: factor `max / (norm + 1e-6)`).
pub fn clip_global_norm(
    model: &Ggpt,
    grads: &mut GradientsParams,
    max_norm: Option<f64>,
) -> Result<f64> {
    let norm = ggpt_model::grads::global_norm(model, grads)?;
    if let Some(max) = max_norm
        && norm > max
    {
        ggpt_model::grads::scale(model, grads, max / (norm + 1e-6));
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
