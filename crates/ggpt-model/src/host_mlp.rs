//! The block MLP branch on the host for CPU devices (network.md §5.2, `docs/training.md`
//! "Memory-efficient training"): the exact-erf GELU over the rayon pool, and the whole backward
//! of the MLP segment of [`crate::recompute`].
//!
//! ```text
//! x3 = x2 + s ⊙ fc2(GELU(fc1(LN2(x2))))       x2, x3 [N, C], hidden H = ratio C, s [N] drop-path scale
//! xhat = (x2 - mean) rstd,  u = xhat γ + β     rstd = 1 / sqrt(var + eps)  (biased variance)
//! h = u W1 + b1 [N, H],  a = GELU(h),  y = a W2 + b2 [N, C]
//! backward, g = d x3:
//!   g_y = s ⊙ g;   dW2 = aᵀ g_y;  db2 = Σ g_y;  g_a = g_y W2ᵀ
//!   g_h = g_a ⊙ GELU'(h);  dW1 = uᵀ g_h;  db1 = Σ g_h;  g_u = g_h W1ᵀ
//!   dγ = Σ g_u ⊙ xhat;  dβ = Σ g_u;  d x2 = g + rstd (g_u γ - mean(g_u γ) - xhat mean(g_u γ ⊙ xhat))
//! ```
//!
//! Why hand-written: Burn 0.22.1's flex backend runs element-wise ops and autodiff's decomposed
//! LayerNorm and GELU backward on one thread. In a training step the MLP segments (five GELU
//! passes and a dozen LayerNorm passes over `[N, H]` and `[N, C]`) were then the largest
//! single-threaded share, the reason why a second CPU thread gained little. Here every pass is
//! split over the rayon pool and the products are multi-threaded GEMMs. Same function, same
//! gradient: [`crate::recompute`] stays equal to plain autodiff up to summation order.

use rayon::prelude::*;

use crate::host_dense::{
    HostLinear, HostNorm, LinearGrads, ROWS_PER_TASK, layer_norm_backward_rows, layer_norm_rows,
    scale_rows,
};
use crate::kernels::{gelu_derivative, gelu_value};
use crate::ops::ROW_BLOCK_BUDGET_FLOATS;

/// Gradients of one MLP branch (row-major; the parameter shapes of the layers).
#[derive(Debug, Clone)]
pub(crate) struct MlpGrads {
    /// `d x2 [N, C]` (the residual included).
    pub input: Vec<f32>,
    /// `d γ [C]`.
    pub ln_gamma: Vec<f32>,
    /// `d β [C]`.
    pub ln_beta: Vec<f32>,
    /// `d W1 [C, H]`, `d b1 [H]` (`input` empty).
    pub fc1: LinearGrads,
    /// `d W2 [H, C]`, `d b2 [C]` (`input` empty).
    pub fc2: LinearGrads,
}

/// The backward of `x3 = x2 + s ⊙ fc2(GELU(fc1(LN2(x2))))` (module docs): `x2, g [N, C]`
/// (the branch input and the gradient of `x3`), `row_scale [N]` (the drop-path scale `s`,
/// `None` = 1). Processed in row blocks whose `[rows, H]` buffers stay below
/// [`ROW_BLOCK_BUDGET_FLOATS`]. `None` when a length does not match its shape.
pub(crate) fn mlp_backward(
    x2: &[f32],
    g: &[f32],
    row_scale: Option<&[f32]>,
    ln: &HostNorm,
    fc1: &HostLinear,
    fc2: &HostLinear,
) -> Option<MlpGrads> {
    mlp_backward_in_blocks(
        x2,
        g,
        row_scale,
        ln,
        fc1,
        fc2,
        (ROW_BLOCK_BUDGET_FLOATS / fc1.d_out.max(1)).max(1),
    )
}

/// Whether the layers chain as `LN [C] -> fc1 [C, H] -> fc2 [H, C]` with consistent lengths.
fn is_consistent(ln: &HostNorm, fc1: &HostLinear, fc2: &HostLinear) -> bool {
    let (c, h) = (ln.gamma.len(), fc1.d_out);
    let linear_ok = |l: &HostLinear| {
        l.weight.len() == l.d_in * l.d_out && l.bias.as_ref().is_none_or(|b| b.len() == l.d_out)
    };
    ln.beta.as_ref().is_none_or(|b| b.len() == c)
        && fc1.d_in == c
        && fc2.d_in == h
        && fc2.d_out == c
        && linear_ok(fc1)
        && linear_ok(fc2)
}

