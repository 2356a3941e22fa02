//! Pre-norm PTv3 block with xCPE (network.md §5.2).
//!
//! ```text
//! x, x_conv : [N, C]      (x_conv = x except for the first block of a decoder stage, §9.2)
//! x1 = x  + CPE(x_conv)             CPE(u) = LayerNorm(Linear(SubMConv3d(u)))
//! x2 = x1 + DropPath(Attn(LN1(x1)))
//! x3 = x2 + DropPath(MLP(LN2(x2)))  MLP(u) = Linear_{4C->C}(GELU(Linear_{C->4C}(u)))
//! ```

use burn::module::Module;
use burn::nn::{LayerNorm, Linear, LinearConfig};
use burn::tensor::{Device, Gradients, Tensor, TensorData};

use crate::attention::{HostAttnIndex, WindowAttention};
use crate::config::GgptConfig;
use crate::drop_path::DropPath;
use crate::gelu::gelu;
use crate::host_conv_grad::{HostConvTables, subm_conv_backward};
use crate::norm::layer_norm;
use crate::ops::map_row_blocks;
use crate::prepared::PreparedLevel;
use crate::profile;
use crate::recorder::Recorder;
use crate::sparse_conv::SubmConv3d;

/// xCPE: sparse conv -> Linear -> LayerNorm (official `cpe.0`, `cpe.1`, `cpe.2`).
#[derive(Module, Debug)]
pub struct Cpe {
    /// `SubMConv3d(C, C)`.
    pub conv: SubmConv3d,
    /// `Linear(C -> C)`.
    pub linear: Linear,
    /// LayerNorm over C.
    pub norm: LayerNorm,
}

/// The block MLP (official `mlp.0.fc1`, `mlp.0.fc2`).
#[derive(Module, Debug)]
pub struct Mlp {
    /// `Linear(C -> ratio C)`.
    pub fc1: Linear,
    /// `Linear(ratio C -> C)`.
    pub fc2: Linear,
}

impl Mlp {
    /// `u [N, C] -> [N, C]`.
    pub fn forward(&self, u: Tensor<2>) -> Tensor<2> {
        self.fc2.forward(gelu(self.fc1.forward(u)))
    }
}

/// One transformer block.
#[derive(Module, Debug)]
pub struct Block {
    /// Conditional positional encoding branch.
    pub cpe: Cpe,
    /// LN1 (official `norm1.0`).
    pub norm1: LayerNorm,
    /// Window attention.
    pub attn: WindowAttention,
    /// LN2 (official `norm2.0`).
    pub norm2: LayerNorm,
    /// MLP.
    pub mlp: Mlp,
    /// Drop path of the attention and MLP branches (training only).
    pub drop_path: DropPath,
    /// Order row used by this block (`i mod 4`).
    pub order_row: usize,
}

impl Block {
    /// Block `index` of a stage with `channels` / `num_heads`, drop-path rate `drop`.
    pub fn new(cfg: &GgptConfig, channels: usize, num_heads: usize, index: usize, drop: f64, device: &Device) -> Self {
        Self {
            cpe: Cpe {
                conv: SubmConv3d::new(channels, channels, device),
                linear: LinearConfig::new(channels, channels).init(device),
                norm: layer_norm(cfg, channels, device),
            },
            norm1: layer_norm(cfg, channels, device),
            attn: WindowAttention::new(channels, num_heads, device),
            norm2: layer_norm(cfg, channels, device),
            mlp: Mlp {
                fc1: LinearConfig::new(channels, cfg.mlp_ratio * channels).init(device),
                fc2: LinearConfig::new(cfg.mlp_ratio * channels, channels).init(device),
            },
            drop_path: DropPath::new(drop),
            order_row: index % 4,
        }
    }

    /// `x, x_conv [N, C] -> [N, C]`; records `{name}.{cpe_conv_out,cpe_out,attn_out,mlp_out,out}`.
    /// The composition of [`Self::cpe_part`], [`Self::attn_part`] and [`Self::mlp_part`] (the
    /// recomputation segments of `crate::recompute`).
    pub fn forward(&self, x: Tensor<2>, x_conv: Tensor<2>, level: &PreparedLevel, rec: &mut Recorder, name: &str) -> Tensor<2> {
        let x1 = self.cpe_part(x, x_conv, level, rec, name);
        let x2 = self.attn_part(x1, level, rec, name);
        self.mlp_part(x2, rec, name)
    }

