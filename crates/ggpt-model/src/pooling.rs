//! Serialized pooling, stride 2 (network.md §8).
//!
//! ```text
//! x        [N_{l-1}, C_in]
//! p        = Linear_{C_in -> C_out}(x)                    [N_{l-1}, C_out]   (projection BEFORE the max)
//! pooled   = max over the children table of each cluster  [N_l, C_out]       fixture enc{l}.down.pooled
//! out      = GELU(BN(pooled))                             [N_l, C_out]       fixture enc{l}.down.out
//! ```
//!
//! The children table is padded with a member of the cluster, so the padded max equals the
//! cluster max and its gradient (gather + `max_dim`) is correct.

use burn::module::Module;
use burn::nn::{BatchNorm, Linear, LinearConfig};
use burn::tensor::{Device, Tensor};

use crate::config::GgptConfig;
use crate::kernels::gather_rows;
use crate::kernels::gelu;
use crate::norm::batch_norm;
use crate::prepared::PoolIndex;
use crate::recorder::Recorder;

/// Official `enc.enc{l}.down`: `proj` (Linear) and `norm.0` (BatchNorm).
#[derive(Module, Debug)]
pub struct SerializedPooling {
    /// `Linear(C_in -> C_out)`.
    pub proj: Linear,
    /// BatchNorm over `C_out`.
    pub norm: BatchNorm,
}

impl SerializedPooling {
    /// New pooling `C_in -> C_out`.
    pub fn new(cfg: &GgptConfig, c_in: usize, c_out: usize, device: &Device) -> Self {
        Self {
            proj: LinearConfig::new(c_in, c_out).init(device),
            norm: batch_norm(cfg, c_out, device),
        }
    }

    /// `x [N_{l-1}, C_in] -> [N_l, C_out]`; records `{name}.pooled`, `{name}.out`.
    pub fn forward(
        &self,
        x: Tensor<2>,
        pool: &PoolIndex,
        rec: &mut Recorder,
        name: &str,
    ) -> Tensor<2> {
        let p = self.proj.forward(x);
        let [_, c] = p.dims();
        let pooled = gather_rows(p, pool.children.clone())
            .reshape([pool.num_coarse, pool.width, c])
            .max_dim(1)
            .reshape([pool.num_coarse, c]);
        rec.record(|| format!("{name}.pooled"), &pooled);
        let out = gelu(crate::norm::batch_norm_forward(&self.norm, pooled));
        rec.record(|| format!("{name}.out"), &out);
        out
    }
}
