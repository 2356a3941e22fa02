//! BatchNorm / LayerNorm constructors with the network's constants (network.md §11).
//!
//! Burn's `nn::BatchNorm` on a rank-2 input `[N, C]` matches PyTorch's `BatchNorm1d`:
//! eval mode uses the running statistics, `(x - mean) / sqrt(var + eps) * gamma + beta`;
//! training mode (autodiff device and training flag on) normalises with the batch mean and
//! biased variance over all `N` rows and updates `running = (1 - m) running + m batch_stat`.
//! PyTorch updates `running_var` with the **unbiased** batch variance (`× N / (N - 1)`), Burn
//! 0.22.1's `BatchNorm::forward` with the biased one, so the network calls
//! [`batch_norm_forward`], which keeps Burn's normalisation and backward and applies PyTorch's
//! running update (checked against the official training step, `ggpt_small_train`). Momentum
//! 0.01 (PyTorch convention) and eps 1e-3 are set explicitly (Burn's defaults are 0.1 / 1e-5).

use std::cell::Cell;

use burn::nn::{BatchNorm, BatchNormConfig, LayerNorm, LayerNormConfig};
use burn::tensor::{Device, Tensor};

use crate::config::GgptConfig;

thread_local! {
    /// Whether [`batch_norm_forward`] leaves the running statistics alone on this thread.
    static FROZEN_RUNNING_STATS: Cell<bool> = const { Cell::new(false) };
}

/// Runs `f` with the running-statistics update of [`batch_norm_forward`] switched off on the
/// current thread (batch statistics are still used): a recomputed segment
/// ([`crate::recompute`]) must not count its batch a second time.
pub fn without_running_updates<R>(f: impl FnOnce() -> R) -> R {
    struct Restore(bool);
    impl Drop for Restore {
        fn drop(&mut self) {
            FROZEN_RUNNING_STATS.with(|c| c.set(self.0));
        }
    }
    let _restore = Restore(FROZEN_RUNNING_STATS.with(|c| c.replace(true)));
    f()
}

/// A BatchNorm over `channels` with eps / momentum from the config.
pub fn batch_norm(cfg: &GgptConfig, channels: usize, device: &Device) -> BatchNorm {
    BatchNormConfig::new(channels)
        .with_epsilon(cfg.bn_eps)
        .with_momentum(cfg.bn_momentum)
        .init(device)
}

/// An affine LayerNorm over the last axis (`channels`), eps from the config, biased variance.
pub fn layer_norm(cfg: &GgptConfig, channels: usize, device: &Device) -> LayerNorm {
    LayerNormConfig::new(channels)
        .with_epsilon(cfg.ln_eps)
        .init(device)
}

/// `ln` (epsilon `eps`, the one it was built with) applied to `x [N, C]`: the `layer_norm_rows`
/// op of the kernel layer (flex: Burn's fused multi-threaded LayerNorm forward and a host
/// backward, under autodiff as well; `docs/architecture.md`, "Kernel layer").
pub fn layer_norm_forward(ln: &LayerNorm, eps: f64, x: Tensor<2>) -> Tensor<2> {
    crate::kernels::layer_norm(x, ln.gamma.val(), ln.beta.as_ref().map(|b| b.val()), eps)
}

/// `bn` applied to `x` `[N, C]` -> `[N, C]` with PyTorch's training semantics: in training mode
/// (autodiff device, training flag on) it normalises with the batch statistics (Burn's
/// `batch_norm_train`, biased variance) and updates the running statistics with momentum `m`
/// as `mean ← (1-m) mean + m μ_B`, `var ← (1-m) var + m σ²_B N/(N-1)` (unbiased, as
/// `torch.nn.BatchNorm1d`; `N = 1` keeps the biased value). Otherwise the running statistics
/// are used, exactly as `BatchNorm::forward`.
pub fn batch_norm_forward(bn: &BatchNorm, x: Tensor<2>) -> Tensor<2> {
    if !(x.device().is_autodiff() && bn.training.is_enabled()) {
        return bn.forward(x);
    }
    let [n, _] = x.dims();
    let r = burn::tensor::module::batch_norm_train(x, bn.gamma.val(), bn.beta.val(), bn.epsilon);
    if FROZEN_RUNNING_STATS.with(Cell::get) {
        return r.output;
    }
    let device = r.output.device();
    let m = bn.momentum;
    let unbias = if n > 1 {
        n as f64 / (n - 1) as f64
    } else {
        1.0
    };
    let mean = bn.running_mean.value_sync().to_device(&device);
    let var = bn.running_var.value_sync().to_device(&device);
    bn.running_mean.update(
        mean.mul_scalar(1.0 - m)
            .add(r.mean.detach().mul_scalar(m))
            .detach(),
    );
    bn.running_var.update(
        var.mul_scalar(1.0 - m)
            .add(r.variance.detach().mul_scalar(m * unbias))
            .detach(),
    );
    r.output
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::TensorData;

    #[test]
    fn running_variance_is_updated_with_the_unbiased_batch_variance() {
        let device = crate::device::device_from_name("ndarray")
            .unwrap()
            .autodiff();
        let bn = BatchNormConfig::new(1).with_momentum(0.5).init(&device);
        let x = Tensor::<2>::from_data(TensorData::new(vec![1.0f32, 3.0], [2, 1]), &device);
        let y = batch_norm_forward(&bn, x);
        let mean: Vec<f32> = bn
            .running_mean
            .value_sync()
            .into_data()
            .try_to_vec::<f32>()
            .unwrap();
        let var: Vec<f32> = bn
            .running_var
            .value_sync()
            .into_data()
            .try_to_vec::<f32>()
            .unwrap();
        // batch mean 2, biased variance 1, unbiased 2: 0.5 * 0 + 0.5 * 2 and 0.5 * 1 + 0.5 * 2
        assert_eq!(mean, vec![1.0]);
        assert_eq!(var, vec![1.5]);
        let out: Vec<f32> = y.into_data().try_to_vec::<f32>().unwrap();
        let want = 1.0 / (1.0f32 + 1e-5).sqrt();
        assert!(
            (out[0] + want).abs() < 1e-6 && (out[1] - want).abs() < 1e-6,
            "{out:?}"
        );
    }
}
