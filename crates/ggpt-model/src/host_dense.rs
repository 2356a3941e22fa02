//! Dense row-wise kernels on the host for the CPU backward of a block's branches
//! ([`crate::block::Block::attn_part_backward`], [`crate::block::Block::cpe_part_backward`],
//! the LayerNorm backward of the kernel layer): LayerNorm forward/backward by rows, column
//! sums and multi-threaded GEMMs, every pass split over the rayon pool. All buffers are
//! row-major `[rows, width]` f32.
//!
//! Why hand-written: Burn 0.22.1's flex backend runs element-wise ops, reductions over rows and
//! autodiff's decomposed LayerNorm on one thread (docs/performance.md).

use burn::nn::{LayerNorm, Linear};
use rayon::prelude::*;

use crate::readback::read_values;

/// Rows per rayon task of the row-wise passes.
pub(crate) const ROWS_PER_TASK: usize = 64;

/// A LayerNorm of `[rows, C]` kept for its backward: `xhat = (x - mean) rstd`, `rstd [rows]`.
#[derive(Debug, Clone, Default)]
pub(crate) struct NormRows {
    pub xhat: Vec<f32>,
    pub rstd: Vec<f32>,
}

impl NormRows {
    /// The kept state of `LN(x)` for `x [rows, C]` (biased variance), without its output:
    /// for a LayerNorm whose output the caller does not need.
    pub fn of(x: &[f32], channels: usize, eps: f32) -> Self {
        let c = channels.max(1);
        let mut state = Self {
            xhat: vec![0.0; x.len()],
            rstd: vec![0.0; x.len() / c],
        };
        normalize_rows(x, c, eps, &mut state.xhat, &mut state.rstd);
        state
    }

    /// `LN(x)` of `x [rows, C]` (biased variance, `C = gamma.len()`): the kept state and
    /// `u = xhat γ + β`.
    pub fn forward(x: &[f32], gamma: &[f32], beta: Option<&[f32]>, eps: f32) -> (Self, Vec<f32>) {
        let state = Self::of(x, gamma.len(), eps);
        let mut u = vec![0.0; x.len()];
        affine_rows(&state.xhat, gamma, beta, &mut u);
        (state, u)
    }

    /// The backward: `g_u [rows, C]` (gradient of `u`) -> `residual + d x` (`residual`:
    /// `None` = 0), and adds `Σ g_u ⊙ xhat`, `Σ g_u` into `d_gamma`, `d_beta`.
    pub fn backward(
        &self,
        g_u: &[f32],
        gamma: &[f32],
        residual: Option<&[f32]>,
        d_gamma: &mut [f32],
        d_beta: &mut [f32],
    ) -> Vec<f32> {
        let mut dx = vec![0.0; g_u.len()];
        layer_norm_backward_rows(
            g_u, &self.xhat, &self.rstd, gamma, residual, &mut dx, d_gamma, d_beta,
        );
        dx
    }
}

/// Row-wise normalisation of `x [rows, C]` (biased variance): `xhat = (x - mean) rstd` and
/// `rstd = 1 / sqrt(var + eps)` `[rows]`.
fn normalize_rows(x: &[f32], c: usize, eps: f32, xhat: &mut [f32], rstd: &mut [f32]) {
    x.par_chunks(ROWS_PER_TASK * c)
        .zip(xhat.par_chunks_mut(ROWS_PER_TASK * c))
        .zip(rstd.par_chunks_mut(ROWS_PER_TASK))
        .for_each(|((x, xh), rs)| {
            for ((x, xh), r) in x.chunks(c).zip(xh.chunks_mut(c)).zip(rs.iter_mut()) {
                let mean = x.iter().sum::<f32>() / c as f32;
                let var = x.iter().map(|&v| (v - mean) * (v - mean)).sum::<f32>() / c as f32;
                *r = 1.0 / (var + eps).sqrt();
                for (xh, &v) in xh.iter_mut().zip(x) {
                    *xh = (v - mean) * *r;
                }
            }
        });
}

