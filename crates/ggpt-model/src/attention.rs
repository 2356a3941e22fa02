//! Serialized window attention (network.md §7), flash window partition.
//!
//! ```text
//! per window group (W windows of L tokens, gathered by the order row):
//!   rows = Linear_{C -> 3C}(x[gather])                [W L, 3C] -> [W, L, 3, H, d]
//!          (columns q | k | v; head h owns h d..(h+1) d)
//!   q, k, v                                           [W, H, L, d]
//!   o    = softmax((q s) k^T) v                       [W, H, L, d] -> [W L, C]   (s = d^-1/2)
//! out  = concat(o of all groups)[take]                [N, C]    (each token from its owning window)
//! y    = Linear_{C -> C}(out)                         [N, C]
//! ```
//!
//! Full windows are processed in sub-groups so that the `[W, H, L, L]` score tensor stays below
//! [`SCORE_BUDGET_FLOATS`] (network.md §7.5).

use burn::module::Module;
use burn::nn::{Linear, LinearConfig};
use burn::tensor::activation::softmax;
use burn::tensor::module::attention;
use burn::tensor::ops::AttentionModuleOptions;
use burn::tensor::{Device, IndexingUpdateOp, Tensor, TensorData};

use crate::host_attention::{WindowShape, window_attention};
use crate::host_attention_grad::window_attention_backward;
use crate::kernels::gather_rows;
use crate::ops::is_cpu_device;
use crate::prepared::AttnIndex;
use crate::profile;
use crate::readback::read_indices;

/// Upper bound on the floats of one score tensor `[W, H, L, L]` (128 MiB of f32).
pub const SCORE_BUDGET_FLOATS: usize = 32 * 1024 * 1024;

/// Multi-head self-attention over serialization windows.
#[derive(Module, Debug)]
pub struct WindowAttention {
    /// `Linear(C -> 3C)` with bias (official `attn.qkv`).
    pub qkv: Linear,
    /// `Linear(C -> C)` (official `attn.proj`).
    pub proj: Linear,
    /// Heads `H`.
    pub num_heads: usize,
}

impl WindowAttention {
    /// New attention over `channels` with `num_heads` heads.
    pub fn new(channels: usize, num_heads: usize, device: &Device) -> Self {
        Self {
            qkv: LinearConfig::new(channels, 3 * channels).init(device),
            proj: LinearConfig::new(channels, channels).init(device),
            num_heads,
        }
    }

    /// `x [N, C]` (already LayerNorm-ed) `-> [N, C]` using the windows of one order row.
    pub fn forward(&self, x: Tensor<2>, index: &AttnIndex) -> Tensor<2> {
        self.forward_profiled(x, index, "attn")
    }

    /// [`Self::forward`], timing its parts under `{stage}.attn.{qkv,core,proj}` when
    /// [`crate::profile`] is on.
    ///
    /// On a CPU device, when `x` is not part of an autodiff graph (inference, and the
    /// graph-free forward of [`crate::recompute`]), the core is the host kernel of
    /// [`crate::host_attention`] (GEMM blocks + vectorised softmax, no `[W, H, L, L]` score
    /// tensor); otherwise the explicit `softmax(q k^T s) v` that autodiff differentiates.
    pub fn forward_profiled(&self, x: Tensor<2>, index: &AttnIndex, stage: &str) -> Tensor<2> {
        self.project(self.core_profiled(x, index, stage), stage)
    }

    /// The output projection `proj`: `core [N, C] -> [N, C]`, timed under `{stage}.attn.proj`.
    pub fn project(&self, core: Tensor<2>, stage: &str) -> Tensor<2> {
        profile::scope(|| format!("{stage}.attn.proj"), || self.proj.forward(core))
    }