/// [`mlp_backward`] in blocks of `block_rows` rows.
fn mlp_backward_in_blocks(
    x2: &[f32],
    g: &[f32],
    row_scale: Option<&[f32]>,
    ln: &HostNorm,
    fc1: &HostLinear,
    fc2: &HostLinear,
    block_rows: usize,
) -> Option<MlpGrads> {
    let (c, hid) = (ln.gamma.len(), fc1.d_out);
    if c == 0
        || hid == 0
        || !is_consistent(ln, fc1, fc2)
        || !x2.len().is_multiple_of(c)
        || g.len() != x2.len()
    {
        return None;
    }
    let n = x2.len() / c;
    if row_scale.is_some_and(|s| s.len() != n) {
        return None;
    }
    let mut out = MlpGrads {
        input: vec![0.0; n * c],
        ln_gamma: vec![0.0; c],
        ln_beta: vec![0.0; c],
        fc1: fc1.zero_grads(),
        fc2: fc2.zero_grads(),
    };
    let block = block_rows.clamp(1, n.max(1));
    // buffers reused by every block (fresh pages are expensive: docs/performance.md)
    let mut xhat = vec![0.0f32; block * c];
    let mut rstd = vec![0.0f32; block];
    let mut u = vec![0.0f32; block * c];
    let mut h = vec![0.0f32; block * hid];
    let mut a = vec![0.0f32; block * hid];
    let mut g_y = vec![0.0f32; block * c];
    let mut g_u = vec![0.0f32; block * c];
    for (b, r0) in (0..n).step_by(block).enumerate() {
        let rows = block.min(n - r0);
        let (xs, gs) = (&x2[r0 * c..(r0 + rows) * c], &g[r0 * c..(r0 + rows) * c]);
        let (xhat, rstd, u) = (&mut xhat[..rows * c], &mut rstd[..rows], &mut u[..rows * c]);
        let (h, a) = (&mut h[..rows * hid], &mut a[..rows * hid]);
        let (g_y, g_u) = (&mut g_y[..rows * c], &mut g_u[..rows * c]);
        let accumulate = b > 0;
        // forward: LN2, fc1, GELU
        layer_norm_rows(xs, &ln.gamma, ln.beta.as_deref(), ln.eps, xhat, rstd, u);
        fc1.forward_into(u, h);
        a.par_chunks_mut(ROWS_PER_TASK * hid)
            .zip(h.par_chunks(ROWS_PER_TASK * hid))
            .for_each(|(a, h)| {
                for (a, &h) in a.iter_mut().zip(h) {
                    *a = gelu_value(h);
                }
            });
        // fc2; g_a = g_y W2ᵀ into `a` (no longer needed), then g_h = g_a ⊙ GELU'(h) in place
        scale_rows(gs, row_scale.map(|sc| &sc[r0..r0 + rows]), c, g_y);
        fc2.param_grads_into(a, g_y, accumulate, &mut out.fc2);
        let g_h = a;
        fc2.input_grad_into(g_y, g_h);
        g_h.par_chunks_mut(ROWS_PER_TASK * hid)
            .zip(h.par_chunks(ROWS_PER_TASK * hid))
            .for_each(|(g, h)| {
                for (g, &h) in g.iter_mut().zip(h) {
                    *g *= gelu_derivative(h);
                }
            });
        // fc1, then LN2
        fc1.backward_into(u, g_h, accumulate, &mut out.fc1, g_u);
        layer_norm_backward_rows(
            g_u,
            xhat,
            rstd,
            &ln.gamma,
            Some(gs),
            &mut out.input[r0 * c..(r0 + rows) * c],
            &mut out.ln_gamma,
            &mut out.ln_beta,
        );
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lcg(seed: u64, len: usize, scale: f32) -> Vec<f32> {
        let mut s = seed;
        (0..len)
            .map(|_| {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((s >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * 2.0 * scale
            })
            .collect()
    }

    /// The branch output `x3 = x2 + s ⊙ MLP(LN(x2))` in f64.
    #[allow(clippy::too_many_arguments)]
    fn forward64(
        x: &[f32],
        s: &[f32],
        eps: f32,
        gamma: &[f32],
        beta: &[f32],
        w1: &[f32],
        b1: &[f32],
        w2: &[f32],
        b2: &[f32],
    ) -> Vec<f64> {
        let (c, hid) = (gamma.len(), b1.len());
        let n = x.len() / c;
        let mut out = vec![0.0f64; n * c];
        for r in 0..n {
            let row: Vec<f64> = x[r * c..(r + 1) * c].iter().map(|&v| v as f64).collect();
            let mean = row.iter().sum::<f64>() / c as f64;
            let var = row.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / c as f64;
            let rs = 1.0 / (var + eps as f64).sqrt();
            let u: Vec<f64> = (0..c)
                .map(|i| (row[i] - mean) * rs * gamma[i] as f64 + beta[i] as f64)
                .collect();
            let a: Vec<f64> = (0..hid)
                .map(|j| {
                    let h =
                        b1[j] as f64 + (0..c).map(|i| u[i] * w1[i * hid + j] as f64).sum::<f64>();
                    0.5 * h * (1.0 + libm::erf(h / 2f64.sqrt()))
                })
                .collect();
            for i in 0..c {
                let y = b2[i] as f64 + (0..hid).map(|j| a[j] * w2[j * c + i] as f64).sum::<f64>();
                out[r * c + i] = row[i] + s[r] as f64 * y;
            }
        }
        out
    }

    #[test]
    fn the_backward_matches_finite_differences_and_blocks_agree() {
        let (n, c, hid) = (7, 5, 12);
        let gamma = lcg(1, c, 1.0).iter().map(|v| v + 1.0).collect::<Vec<_>>();
        let beta = lcg(2, c, 0.3);
        let (w1, b1, w2, b2) = (
            lcg(3, c * hid, 0.6),
            lcg(4, hid, 0.2),
            lcg(5, hid * c, 0.6),
            lcg(6, c, 0.2),
        );
        let eps = 1e-5;
        let ln = HostNorm {
            gamma: gamma.clone(),
            beta: Some(beta.clone()),
            eps,
        };
        let fc1 = HostLinear {
            d_in: c,
            d_out: hid,
            weight: w1.clone(),
            bias: Some(b1.clone()),
        };
        let fc2 = HostLinear {
            d_in: hid,
            d_out: c,
            weight: w2.clone(),
            bias: Some(b2.clone()),
        };
        let x = lcg(7, n * c, 1.5);
        let g = lcg(8, n * c, 1.0);
        let s: Vec<f32> = (0..n)
            .map(|r| if r % 3 == 1 { 0.0 } else { 1.25 })
            .collect();
        let d = mlp_backward(&x, &g, Some(&s), &ln, &fc1, &fc2).expect("consistent shapes");
        // objective <x3, g> in f64, central differences in f64 on every input
        let objective = |x: &[f32],
                         gamma: &[f32],
                         beta: &[f32],
                         w1: &[f32],
                         b1: &[f32],
                         w2: &[f32],
                         b2: &[f32]|
         -> f64 {
            forward64(x, &s, eps, gamma, beta, w1, b1, w2, b2)
                .iter()
                .zip(&g)
                .map(|(a, &b)| a * b as f64)
                .sum()
        };
        let step = 1e-3f32;
        let check = |name: &str, analytic: &[f32], base: &[f32], f: &dyn Fn(&[f32]) -> f64| {
            for i in 0..base.len() {
                let (mut p, mut m) = (base.to_vec(), base.to_vec());
                p[i] += step;
                m[i] -= step;
                let fd = (f(&p) - f(&m)) / (2.0 * step as f64);
                assert!(
                    (analytic[i] as f64 - fd).abs() < 2e-3 * (1.0 + fd.abs()),
                    "{name}[{i}]: {} vs {fd}",
                    analytic[i]
                );
            }
        };
        check("x", &d.input, &x, &|v| {
            objective(v, &gamma, &beta, &w1, &b1, &w2, &b2)
        });
        check("gamma", &d.ln_gamma, &gamma, &|v| {
            objective(&x, v, &beta, &w1, &b1, &w2, &b2)
        });
        check("beta", &d.ln_beta, &beta, &|v| {
            objective(&x, &gamma, v, &w1, &b1, &w2, &b2)
        });
        check("w1", &d.fc1.weight, &w1, &|v| {
            objective(&x, &gamma, &beta, v, &b1, &w2, &b2)
        });
        check("b1", &d.fc1.bias, &b1, &|v| {
            objective(&x, &gamma, &beta, &w1, v, &w2, &b2)
        });
        check("w2", &d.fc2.weight, &w2, &|v| {
            objective(&x, &gamma, &beta, &w1, &b1, v, &b2)
        });
        check("b2", &d.fc2.bias, &b2, &|v| {
            objective(&x, &gamma, &beta, &w1, &b1, &w2, v)
        });
        // row blocks (weight gradients accumulated over blocks) give the same result
        let blocked = mlp_backward_in_blocks(&x, &g, Some(&s), &ln, &fc1, &fc2, 2)
            .expect("consistent shapes");
        for (a, b) in [
            (&d.input, &blocked.input),
            (&d.fc1.weight, &blocked.fc1.weight),
            (&d.fc2.bias, &blocked.fc2.bias),
            (&d.ln_gamma, &blocked.ln_gamma),
        ] {
            assert!(
                a.iter()
                    .zip(b.iter())
                    .all(|(x, y)| (x - y).abs() <= 1e-5 * (1.0 + x.abs())),
                "blocked backward differs"
            );
        }
        assert!(
            mlp_backward(&x[1..], &g[1..], None, &ln, &fc1, &fc2).is_none(),
            "a ragged input is refused"
        );
        assert!(
            mlp_backward(&x, &g, Some(&s[1..]), &ln, &fc1, &fc2).is_none(),
            "a short drop-path scale is refused"
        );
    }
}