/// `u = xhat γ + β` by rows (`xhat, u [rows, C]`, `C = gamma.len()`; `beta`: `None` = 0).
fn affine_rows(xhat: &[f32], gamma: &[f32], beta: Option<&[f32]>, u: &mut [f32]) {
    let c = gamma.len();
    xhat.par_chunks(ROWS_PER_TASK * c)
        .zip(u.par_chunks_mut(ROWS_PER_TASK * c))
        .for_each(|(xh, u)| {
            for (xh, u) in xh.chunks(c).zip(u.chunks_mut(c)) {
                for (i, (u, &v)) in u.iter_mut().zip(xh).enumerate() {
                    *u = v * gamma[i] + beta.map_or(0.0, |b| b[i]);
                }
            }
        });
}

/// LayerNorm backward of a row block: `g_u [rows, C]` (gradient of the LN output), `xhat`,
/// `rstd` -> `dx = residual + rstd (g_u γ - mean(g_u γ) - xhat mean(g_u γ ⊙ xhat))`
/// (`residual`: `None` = 0), and adds
/// `Σ g_u ⊙ xhat`, `Σ g_u` into `d_gamma`, `d_beta`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn layer_norm_backward_rows(
    g_u: &[f32],
    xhat: &[f32],
    rstd: &[f32],
    gamma: &[f32],
    residual: Option<&[f32]>,
    dx: &mut [f32],
    d_gamma: &mut [f32],
    d_beta: &mut [f32],
) {
    let c = gamma.len();
    let partial = g_u
        .par_chunks(ROWS_PER_TASK * c)
        .zip(xhat.par_chunks(ROWS_PER_TASK * c))
        .zip(rstd.par_chunks(ROWS_PER_TASK))
        .zip(dx.par_chunks_mut(ROWS_PER_TASK * c))
        .enumerate()
        .map(|(t, (((gu, xh), rs), dx))| {
            let (mut dg, mut db) = (vec![0.0f32; c], vec![0.0f32; c]);
            for (i, (((gu, xh), &r), dx)) in gu
                .chunks(c)
                .zip(xh.chunks(c))
                .zip(rs)
                .zip(dx.chunks_mut(c))
                .enumerate()
            {
                let row = t * ROWS_PER_TASK + i;
                let res = residual.map(|res| &res[row * c..(row + 1) * c]);
                let (mut mean_g, mut mean_gx) = (0.0f32, 0.0f32);
                for i in 0..c {
                    let gg = gu[i] * gamma[i];
                    mean_g += gg;
                    mean_gx += gg * xh[i];
                    dg[i] += gu[i] * xh[i];
                    db[i] += gu[i];
                }
                mean_g /= c as f32;
                mean_gx /= c as f32;
                for i in 0..c {
                    dx[i] = res.map_or(0.0, |res| res[i])
                        + r * (gu[i] * gamma[i] - mean_g - xh[i] * mean_gx);
                }
            }
            (dg, db)
        })
        .collect::<Vec<_>>();
    // per-task partial sums added in task order: the result does not depend on how rayon
    // scheduled the tasks (exact resume, docs/training.md)
    for (dg, db) in &partial {
        d_gamma.iter_mut().zip(dg).for_each(|(a, x)| *a += x);
        d_beta.iter_mut().zip(db).for_each(|(a, x)| *a += x);
    }
}

/// `dst[i, :] = s[i] src[i, :]` for `src, dst [rows, width]` (`s`: `None` = 1).
pub(crate) fn scale_rows(src: &[f32], s: Option<&[f32]>, width: usize, dst: &mut [f32]) {
    dst.par_chunks_mut(ROWS_PER_TASK * width)
        .zip(src.par_chunks(ROWS_PER_TASK * width))
        .enumerate()
        .for_each(|(t, (dst, src))| {
            for (i, (d, v)) in dst.chunks_mut(width).zip(src.chunks(width)).enumerate() {
                let scale = s.map_or(1.0, |s| s[t * ROWS_PER_TASK + i]);
                d.iter_mut().zip(v).for_each(|(d, &v)| *d = v * scale);
            }
        });
}

/// Every row of `dst [rows, width]` set to `bias` (zeros when `None`).
pub(crate) fn broadcast_rows(dst: &mut [f32], bias: Option<&[f32]>, width: usize) {
    dst.par_chunks_mut(ROWS_PER_TASK * width)
        .for_each(|d| match bias {
            Some(b) => d.chunks_mut(width).for_each(|row| row.copy_from_slice(b)),
            None => d.fill(0.0),
        });
}