    /// The attention before its output projection: `x [N, C]` (normalised tokens) `-> [N, C]`,
    /// every token's row of its window's `softmax(q kᵀ s) v` (heads concatenated). Timed under
    /// `{stage}.attn.{qkv,core}`; the core as described at [`Self::forward_profiled`].
    pub fn core_profiled(&self, x: Tensor<2>, index: &AttnIndex, stage: &str) -> Tensor<2> {
        let [_, c] = x.dims();
        let h = self.num_heads;
        let d = c / h;
        let scale = (d as f64).powf(-0.5);
        let device = x.device();
        let untracked = !x.is_tracked() && !self.qkv.weight.val().is_tracked();
        let host = untracked && is_cpu_device(&device);
        // GPU inference with autotune: Burn's fused attention, so that its flash kernel can be
        // picked. Without autotune that call is Burn's naive fallback, which scales the whole
        // score tensor and clamps its row maxima and sums (4 more launches per call than the
        // explicit form, which scales q): the explicit form is used then.
        let fused = untracked && !host && FLASH_REACHABLE;
        let mut outs = Vec::new();
        // The host kernel and the flash kernel need no score buffer: only bound the gathered
        // rows. Without autotune, Burn's fused attention is its naive fallback, which
        // materialises the scores: bound those.
        let scores_materialised = !(host || fused);
        for sg in sub_groups(index, c, h, SCORE_BUDGET_FLOATS, scores_materialised) {
            let (group, nw, w0) = (&index.groups[sg.group], sg.windows, sg.w0);
            let l = group.len;
            let idx = group.gather.clone().narrow(0, w0 * l, nw * l);
            // qkv is row-wise: project only the gathered rows (no [N, 3C] buffer).
            let rows = profile::scope(
                || format!("{stage}.attn.qkv"),
                || self.qkv.forward(gather_rows(x.clone(), idx)),
            );
            let shape = WindowShape {
                windows: nw,
                len: l,
                heads: h,
                head_dim: d,
            };
            let o = profile::scope(
                || format!("{stage}.attn.core"),
                || match host
                    .then(|| host_core(&rows, shape, scale as f32))
                    .flatten()
                {
                    Some(out) => Tensor::from_data(TensorData::new(out, [nw * l, c]), &device),
                    None => tensor_core(rows, shape, scale, host || fused),
                },
            );
            outs.push(o);
        }
        let all = match outs.len() {
            0 => return Tensor::zeros([0, c], &device),
            1 => match outs.pop() {
                Some(o) => o,
                None => return Tensor::zeros([0, c], &device),
            },
            _ => Tensor::cat(outs, 0),
        };
        gather_rows(all, index.take.clone())
    }
}

/// A slice of one window group: windows `w0..w0 + windows` of `groups[group]`, whose outputs
/// are rows `row0..row0 + windows · len` of the concatenated window outputs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct SubGroup {
    group: usize,
    w0: usize,
    windows: usize,
    row0: usize,
}

/// The window sub-groups of `index` (channels `c`, heads `h`), in output order: each holds at
/// most `budget` floats of scores `[W, H, L, L]` when `scores` (the score tensor is
/// materialised), otherwise of gathered projection rows `[W L, 3C]`; at least one window.
fn sub_groups(index: &AttnIndex, c: usize, h: usize, budget: usize, scores: bool) -> Vec<SubGroup> {
    let mut out = Vec::new();
    let mut row0 = 0;
    for (gi, group) in index.groups.iter().enumerate() {
        let l = group.len;
        let per_window = if scores { h * l * l } else { l * 3 * c };
        let step = (budget / per_window.max(1)).max(1);
        let mut w0 = 0;
        while w0 < group.num_windows {
            let windows = step.min(group.num_windows - w0);
            out.push(SubGroup {
                group: gi,
                w0,
                windows,
                row0,
            });
            w0 += windows;
            row0 += windows * l;
        }
    }
    out
}

/// The gradients of [`WindowAttention::core_backward_grouped`]: of the normalised tokens and of
/// the `qkv` Linear.
#[derive(Debug)]
pub struct CoreGrads {
    /// `[N, C]`, of the core's input.
    pub input: Tensor<2>,
    /// `[C, 3C]`, of `qkv.weight`.
    pub qkv_weight: Tensor<2>,
    /// `[3C]`, of `qkv.bias`.
    pub qkv_bias: Option<Tensor<1>>,
}

