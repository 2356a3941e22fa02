//! BatchNorm / LayerNorm constructors with the network's constants (network.md §11).
//!
//! Burn's `nn::BatchNorm` on a rank-2 input `[N, C]` matches PyTorch's `BatchNorm1d`:
//! eval mode uses the running statistics, `(x - mean) / sqrt(var + eps) * gamma + beta`;
//! training mode (autodiff device and training flag on) normalises with the batch mean and
//! biased variance over all `N` rows and updates `running = (1 - m) running + m batch_stat`
//! (Burn uses the biased variance for the running update, PyTorch the unbiased one: negligible
//! at these token counts, network.md §11.2). Momentum 0.01 (PyTorch convention) and eps 1e-3
//! are set explicitly (Burn's defaults are 0.1 / 1e-5).

use burn::nn::{BatchNorm, BatchNormConfig, LayerNorm, LayerNormConfig};
use burn::tensor::Device;

use crate::config::GgptConfig;

/// A BatchNorm over `channels` with eps / momentum from the config.
pub fn batch_norm(cfg: &GgptConfig, channels: usize, device: &Device) -> BatchNorm {
    BatchNormConfig::new(channels).with_epsilon(cfg.bn_eps).with_momentum(cfg.bn_momentum).init(device)
}

/// An affine LayerNorm over the last axis (`channels`), eps from the config, biased variance.
pub fn layer_norm(cfg: &GgptConfig, channels: usize, device: &Device) -> LayerNorm {
    LayerNormConfig::new(channels).with_epsilon(cfg.ln_eps).init(device)
}
