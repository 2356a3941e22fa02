//! `GELU(BN(Linear(x)))`: the stem (network.md §5.1) and both unpooling branches (§9.1).

use burn::module::Module;
use burn::nn::{BatchNorm, Linear, LinearConfig};
use burn::tensor::{Device, Tensor};

use crate::config::GgptConfig;
use crate::kernels::gelu;
use crate::norm::batch_norm;

/// `Linear(C_in -> C_out)` -> BatchNorm -> exact GELU, per row.
///
/// Official keys: `<prefix>.0.{weight,bias}` (Linear) and `<prefix>.1.*` (BatchNorm).
#[derive(Module, Debug)]
pub struct LinearBnGelu {
    /// The projection; Burn layout `[C_in, C_out]`.
    pub linear: Linear,
    /// BatchNorm over `C_out`.
    pub norm: BatchNorm,
}

impl LinearBnGelu {
    /// New layer with PyTorch-default initialisation (network.md §11.4).
    pub fn new(cfg: &GgptConfig, c_in: usize, c_out: usize, device: &Device) -> Self {
        Self {
            linear: LinearConfig::new(c_in, c_out).init(device),
            norm: batch_norm(cfg, c_out, device),
        }
    }

    /// `x [N, C_in] -> [N, C_out]`.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        gelu(crate::norm::batch_norm_forward(
            &self.norm,
            self.linear.forward(x),
        ))
    }
}