impl WindowAttention {
    /// The gradient of the core ([`Self::core_profiled`]: `qkv`, gathers, `softmax(q kᵀ s) v`,
    /// take) on any device, one window sub-group at a time: `u [N, C]` (the normalised tokens,
    /// no autodiff), `d_core [N, C]` (no autodiff) -> [`CoreGrads`] (no autodiff).
    ///
    /// Each sub-group's rows and `[W, H, L, L]` scores are rebuilt under autodiff,
    /// differentiated against its rows of `d_core`, and freed before the next: the graph never
    /// holds more than `score_budget` floats of scores (the training formulation of GPU
    /// devices, whose memory does not grow with the number of windows; docs/training.md).
    /// `self` must be the tracked (training) layer.
    pub fn core_backward_grouped(
        &self,
        u: Tensor<2>,
        d_core: Tensor<2>,
        index: &AttnIndex,
        score_budget: usize,
    ) -> Option<CoreGrads> {
        let [_, c] = u.dims();
        let h = self.num_heads;
        if h == 0 || c % h != 0 {
            return None;
        }
        let d = c / h;
        let scale = (d as f64).powf(-0.5);
        let inner = u.device();
        let rows_total: usize = index.groups.iter().map(|g| g.num_windows * g.len).sum();
        // every token's output gradient at its window row (rows no token takes get 0)
        let d_rows = Tensor::<2>::zeros([rows_total, c], &inner).select_assign(
            0,
            index.take.clone(),
            d_core,
            IndexingUpdateOp::Add,
        );
        let u_leaf = u.autodiff().require_grad();
        let (mut d_u, mut d_w, mut d_b): (Option<Tensor<2>>, Option<Tensor<2>>, Option<Tensor<1>>) =
            (None, None, None);
        fn add<const D: usize>(acc: &mut Option<Tensor<D>>, g: Option<Tensor<D>>) {
            if let Some(g) = g {
                *acc = Some(match acc.take() {
                    Some(a) => a + g,
                    None => g,
                });
            }
        }
        for sg in sub_groups(index, c, h, score_budget, true) {
            let group = &index.groups[sg.group];
            let l = group.len;
            let idx = group.gather.clone().narrow(0, sg.w0 * l, sg.windows * l);
            let rows = self.qkv.forward(gather_rows(u_leaf.clone(), idx));
            let shape = WindowShape {
                windows: sg.windows,
                len: l,
                heads: h,
                head_dim: d,
            };
            let o = tensor_core(rows, shape, scale, false);
            let g = d_rows.clone().narrow(0, sg.row0, sg.windows * l).autodiff();
            let mut grads = (o * g).sum().backward();
            add(&mut d_u, u_leaf.grad_remove(&mut grads));
            add(&mut d_w, self.qkv.weight.val().grad_remove(&mut grads));
            if let Some(b) = &self.qkv.bias {
                add(&mut d_b, b.val().grad_remove(&mut grads));
            }
        }
        let [n, _] = u_leaf.dims();
        Some(CoreGrads {
            input: d_u.unwrap_or_else(|| Tensor::zeros([n, c], &inner)),
            qkv_weight: d_w.unwrap_or_else(|| Tensor::zeros([c, 3 * c], &inner)),
            qkv_bias: match (&self.qkv.bias, d_b) {
                (Some(_), Some(b)) => Some(b),
                (Some(_), None) => Some(Tensor::zeros([3 * c], &inner)),
                (None, _) => None,
            },
        })
    }
}

/// Host copies of the tables of one [`AttnIndex`], for the training core
/// ([`WindowAttention::host_core_forward`]).
#[derive(Debug, Clone)]
pub struct HostAttnIndex {
    /// Per window group: the token of every window slot (`[W L]`), `W`, `L`.
    pub groups: Vec<(Vec<usize>, usize, usize)>,
    /// `[N]`: for every token, its row in the concatenated window outputs.
    pub take: Vec<usize>,
}

impl HostAttnIndex {
    /// Reads the tables of `index` back; `None` when they cannot be read or are inconsistent
    /// (a gather entry outside `0..num_tokens`, a take entry outside the window rows).
    pub fn read(index: &AttnIndex, num_tokens: usize) -> Option<Self> {
        let mut groups = Vec::with_capacity(index.groups.len());
        let mut rows = 0;
        for g in &index.groups {
            let gather = read_indices(&g.gather)?;
            if gather.len() != g.num_windows * g.len || gather.iter().any(|&t| t >= num_tokens) {
                return None;
            }
            rows += gather.len();
            groups.push((gather, g.num_windows, g.len));
        }
        let take = read_indices(&index.take)?;
        (take.len() == num_tokens && take.iter().all(|&r| r < rows))
            .then_some(Self { groups, take })
    }
}

/// What [`WindowAttention::host_core_forward`] keeps for its backward: the gathered
/// projection rows of every window group.
#[derive(Debug)]
pub struct HostCoreSaved {
    groups: Vec<(Vec<f32>, WindowShape)>,
}

