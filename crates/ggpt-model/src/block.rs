//! Pre-norm PTv3 block with xCPE (network.md §5.2).
//!
//! ```text
//! x, x_conv : [N, C]      (x_conv = x except for the first block of a decoder stage, §9.2)
//! x1 = x  + CPE(x_conv)             CPE(u) = LayerNorm(Linear(SubMConv3d(u)))
//! x2 = x1 + DropPath(Attn(LN1(x1)))
//! x3 = x2 + DropPath(MLP(LN2(x2)))  MLP(u) = Linear_{4C->C}(GELU(Linear_{C->4C}(u)))
//! ```

use burn::module::{Module, ParamId};
use burn::nn::{LayerNorm, Linear, LinearConfig};
use burn::tensor::{Device, Tensor, TensorData};

use crate::attention::{HostAttnIndex, WindowAttention};
use crate::config::GgptConfig;
use crate::drop_path::DropPath;
use crate::host_conv_grad::{HostConvTables, subm_conv_backward};
use crate::host_dense::{HostLinear, HostNorm, LinearGrads, NormRows, scale_rows};
use crate::kernels::gelu;
use crate::norm::{layer_norm, layer_norm_forward};
use crate::ops::map_row_blocks;
use crate::prepared::PreparedLevel;
use crate::profile;
use crate::readback::read_values;
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
    /// Epsilon of the block's LayerNorms (`GgptConfig::ln_eps`; Burn's `LayerNorm` does not
    /// expose its own), for the host backward ([`Self::attn_part_backward`]).
    pub ln_eps: f64,
}