    /// `x1 = x + CPE(x_conv)`: `x, x_conv [N, C] -> [N, C]`; records `{name}.cpe_conv_out`,
    /// `{name}.cpe_out`.
    pub fn cpe_part(&self, x: Tensor<2>, x_conv: Tensor<2>, level: &PreparedLevel, rec: &mut Recorder, name: &str) -> Tensor<2> {
        let stage = stage_of(name);
        let conv = profile::scope(|| format!("{stage}.conv"), || self.cpe.conv.forward(x_conv, &level.conv));
        rec.record(|| format!("{name}.cpe_conv_out"), &conv);
        let cpe = profile::scope(|| format!("{stage}.cpe_linear_ln"), || self.cpe.norm.forward(self.cpe.linear.forward(conv)));
        rec.record(|| format!("{name}.cpe_out"), &cpe);
        x + cpe
    }

    /// Backward of [`Self::cpe_part`] with the sparse conv differentiated on the host (CPU
    /// training, `crate::recompute`, [`crate::host_conv_grad`]): `x, x_conv [N, C]` (the segment
    /// inputs, no graph) and `g_x1 [N, C]` (the gradient of its output). The graph holds only
    /// the CPE Linear and LayerNorm on the conv output; their parameter gradients go to
    /// `collect`. `None` (nothing collected) when a host readback fails or the tables are
    /// inconsistent: the caller then differentiates [`Self::cpe_part`] itself.
    pub fn cpe_part_backward(&self, x: Tensor<2>, x_conv: Tensor<2>, g_x1: Tensor<2>, level: &PreparedLevel, collect: &mut dyn FnMut(&mut Gradients)) -> Option<CpeGrads> {
        let [n, c_in] = x_conv.dims();
        let c_out = self.cpe.conv.bias.val().dims()[0];
        let device = x.device();
        let tables = HostConvTables::read(&level.conv)?;
        // the conv output without a graph (frozen weights), then a leaf for the rest
        let conv = self.cpe.conv.clone().no_grad().forward(x_conv.clone().autodiff(), &level.conv);
        let y = conv.require_grad();
        let xb = x.autodiff().require_grad();
        let x1 = xb.clone() + self.cpe.norm.forward(self.cpe.linear.forward(y.clone()));
        let mut grads = (x1 * g_x1.autodiff()).sum().backward();
        let g_x = xb.grad_remove(&mut grads).unwrap_or_else(|| Tensor::zeros([n, c_in], &device));
        let g_y = match y.grad_remove(&mut grads) {
            Some(g) => read_f32(g)?,
            None => vec![0.0; n * c_out],
        };
        let weight = read_f32(self.cpe.conv.weight.val())?;
        let d = profile::scope(|| "step.host_conv.backward".to_string(), || subm_conv_backward(&read_f32(x_conv)?, &g_y, &weight, c_in, c_out, &tables))?;
        // only now, so that a `None` above collected nothing
        collect(&mut grads);
        let [_, k0, k1, k2, _] = self.cpe.conv.weight.dims();
        Some(CpeGrads {
            x: g_x,
            x_conv: Tensor::from_data(TensorData::new(d.input, [n, c_in]), &device),
            conv_weight: Tensor::from_data(TensorData::new(d.weight, [c_out, k0, k1, k2, c_in]), &device),
            conv_bias: Tensor::from_data(TensorData::new(d.bias, [c_out]), &device),
        })
    }

    /// `x2 = x1 + DropPath(Attn(LN1(x1)))`: `x1 [N, C] -> [N, C]`; records `{name}.attn_out`.
    pub fn attn_part(&self, x1: Tensor<2>, level: &PreparedLevel, rec: &mut Recorder, name: &str) -> Tensor<2> {
        self.attn_part_with_core(x1, level, rec, name).0
    }

    /// [`Self::attn_part`], also returning the attention before its output projection
    /// `[N, C]` ([`WindowAttention::core_profiled`]), which [`Self::attn_part_backward`] can
    /// take instead of recomputing it.
    pub fn attn_part_with_core(&self, x1: Tensor<2>, level: &PreparedLevel, rec: &mut Recorder, name: &str) -> (Tensor<2>, Tensor<2>) {
        let stage = stage_of(name);
        let normed = profile::scope(|| format!("{stage}.ln1"), || self.norm1.forward(x1.clone()));
        let core = self.attn.core_profiled(normed, &level.attn[self.order_row], stage);
        let attn = self.attn.project(core.clone(), stage);
        rec.record(|| format!("{name}.attn_out"), &attn);
        (x1 + self.drop_path.forward(attn), core)
    }