/// `sums[j] += Σ_i m[i, j]` for `m [rows, width]`.
pub(crate) fn add_col_sums(sums: &mut [f32], m: &[f32], width: usize) {
    let partial: Vec<Vec<f32>> = m
        .par_chunks(ROWS_PER_TASK * width)
        .map(|rows| {
            let mut acc = vec![0.0f32; width];
            for row in rows.chunks(width) {
                acc.iter_mut().zip(row).for_each(|(a, v)| *a += v);
            }
            acc
        })
        .collect();
    // per-task partial sums added in task order (deterministic, independent of scheduling)
    for p in &partial {
        sums.iter_mut().zip(p).for_each(|(s, v)| *s += v);
    }
}

/// `dst [m, n] (+)= op(lhs) rhs` with `op(lhs) [m, k]` and `rhs [k, n]` row-major; `lhs_t`:
/// `lhs` is stored `[k, m]` (transposed), `rhs_t` likewise `rhs` as `[n, k]`. Multi-threaded.
#[allow(clippy::too_many_arguments)]
pub(crate) fn matmul(
    m: usize,
    n: usize,
    k: usize,
    dst: &mut [f32],
    accumulate: bool,
    lhs: &[f32],
    lhs_t: bool,
    rhs: &[f32],
    rhs_t: bool,
) {
    debug_assert!(dst.len() >= m * n && lhs.len() >= m * k && rhs.len() >= k * n);
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        if !accumulate {
            dst[..m * n].fill(0.0);
        }
        return;
    }
    // (column stride, row stride) of each operand
    let (lhs_cs, lhs_rs) = if lhs_t {
        (m as isize, 1)
    } else {
        (1, k as isize)
    };
    let (rhs_cs, rhs_rs) = if rhs_t {
        (k as isize, 1)
    } else {
        (1, n as isize)
    };
    // SAFETY: the strides address `lhs [m, k]`, `rhs [k, n]` and `dst [m, n]` inside the slices
    // (lengths checked above in debug builds; every caller passes exact shapes).
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            1,
            n as isize,
            accumulate,
            lhs.as_ptr(),
            lhs_cs,
            lhs_rs,
            rhs.as_ptr(),
            rhs_cs,
            rhs_rs,
            1.0f32,
            1.0f32,
            false,
            false,
            false,
            gemm::Parallelism::Rayon(0),
        );
    }
}

/// `dst [m, n] = lhs [m, k] · wᵀ` where `w` is stored `[n, k]` row-major (a Burn `Linear`
/// weight `[d_in = n, d_out = k]`).
pub(crate) fn matmul_bt(m: usize, n: usize, k: usize, dst: &mut [f32], lhs: &[f32], w: &[f32]) {
    matmul(m, n, k, dst, false, lhs, false, w, true);
}

/// Host copy of a Burn `Linear` (`W [d_in, d_out]`, `b [d_out]`) for the host backward.
#[derive(Debug, Clone)]
pub(crate) struct HostLinear {
    pub d_in: usize,
    pub d_out: usize,
    pub weight: Vec<f32>,
    pub bias: Option<Vec<f32>>,
}

/// Gradients of a [`HostLinear`]: `d W [d_in, d_out]`, `d b [d_out]`, `d x [rows, d_in]`.
#[derive(Debug, Clone)]
pub(crate) struct LinearGrads {
    pub weight: Vec<f32>,
    pub bias: Vec<f32>,
    pub input: Vec<f32>,
}

impl HostLinear {
    /// The values of `linear`; `None` when they cannot be read back.
    pub fn read(linear: &Linear) -> Option<Self> {
        let [d_in, d_out] = linear.weight.dims();
        let weight = read_values(linear.weight.val())?;
        let bias = match &linear.bias {
            Some(b) => Some(read_values(b.val())?),
            None => None,
        };
        Some(Self {
            d_in,
            d_out,
            weight,
            bias,
        })
    }