impl Block {
    /// Block `index` of a stage with `channels` / `num_heads`, drop-path rate `drop`.
    pub fn new(
        cfg: &GgptConfig,
        channels: usize,
        num_heads: usize,
        index: usize,
        drop: f64,
        device: &Device,
    ) -> Self {
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
            ln_eps: cfg.ln_eps,
        }
    }

    /// `x, x_conv [N, C] -> [N, C]`; records `{name}.{cpe_conv_out,cpe_out,attn_out,mlp_out,out}`.
    /// The composition of [`Self::cpe_part`], [`Self::attn_part`] and [`Self::mlp_part`] (the
    /// recomputation segments of `crate::recompute`).
    pub fn forward(
        &self,
        x: Tensor<2>,
        x_conv: Tensor<2>,
        level: &PreparedLevel,
        rec: &mut Recorder,
        name: &str,
    ) -> Tensor<2> {
        let x1 = self.cpe_part(x, x_conv, level, rec, name);
        let x2 = self.attn_part(x1, level, rec, name);
        self.mlp_part(x2, rec, name)
    }

    /// `x1 = x + CPE(x_conv)`: `x, x_conv [N, C] -> [N, C]`; records `{name}.cpe_conv_out`,
    /// `{name}.cpe_out`.
    pub fn cpe_part(
        &self,
        x: Tensor<2>,
        x_conv: Tensor<2>,
        level: &PreparedLevel,
        rec: &mut Recorder,
        name: &str,
    ) -> Tensor<2> {
        self.cpe_part_with_conv(x, x_conv, level, rec, name).0
    }

    /// [`Self::cpe_part`], also returning the sparse conv's output `[N, C]`, which
    /// [`Self::cpe_part_backward`] can take instead of recomputing it.
    pub fn cpe_part_with_conv(
        &self,
        x: Tensor<2>,
        x_conv: Tensor<2>,
        level: &PreparedLevel,
        rec: &mut Recorder,
        name: &str,
    ) -> (Tensor<2>, Tensor<2>) {
        let stage = stage_of(name);
        let conv = profile::scope(
            || format!("{stage}.conv"),
            || self.cpe.conv.forward(x_conv, &level.conv),
        );
        rec.record(|| format!("{name}.cpe_conv_out"), &conv);
        let cpe = profile::scope(
            || format!("{stage}.cpe_linear_ln"),
            || {
                layer_norm_forward(
                    &self.cpe.norm,
                    self.ln_eps,
                    self.cpe.linear.forward(conv.clone()),
                )
            },
        );
        rec.record(|| format!("{name}.cpe_out"), &cpe);
        (x + cpe, conv)
    }

    /// Backward of [`Self::cpe_part`] on the host (CPU training, `crate::recompute`,
    /// [`crate::host_conv_grad`], [`crate::host_dense`]): `x_conv [N, C]` (the conv input, no
    /// graph) and `g_x1 [N, C]` (the gradient of the segment output). `conv`, when given, is
    /// the conv output the forward computed ([`Self::cpe_part_with_conv`]); otherwise it is
    /// recomputed. No autodiff graph is built. [`PartGrads::inputs`] holds the gradients of
    /// `x` and `x_conv`. `None` when a host readback fails or the tables are inconsistent: the
    /// caller then differentiates [`Self::cpe_part`] itself.
    pub fn cpe_part_backward(
        &self,
        x_conv: Tensor<2>,
        conv: Option<Tensor<2>>,
        g_x1: Tensor<2>,
        level: &PreparedLevel,
    ) -> Option<PartGrads> {
        let [n, c_in] = x_conv.dims();
        let [c_out, k0, k1, k2, _] = self.cpe.conv.weight.dims();
        let device = x_conv.device();
        let tables = HostConvTables::read(&level.conv)?;
        let y = match conv {
            Some(y) if y.dims() == [n, c_out] => read_values(y)?,
            _ => read_values(
                self.cpe
                    .conv
                    .clone()
                    .no_grad()
                    .forward(x_conv.clone().autodiff(), &level.conv),
            )?,
        };
        let (linear, norm) = (
            HostLinear::read(&self.cpe.linear)?,
            HostNorm::read(&self.cpe.norm, self.ln_eps)?,
        );
        let g = read_values(g_x1.clone())?;
        // x1 = x + LN(y W + b): back through the LayerNorm and the Linear, then the conv
        let ln = norm.state(&linear.forward(&y));
        let mut grads = PartGrads::default();
        let g_z = grads.norm_backward(&self.cpe.norm, &ln, &norm, &g, None, &device);
        let d_lin = linear.backward(&y, &g_z);
        grads.linear(&self.cpe.linear, &d_lin, &device);
        let weight = read_values(self.cpe.conv.weight.val())?;
        let d = profile::scope(
            || "step.host_conv.backward".to_string(),
            || {
                subm_conv_backward(
                    &read_values(x_conv)?,
                    &d_lin.input,
                    &weight,
                    c_in,
                    c_out,
                    &tables,
                )
            },
        )?;
        grads.kernels.push((
            self.cpe.conv.weight.id,
            Tensor::from_data(
                TensorData::new(d.weight, [c_out, k0, k1, k2, c_in]),
                &device,
            ),
        ));
        grads.vectors.push((
            self.cpe.conv.bias.id,
            Tensor::from_data(TensorData::new(d.bias, [c_out]), &device),
        ));
        grads.inputs = vec![
            g_x1,
            Tensor::from_data(TensorData::new(d.input, [n, c_in]), &device),
        ];
        Some(grads)
    }

    /// `x2 = x1 + DropPath(Attn(LN1(x1)))`: `x1 [N, C] -> [N, C]`; records `{name}.attn_out`.
    pub fn attn_part(
        &self,
        x1: Tensor<2>,
        level: &PreparedLevel,
        rec: &mut Recorder,
        name: &str,
    ) -> Tensor<2> {
        self.attn_part_with_core(x1, level, rec, name).0
    }

    /// [`Self::attn_part`], also returning the attention before its output projection
    /// `[N, C]` ([`WindowAttention::core_profiled`]), which [`Self::attn_part_backward`] can
    /// take instead of recomputing it.
    pub fn attn_part_with_core(
        &self,
        x1: Tensor<2>,
        level: &PreparedLevel,
        rec: &mut Recorder,
        name: &str,
    ) -> (Tensor<2>, Tensor<2>) {
        let stage = stage_of(name);
        let normed = profile::scope(
            || format!("{stage}.ln1"),
            || layer_norm_forward(&self.norm1, self.ln_eps, x1.clone()),
        );
        let core = self
            .attn
            .core_profiled(normed, &level.attn[self.order_row], stage);
        let attn = self.attn.project(core.clone(), stage);
        rec.record(|| format!("{name}.attn_out"), &attn);
        (x1 + self.drop_path.forward(attn), core)
    }

    /// Backward of [`Self::attn_part`] on the host (CPU training, `crate::recompute`,
    /// [`crate::host_attention_grad`], [`crate::host_dense`]): `x1 [N, C]` (the segment input,
    /// no graph) and `g_x2 [N, C]` (the gradient of its output) -> [`PartGrads`] with the
    /// gradient of `x1`. No autodiff graph is built, and no score tensor. `None` when a host
    /// readback fails or the tables are inconsistent: the caller then differentiates
    /// [`Self::attn_part`] itself.
    ///
    /// `core`, when given, is the attention before its projection that the forward computed
    /// ([`Self::attn_part_with_core`], `[N, C]`): the backward then skips recomputing it.
    ///
    /// The drop-path mask is drawn once, as by [`Self::attn_part`] (the caller restores the
    /// mask RNG before).
    pub fn attn_part_backward(
        &self,
        x1: Tensor<2>,
        g_x2: Tensor<2>,
        level: &PreparedLevel,
        core: Option<Tensor<2>>,
    ) -> Option<PartGrads> {
        let [n, c] = x1.dims();
        let device = x1.device();
        let index = HostAttnIndex::read(&level.attn[self.order_row], n)?;
        let row_scale = self.drop_path_scale(n, &device)?;
        let (norm, qkv_linear, proj) = (
            HostNorm::read(&self.norm1, self.ln_eps)?,
            HostLinear::read(&self.attn.qkv)?,
            HostLinear::read(&self.attn.proj)?,
        );
        let g = read_values(g_x2)?;
        // x2 = x1 + s ⊙ proj(core(qkv(LN1(x1))))
        let (ln, u) = norm.forward(&read_values(x1)?);
        let qkv = qkv_linear.forward(&u);
        let (out, saved) = match core {
            Some(core) if core.dims() == [n, c] => {
                (read_values(core)?, self.attn.host_core_saved(&qkv, &index)?)
            }
            _ => profile::scope(
                || "step.host_attn_core.forward".to_string(),
                || self.attn.host_core_forward(&qkv, &index),
            )?,
        };
        drop(qkv);
        let mut g_y = vec![0.0; n * c];
        scale_rows(&g, row_scale.as_deref(), c, &mut g_y);
        let mut grads = PartGrads::default();
        let d_proj = proj.backward(&out, &g_y);
        drop((out, g_y));
        grads.linear(&self.attn.proj, &d_proj, &device);
        let d_qkv = profile::scope(
            || "step.host_attn_core.backward".to_string(),
            || self.attn.host_core_backward(&saved, &d_proj.input, &index),
        )?;
        drop(saved);
        let d_lin = qkv_linear.backward(&u, &d_qkv);
        grads.linear(&self.attn.qkv, &d_lin, &device);
        let g_x1 = grads.norm_backward(&self.norm1, &ln, &norm, &d_lin.input, Some(&g), &device);
        grads.inputs = vec![Tensor::from_data(TensorData::new(g_x1, [n, c]), &device)];
        Some(grads)
    }

    /// The drop-path scale of this block's next mask, per row `[N]` (`0` or `1 / (1 - p)`),
    /// drawn as [`DropPath::forward`] draws it (one draw per row); `Some(None)` when the drop
    /// path is inactive (scale 1), `None` when the readback fails.
    fn drop_path_scale(&self, n: usize, device: &Device) -> Option<Option<Vec<f32>>> {
        if !(self.drop_path.prob > 0.0 && self.drop_path.training.is_enabled()) {
            return Some(None);
        }
        let ones = Tensor::<2>::ones([n, 1], device).autodiff();
        read_values(self.drop_path.forward(ones)).map(Some)
    }

    /// `x3 = x2 + DropPath(MLP(LN2(x2)))`: `x2 [N, C] -> [N, C]`; records `{name}.mlp_out`,
    /// `{name}.out`.
    pub fn mlp_part(&self, x2: Tensor<2>, rec: &mut Recorder, name: &str) -> Tensor<2> {
        let stage = stage_of(name);
        let hidden = self.mlp.fc1.weight.dims()[1];
        let mlp = profile::scope(
            || format!("{stage}.ln2_mlp"),
            || {
                map_row_blocks(x2.clone(), hidden, |rows| {
                    self.mlp
                        .forward(layer_norm_forward(&self.norm2, self.ln_eps, rows))
                })
            },
        );
        rec.record(|| format!("{name}.mlp_out"), &mlp);
        let x3 = profile::scope(
            || format!("{stage}.residual"),
            || x2 + self.drop_path.forward(mlp),
        );
        rec.record(|| format!("{name}.out"), &x3);
        x3
    }
}