    /// Backward of [`Self::attn_part`] with the attention core on the host (CPU training,
    /// `crate::recompute`): `x1 [N, C]` (the segment input, no graph) and `g_x2 [N, C]` (the
    /// gradient of its output) -> the gradient of `x1`. The parameter gradients go to
    /// `collect`, once per partial backward. The graphs hold `LN1`, `qkv [N, 3C]` and `proj`,
    /// never a score tensor. `None` (nothing collected) when a host readback fails or the
    /// tables are inconsistent: the caller then differentiates [`Self::attn_part`] itself.
    ///
    /// `core`, when given, is the attention before its projection that the forward computed
    /// ([`Self::attn_part_with_core`], `[N, C]`): the backward then skips recomputing it.
    ///
    /// The drop-path mask is drawn once, as by [`Self::attn_part`] (the caller restores the
    /// mask RNG before).
    pub fn attn_part_backward(&self, x1: Tensor<2>, g_x2: Tensor<2>, level: &PreparedLevel, core: Option<Tensor<2>>, collect: &mut dyn FnMut(&mut Gradients)) -> Option<Tensor<2>> {
        let [n, c] = x1.dims();
        let device = x1.device();
        let index = HostAttnIndex::read(&level.attn[self.order_row], n)?;
        // qkv of every token under autodiff; its values for the host core
        let xa = x1.clone().autodiff().require_grad();
        let qkv = self.attn.qkv.forward(self.norm1.forward(xa.clone()));
        let qkv_host = read_f32(qkv.clone())?;
        let (out, saved) = match core {
            Some(core) if core.dims() == [n, c] => {
                (read_f32(core)?, self.attn.host_core_saved(&qkv_host, &index)?)
            }
            _ => profile::scope(|| "step.host_attn_core.forward".to_string(), || self.attn.host_core_forward(&qkv_host, &index))?,
        };
        drop(qkv_host);
        // y = x1 + DropPath(proj(out)): gradients of x1 (residual), proj and out
        let out = Tensor::<2>::from_data(TensorData::new(out, [n, c]), &device).autodiff().require_grad();
        let xb = x1.autodiff().require_grad();
        let y = xb.clone() + self.drop_path.forward(self.attn.proj.forward(out.clone()));
        let mut grads = (y * g_x2.autodiff()).sum().backward();
        let g_residual = xb.grad_remove(&mut grads);
        let g_out = out.grad_remove(&mut grads);
        let g_out = match g_out {
            Some(g) => read_f32(g)?,
            None => vec![0.0; n * c],
        };
        let d_qkv = profile::scope(|| "step.host_attn_core.backward".to_string(), || self.attn.host_core_backward(&saved, &g_out, &index))?;
        drop(saved);
        let d_qkv = Tensor::<2>::from_data(TensorData::new(d_qkv, [n, 3 * c]), &device).autodiff();
        let mut grads_ln = (qkv * d_qkv).sum().backward();
        let g_ln = xa.grad_remove(&mut grads_ln);
        // only now, so that a `None` above collected nothing
        collect(&mut grads);
        collect(&mut grads_ln);
        Some(match (g_residual, g_ln) {
            (Some(a), Some(b)) => a + b,
            (Some(a), None) | (None, Some(a)) => a,
            (None, None) => Tensor::zeros([n, c], &device),
        })
    }

    /// `x3 = x2 + DropPath(MLP(LN2(x2)))`: `x2 [N, C] -> [N, C]`; records `{name}.mlp_out`,
    /// `{name}.out`.
    pub fn mlp_part(&self, x2: Tensor<2>, rec: &mut Recorder, name: &str) -> Tensor<2> {
        let stage = stage_of(name);
        let hidden = self.mlp.fc1.weight.dims()[1];
        let mlp = profile::scope(
            || format!("{stage}.ln2_mlp"),
            || map_row_blocks(x2.clone(), hidden, |rows| self.mlp.forward(self.norm2.forward(rows))),
        );
        rec.record(|| format!("{name}.mlp_out"), &mlp);
        let x3 = profile::scope(|| format!("{stage}.residual"), || x2 + self.drop_path.forward(mlp));
        rec.record(|| format!("{name}.out"), &x3);
        x3
    }
}

/// Gradients of [`Block::cpe_part_backward`] (on the device of its inputs, no graph).
#[derive(Debug, Clone)]
pub struct CpeGrads {
    /// Of the residual input `x` `[N, C]`.
    pub x: Tensor<2>,
    /// Of the conv input `x_conv` `[N, C]`.
    pub x_conv: Tensor<2>,
    /// Of `cpe.conv.weight` `[C_out, 3, 3, 3, C_in]`.
    pub conv_weight: Tensor<5>,
    /// Of `cpe.conv.bias` `[C_out]`.
    pub conv_bias: Tensor<1>,
}

/// The f32 values of `t`, row-major; `None` when they cannot be read back.
fn read_f32<const D: usize>(t: Tensor<D>) -> Option<Vec<f32>> {
    t.try_into_data().ok()?.convert::<f32>().try_into_vec::<f32>().ok()
}

/// Profile key of a block name: the stage (`enc0`, `dec3`, ...).
fn stage_of(name: &str) -> &str {
    name.split('.').next().unwrap_or(name)
}