impl WindowAttention {
    /// The attention core on the host from the projection of every token:
    /// `qkv [N, 3C]` row-major (the `qkv` Linear applied to all `N` rows) `-> [N, C]`, the
    /// same function as [`Self::core_profiled`] (whose `qkv` runs on the gathered rows), and
    /// what its backward needs.
    pub fn host_core_forward(
        &self,
        qkv: &[f32],
        index: &HostAttnIndex,
    ) -> Option<(Vec<f32>, HostCoreSaved)> {
        let saved = self.host_core_saved(qkv, index)?;
        let c = self.qkv.weight.dims()[1] / 3;
        let mut all = Vec::new();
        for (rows, shape) in &saved.groups {
            all.extend(window_attention(
                rows,
                *shape,
                attention_scale(shape.head_dim),
            )?);
        }
        let mut out = Vec::with_capacity(index.take.len() * c);
        for &r in &index.take {
            out.extend_from_slice(all.get(r * c..(r + 1) * c)?);
        }
        Some((out, saved))
    }

    /// What [`Self::host_core_backward`] needs from `qkv [N, 3C]` (row-major, every token):
    /// the projection rows of every window slot, group by group. `None` when the lengths do
    /// not match the layer.
    pub fn host_core_saved(&self, qkv: &[f32], index: &HostAttnIndex) -> Option<HostCoreSaved> {
        let (c3, n) = (self.qkv.weight.dims()[1], index.take.len());
        let (c, h) = (c3 / 3, self.num_heads);
        if qkv.len() != n * c3 || h == 0 || c % h != 0 {
            return None;
        }
        let d = c / h;
        let mut groups = Vec::with_capacity(index.groups.len());
        for (gather, windows, len) in &index.groups {
            let mut rows = Vec::with_capacity(gather.len() * c3);
            for &t in gather {
                rows.extend_from_slice(qkv.get(t * c3..(t + 1) * c3)?);
            }
            groups.push((
                rows,
                WindowShape {
                    windows: *windows,
                    len: *len,
                    heads: h,
                    head_dim: d,
                },
            ));
        }
        Some(HostCoreSaved { groups })
    }

    /// Gradient of [`Self::host_core_forward`]: `d_out [N, C]` -> `d_qkv [N, 3C]` (the rows of
    /// a token that sits in several window slots, padding included, are summed).
    pub fn host_core_backward(
        &self,
        saved: &HostCoreSaved,
        d_out: &[f32],
        index: &HostAttnIndex,
    ) -> Option<Vec<f32>> {
        let n = index.take.len();
        let c3 = self.qkv.weight.dims()[1];
        let c = c3 / 3;
        if d_out.len() != n * c {
            return None;
        }
        // the gradient of every window output row (rows no token takes get 0)
        let total: usize = saved.groups.iter().map(|(rows, _)| rows.len() / 3).sum();
        let mut d_rows_out = vec![0.0f32; total];
        for (t, &r) in index.take.iter().enumerate() {
            d_rows_out
                .get_mut(r * c..(r + 1) * c)?
                .copy_from_slice(&d_out[t * c..(t + 1) * c]);
        }
        let mut d_qkv = vec![0.0f32; n * c3];
        let mut offset = 0;
        for ((rows, shape), (gather, _, _)) in saved.groups.iter().zip(&index.groups) {
            let m = rows.len() / 3;
            let d_rows = window_attention_backward(
                rows,
                d_rows_out.get(offset..offset + m)?,
                *shape,
                attention_scale(shape.head_dim),
            )?;
            offset += m;
            for (&t, g) in gather.iter().zip(d_rows.chunks_exact(c3)) {
                for (acc, x) in d_qkv[t * c3..(t + 1) * c3].iter_mut().zip(g) {
                    *acc += x;
                }
            }
        }
        Some(d_qkv)
    }
}

/// The softmax scale `d^-1/2` of a head width `d` (network.md §7), in f32 for the host kernels.
fn attention_scale(head_dim: usize) -> f32 {
    (head_dim as f64).powf(-0.5) as f32
}

/// The host kernel on the `[W L, 3C]` projection rows; `None` when they cannot be read back as
/// f32 (the caller then uses the tensor formulation).
fn host_core(rows: &Tensor<2>, shape: WindowShape, scale: f32) -> Option<Vec<f32>> {
    crate::device_stats::note_readback();
    let data = rows.clone().try_into_data().ok()?.convert::<f32>();
    let v = data.as_slice::<f32>().ok()?;
    window_attention(v, shape, scale)
}

/// Whether Burn can choose its flash attention kernel: only its autotune does (burn-cubecl
/// 0.22.1 `ops/module.rs`: without autotune `module::attention` is the naive fallback, which
/// materialises the `[W, H, L, L]` scores).
const FLASH_REACHABLE: bool = cfg!(feature = "autotune");