/// Gradients of a block part's host backward ([`Block::cpe_part_backward`],
/// [`Block::attn_part_backward`]), on the device of its inputs, no graph.
#[derive(Debug, Clone, Default)]
pub struct PartGrads {
    /// Of the part's inputs, in the order of its segment inputs (`[N, C]` each).
    pub inputs: Vec<Tensor<2>>,
    /// Of its rank-1 parameters (LayerNorm γ, β, biases).
    pub vectors: Vec<(ParamId, Tensor<1>)>,
    /// Of its Linear weights.
    pub matrices: Vec<(ParamId, Tensor<2>)>,
    /// Of its sparse-conv weights.
    pub kernels: Vec<(ParamId, Tensor<5>)>,
}

impl PartGrads {
    /// Adds the gradients of `linear` (weight and bias).
    fn linear(&mut self, linear: &Linear, d: &LinearGrads, device: &Device) {
        let [d_in, d_out] = linear.weight.dims();
        self.matrices.push((
            linear.weight.id,
            Tensor::from_data(TensorData::new(d.weight.clone(), [d_in, d_out]), device),
        ));
        if let Some(b) = &linear.bias {
            self.vectors.push((
                b.id,
                Tensor::from_data(TensorData::new(d.bias.clone(), [d_out]), device),
            ));
        }
    }

