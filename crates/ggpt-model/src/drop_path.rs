//! Drop path (stochastic depth) on a residual branch, training only (network.md §11.3).

use std::cell::RefCell;

use burn::module::{Flag, Module, Param};
use burn::tensor::{Distribution, Tensor, TensorData};
use rand::{Rng, SeedableRng};

thread_local! {
    /// The mask RNG of this thread ([`seed_drop_path`]).
    static MASK_RNG: RefCell<Option<rand_pcg::Pcg64>> = const { RefCell::new(None) };
}

/// Seeds (or, with `None`, clears) the drop-path mask RNG of the **current thread**. While it is
/// set, masks are drawn on the host from it, in forward order, and uploaded; so a forward is
/// reproducible from the seed alone, whatever other threads do on the same device (data-parallel
/// replicas share a CPU device and its RNG). Unset, the device RNG is used.
pub fn seed_drop_path(seed: Option<u64>) {
    MASK_RNG.with(|r| *r.borrow_mut() = seed.map(rand_pcg::Pcg64::seed_from_u64));
}

/// The state of this thread's mask RNG (`None`: unseeded, masks come from the device RNG), so
/// that a recomputed segment draws the same masks as the forward ([`crate::recompute`]).
#[derive(Debug, Clone)]
pub struct MaskRngState(Option<rand_pcg::Pcg64>);

/// A copy of this thread's mask RNG state.
pub fn mask_rng_state() -> MaskRngState {
    MaskRngState(MASK_RNG.with(|r| r.borrow().clone()))
}

/// Restores a state taken by [`mask_rng_state`]: the following masks repeat the draws made
/// after it was taken.
pub fn restore_mask_rng(state: &MaskRngState) {
    MASK_RNG.with(|r| *r.borrow_mut() = state.0.clone());
}

impl MaskRngState {
    /// Whether masks are drawn on the host (the thread's RNG is seeded).
    pub fn is_seeded(&self) -> bool {
        self.0.is_some()
    }
}

/// Per row (token), independently per call: keep with probability `1 - p` and scale kept rows
/// by `1 / (1 - p)`. Identity when `p = 0`, outside training mode (see [`DropPath::forward`]),
/// or after `Module::valid`.
#[derive(Module, Debug)]
pub struct DropPath {
    /// Drop probability `p`.
    pub prob: f64,
    /// Training flag (disabled by `Module::valid`, like BatchNorm's).
    pub training: Param<Flag>,
}

impl DropPath {
    /// A drop path of rate `prob` in `[0, 1)`.
    pub fn new(prob: f64) -> Self {
        Self {
            prob,
            training: Param::from_bool(true),
        }
    }

    /// `x [N, C] -> [N, C]`; active only on an autodiff device with the training flag on.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let device = x.device();
        if self.prob <= 0.0 || !device.is_autodiff() || !self.training.is_enabled() {
            return x;
        }
        let [n, _] = x.dims();
        let keep = 1.0 - self.prob;
        let host: Option<Vec<f32>> = MASK_RNG.with(|r| {
            r.borrow_mut().as_mut().map(|rng| {
                (0..n)
                    .map(|_| if rng.random::<f64>() < keep { 1.0 } else { 0.0 })
                    .collect()
            })
        });
        let mask = match host {
            Some(values) => Tensor::<2>::from_data(TensorData::new(values, [n, 1]), &device),
            None => Tensor::<2>::random([n, 1], Distribution::Bernoulli(keep), &device),
        }
        .detach();
        x * mask.div_scalar(keep)
    }
}
