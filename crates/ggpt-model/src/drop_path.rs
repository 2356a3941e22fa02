//! Drop path (stochastic depth) on a residual branch, training only (network.md §11.3).

use burn::module::{Flag, Module, Param};
use burn::tensor::{Distribution, Tensor};

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
        Self { prob, training: Param::from_bool(true) }
    }

    /// `x [N, C] -> [N, C]`; active only on an autodiff device with the training flag on.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let device = x.device();
        if self.prob <= 0.0 || !device.is_autodiff() || !self.training.is_enabled() {
            return x;
        }
        let [n, _] = x.dims();
        let keep = 1.0 - self.prob;
        let mask = Tensor::<2>::random([n, 1], Distribution::Bernoulli(keep), &device).detach();
        x * mask.div_scalar(keep)
    }
}
