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
//! Full windows are processed in sub-groups so that the gathered projection rows `[W L, 3C]`
//! stay below [`ROWS_BUDGET_FLOATS`]; the core of each sub-group is the kernel layer's
//! [`crate::kernels::window_attention`] (host kernels on the CPU backends, which hold no score
//! tensor; on CubeCL the flash kernel where autotune reaches it, otherwise the explicit form in
//! score-bounded sub-groups, network.md §7.5), whose `Backward` differentiates it.

use burn::module::Module;
use burn::nn::{Linear, LinearConfig};
use burn::tensor::{Device, Tensor};

use crate::host_attention::{WindowShape, window_attention};
use crate::host_attention_grad::window_attention_backward;
use crate::kernels::attention::attention_scale;
use crate::kernels::gather_rows;
use crate::prepared::AttnIndex;
use crate::profile;
use crate::readback::read_indices;

/// Upper bound on the floats of one sub-group's gathered projection rows `[W L, 3C]` (128 MiB
/// of f32).
pub const ROWS_BUDGET_FLOATS: usize = 32 * 1024 * 1024;

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
        let device = x.device();
        let mut outs = Vec::new();
        for sg in sub_groups(index, c, ROWS_BUDGET_FLOATS) {
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
                head_dim: c / h,
            };
            let o = profile::scope(
                || format!("{stage}.attn.core"),
                || crate::kernels::window_attention(rows, shape),
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

/// A slice of one window group: windows `w0..w0 + windows` of `groups[group]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct SubGroup {
    group: usize,
    w0: usize,
    windows: usize,
}

/// The window sub-groups of `index` (channels `c`), in output order: each holds at most
/// `budget` floats of gathered projection rows `[W L, 3C]`, and at least one window.
fn sub_groups(index: &AttnIndex, c: usize, budget: usize) -> Vec<SubGroup> {
    let mut out = Vec::new();
    for (gi, group) in index.groups.iter().enumerate() {
        let l = group.len;
        let step = (budget / (l * 3 * c).max(1)).max(1);
        let mut w0 = 0;
        while w0 < group.num_windows {
            let windows = step.min(group.num_windows - w0);
            out.push(SubGroup {
                group: gi,
                w0,
                windows,
            });
            w0 += windows;
        }
    }
    out
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
                attention_scale(shape.head_dim) as f32,
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
                attention_scale(shape.head_dim) as f32,
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

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

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
        // rows: 4 x 24 = 96 floats per window of 4 (C = 8), budget 200 -> 2 windows
        let sg = sub_groups(&index, 8, 200);
        let got: Vec<_> = sg.iter().map(|s| (s.group, s.w0, s.windows)).collect();
        assert_eq!(got, vec![(0, 0, 2), (0, 2, 2), (0, 4, 1), (1, 0, 1)]);
        // a budget below one window still takes one
        let sg = sub_groups(&index, 8, 10);
        assert_eq!(sg.len(), 6);
        assert!(sg.iter().all(|s| s.windows == 1));
    }
}