/// The tensor formulation of the core: `rows [W L, 3C] -> [W L, C]`. `fused` uses Burn's
/// `module::attention` (not differentiated here) with `scale = None`, the only form for which
/// burn-cubecl may pick its flash kernel (any `scale` sends it to the naive fallback; the
/// default `d^-1/2` is the network's `s`); otherwise the explicit `softmax(q k^T s) v` that autodiff differentiates.
fn tensor_core(rows: Tensor<2>, shape: WindowShape, scale: f64, fused: bool) -> Tensor<2> {
    let WindowShape {
        windows: nw,
        len: l,
        heads: h,
        head_dim: d,
    } = shape;
    // [3, W, H, L, d]: one permutation, then q, k, v are views.
    let qkv = rows.reshape([nw, l, 3, h, d]).permute([2, 0, 3, 1, 4]);
    let part = |i: usize| qkv.clone().narrow(0, i, 1).reshape([nw, h, l, d]);
    let (q, k, v) = (part(0), part(1), part(2));
    let o = if fused {
        let opts = AttentionModuleOptions {
            scale: None,
            softcap: None,
            is_causal: false,
        };
        // `scale = None` is the kernels' default `d^-1/2`, which is the network's scale
        // (network.md §7): q needs no pre-scaling.
        attention(q, k, v, None, None, opts)
    } else {
        let scores = q.mul_scalar(scale).matmul(k.swap_dims(2, 3));
        softmax(scores, 3).matmul(v)
    };
    o.swap_dims(1, 2).reshape([nw * l, shape.channels()])
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use burn::tensor::Distribution;

    /// Burn's fused attention, called as the GPU inference path calls it (`scale = None`),
    /// equals the explicit `softmax((q s) kᵀ) v` on the same rows: same layout, same scale.
    fn fused_equals_explicit_on(device: &Device) {
        let shape = WindowShape {
            windows: 3,
            len: 20,
            heads: 2,
            head_dim: 8,
        };
        device.seed(3);
        let rows = Tensor::<2>::random(
            [shape.windows * shape.len, 3 * shape.channels()],
            Distribution::Uniform(-2.0, 2.0),
            device,
        );
        let scale = (shape.head_dim as f64).powf(-0.5);
        let fused = tensor_core(rows.clone(), shape, scale, true);
        let explicit = tensor_core(rows, shape, scale, false);
        let (a, b) = (
            crate::readback::tensor_into_f32(fused, "fused").unwrap(),
            crate::readback::tensor_into_f32(explicit, "explicit").unwrap(),
        );
        let worst = a
            .iter()
            .zip(&b)
            .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
        assert!(worst < 1e-5, "fused vs explicit: {worst:e}");
    }

    #[test]
    fn fused_core_equals_explicit_core() {
        fused_equals_explicit_on(&crate::device::device_from_name("ndarray").unwrap());
        fused_equals_explicit_on(&crate::device::device_from_name("flex").unwrap());
    }

    /// The same on wgpu (Burn's fallback without the `autotune` feature, the flash kernel where
    /// autotune picks it).
    #[cfg(feature = "wgpu")]
    #[test]
    fn fused_core_equals_explicit_core_on_wgpu() {
        fused_equals_explicit_on(&crate::device::device_from_name("wgpu").unwrap());
    }

    /// The sub-groups cover every window once, in output order, within the budget.
    #[test]
    fn sub_groups_cover_the_windows_in_order() {
        let device = crate::device::device_from_name("ndarray").unwrap();
        let group = |windows: usize, len: usize| crate::prepared::WindowGroup {
            gather: Tensor::zeros([windows * len], &device),
            num_windows: windows,
            len,
        };
        let index = AttnIndex {
            groups: vec![group(5, 4), group(1, 3)],
            take: Tensor::zeros([0], &device),
        };
        // scores: 2 heads x 4 x 4 = 32 floats per window of 4, budget 70 -> 2 windows
        let sg = sub_groups(&index, 8, 2, 70, true);
        let got: Vec<_> = sg
            .iter()
            .map(|s| (s.group, s.w0, s.windows, s.row0))
            .collect();
        assert_eq!(
            got,
            vec![(0, 0, 2, 0), (0, 2, 2, 8), (0, 4, 1, 16), (1, 0, 1, 20)]
        );
        // rows: 4 x 24 = 96 floats per window of 4; a budget below one window still takes one
        let sg = sub_groups(&index, 8, 2, 10, false);
        assert_eq!(sg.len(), 6);
        assert!(sg.iter().all(|s| s.windows == 1));
    }
}