    /// `x W + b`: `x [rows, d_in] -> [rows, d_out]`.
    pub fn forward(&self, x: &[f32]) -> Vec<f32> {
        let mut y = vec![0.0; x.len() / self.d_in.max(1) * self.d_out];
        self.forward_into(x, &mut y);
        y
    }

    /// [`Self::forward`] into `y [rows, d_out]`.
    pub fn forward_into(&self, x: &[f32], y: &mut [f32]) {
        let rows = x.len() / self.d_in.max(1);
        broadcast_rows(y, self.bias.as_deref(), self.d_out);
        matmul(
            rows,
            self.d_out,
            self.d_in,
            y,
            true,
            x,
            false,
            &self.weight,
            false,
        );
    }

    /// Zeroed parameter gradients of this layer (`input` left empty), for
    /// [`Self::backward_into`].
    pub fn zero_grads(&self) -> LinearGrads {
        LinearGrads {
            weight: vec![0.0; self.d_in * self.d_out],
            bias: vec![0.0; self.d_out],
            input: Vec::new(),
        }
    }

    /// The backward of [`Self::forward`] at input `x [rows, d_in]` for `g [rows, d_out]`.
    pub fn backward(&self, x: &[f32], g: &[f32]) -> LinearGrads {
        let mut grads = self.zero_grads();
        let mut input = vec![0.0; x.len()];
        self.backward_into(x, g, false, &mut grads, &mut input);
        grads.input = input;
        grads
    }

    /// The backward of [`Self::forward`] at `x [rows, d_in]` for `g [rows, d_out]`, in caller
    /// buffers: [`Self::param_grads_into`], then [`Self::input_grad_into`].
    pub fn backward_into(
        &self,
        x: &[f32],
        g: &[f32],
        accumulate: bool,
        params: &mut LinearGrads,
        d_input: &mut [f32],
    ) {
        self.param_grads_into(x, g, accumulate, params);
        self.input_grad_into(g, d_input);
    }

    /// `d W = xᵀ g`, `d b = Σ g` at `x [rows, d_in]` for `g [rows, d_out]`, into
    /// `params.weight`, `params.bias`: added to them when `accumulate` (e.g. over row
    /// blocks), overwriting them otherwise. `params.input` is not touched.
    pub fn param_grads_into(
        &self,
        x: &[f32],
        g: &[f32],
        accumulate: bool,
        params: &mut LinearGrads,
    ) {
        let rows = x.len() / self.d_in.max(1);
        matmul(
            self.d_in,
            self.d_out,
            rows,
            &mut params.weight,
            accumulate,
            x,
            true,
            g,
            false,
        );
        if !accumulate {
            params.bias.fill(0.0);
        }
        add_col_sums(&mut params.bias, g, self.d_out);
    }

    /// `d x = g Wᵀ [rows, d_in]` for `g [rows, d_out]`, into `d_input`.
    pub fn input_grad_into(&self, g: &[f32], d_input: &mut [f32]) {
        matmul_bt(
            g.len() / self.d_out.max(1),
            self.d_in,
            self.d_out,
            d_input,
            g,
            &self.weight,
        );
    }
}

/// Host copy of a Burn `LayerNorm`'s `γ`, `β`.
#[derive(Debug, Clone)]
pub(crate) struct HostNorm {
    pub gamma: Vec<f32>,
    pub beta: Option<Vec<f32>>,
    pub eps: f32,
}

impl HostNorm {
    /// The values of `norm` (epsilon `eps`, the one it was built with).
    pub fn read(norm: &LayerNorm, eps: f64) -> Option<Self> {
        let gamma = read_values(norm.gamma.val())?;
        let beta = match &norm.beta {
            Some(b) => Some(read_values(b.val())?),
            None => None,
        };
        Some(Self {
            gamma,
            beta,
            eps: eps as f32,
        })
    }

    /// `LN(x)` of `x [rows, C]`: the kept state and the output.
    pub fn forward(&self, x: &[f32]) -> (NormRows, Vec<f32>) {
        NormRows::forward(x, &self.gamma, self.beta.as_deref(), self.eps)
    }

    /// The kept state of `LN(x)` without its output ([`NormRows::of`]).
    pub fn state(&self, x: &[f32]) -> NormRows {
        NormRows::of(x, self.gamma.len(), self.eps)
    }
}