    /// Adds the gradients of `norm` (γ, β).
    fn norm(&mut self, norm: &LayerNorm, d_gamma: Vec<f32>, d_beta: Vec<f32>, device: &Device) {
        let c = d_gamma.len();
        self.vectors.push((
            norm.gamma.id,
            Tensor::from_data(TensorData::new(d_gamma, [c]), device),
        ));
        if let Some(b) = &norm.beta {
            self.vectors.push((
                b.id,
                Tensor::from_data(TensorData::new(d_beta, [c]), device),
            ));
        }
    }

    /// The LayerNorm backward ([`NormRows::backward`]): adds the gradients of `norm` and
    /// returns `residual + d x`.
    fn norm_backward(
        &mut self,
        norm: &LayerNorm,
        state: &NormRows,
        host: &HostNorm,
        g_u: &[f32],
        residual: Option<&[f32]>,
        device: &Device,
    ) -> Vec<f32> {
        let c = host.gamma.len();
        let (mut d_gamma, mut d_beta) = (vec![0.0; c], vec![0.0; c]);
        let dx = state.backward(g_u, &host.gamma, residual, &mut d_gamma, &mut d_beta);
        self.norm(norm, d_gamma, d_beta, device);
        dx
    }
}

/// Profile key of a block name: the stage (`enc0`, `dec3`, ...).
fn stage_of(name: &str) -> &str {
    name.split('.').next().unwrap_or(name)
}
