//! Unpooling of decoder stage `s` (network.md §9.1).
//!
//! ```text
//! y         [N_{s+1}, D_{s+1}]   coarse features (enc4.out or dec{s+1}.out)
//! e_s       [N_s, E_s]           encoder skip (enc{s}.out)
//! proj      = GELU(BN(Linear(y)))        [N_{s+1}, D_s]
//! proj_skip = GELU(BN(Linear(e_s)))      [N_s, D_s]     also the stale xCPE input of dec{s}.block0 (§9.2)
//! u         = proj_skip + proj[cluster]  [N_s, D_s]
//! ```

use burn::module::Module;
use burn::tensor::{Device, Int, Tensor};

use crate::config::GgptConfig;
use crate::kernels::gather_rows;
use crate::linear_bn::LinearBnGelu;
use crate::recorder::Recorder;

/// Official `dec.dec{s}.up`: `proj.{0,1}` and `proj_skip.{0,1}`.
#[derive(Module, Debug)]
pub struct Unpooling {
    /// Coarse branch.
    pub proj: LinearBnGelu,
    /// Skip branch.
    pub proj_skip: LinearBnGelu,
}

impl Unpooling {
    /// New unpooling from `c_coarse` and `c_skip` channels to `c_out`.
    pub fn new(
        cfg: &GgptConfig,
        c_coarse: usize,
        c_skip: usize,
        c_out: usize,
        device: &Device,
    ) -> Self {
        Self {
            proj: LinearBnGelu::new(cfg, c_coarse, c_out, device),
            proj_skip: LinearBnGelu::new(cfg, c_skip, c_out, device),
        }
    }

    /// Returns `(u, proj_skip)`; records `{name}.proj`, `{name}.proj_skip`, `{name}.out`.
    pub fn forward(
        &self,
        coarse: Tensor<2>,
        skip: Tensor<2>,
        cluster: Tensor<1, Int>,
        rec: &mut Recorder,
        name: &str,
    ) -> (Tensor<2>, Tensor<2>) {
        let proj = self.proj.forward(coarse);
        rec.record(|| format!("{name}.proj"), &proj);
        let proj_skip = self.proj_skip.forward(skip);
        rec.record(|| format!("{name}.proj_skip"), &proj_skip);
        let u = proj_skip.clone() + gather_rows(proj, cluster);
        rec.record(|| format!("{name}.out"), &u);
        (u, proj_skip)
    }
}
