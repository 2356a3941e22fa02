//! Training loss (`pipeline.md` §11.3), in normalised chunk coordinates:
//!
//! ```text
//! L_conf(b) = (1/|V_b|) Σ_{i∈V_b} ( c_i ||x̂_i - x_gt,i|| - α log c_i )    V_b: dense tokens with valid GT
//! L_id(b)   = (1/|G_b|) Σ_{i∈G_b} ||x̂_i - geo_pts_i||                      G_b: dense tokens with a DLT point
//! L         = (1/B) Σ_b ( L_conf(b) + λ_id L_id(b) )                        α = 0.2, λ_id = 1
//! ```
//!
//! A term over an empty set is 0; DLT-token outputs are not supervised. The per-token weights
//! `1/(B |V_b|)` and `1/(B |G_b|)` are built on the host, so the device computes two weighted sums.
//! [`distance`] is `sqrt(Σ d² + DIST_EPS)`: the epsilon (1e-12, i.e. a shift of at most 1e-6
//! chunk units) keeps the gradient finite for rows whose distance is exactly 0 (e.g. rows
//! excluded by a zero weight).

use burn::tensor::{Device, Int, Tensor, TensorData};

use crate::chunkset::TrainChunk;

/// `α` of `L_conf` (paper).
pub const ALPHA: f64 = 0.2;
/// `λ_id` (paper).
pub const LAMBDA_ID: f64 = 1.0;
/// Added under the square root of the distances (see the module docs).
pub const DIST_EPS: f64 = 1e-12;

/// Host-side targets of one batch, in the token order of the batched forward
/// (chunk 0's `K_0` dense tokens, its DLT tokens, chunk 1's dense tokens, ...).
#[derive(Debug, Clone)]
pub struct HostTargets {
    /// Global token index of every dense token `[D]`.
    pub dense_index: Vec<i64>,
    /// `[D, 3]` GT (0 where invalid).
    pub gt: Vec<f32>,
    /// `[D, 3]` DLT point (0 where none).
    pub geo: Vec<f32>,
    /// `[D]` `1/(B |V_b|)` on valid-GT tokens, else 0.
    pub w_conf: Vec<f32>,
    /// `[D]` `1/(B |G_b|)` on tokens with a DLT point, else 0.
    pub w_id: Vec<f32>,
}

impl HostTargets {
    /// Targets of `chunks` batched in this order (token layout of `network.md` §4.1).
    pub fn new(chunks: &[&TrainChunk]) -> Self {
        let b = chunks.len().max(1) as f32;
        let d: usize = chunks.iter().map(|c| c.len()).sum();
        let mut t = HostTargets {
            dense_index: Vec::with_capacity(d),
            gt: Vec::with_capacity(3 * d),
            geo: Vec::with_capacity(3 * d),
            w_conf: Vec::with_capacity(d),
            w_id: Vec::with_capacity(d),
        };
        let mut start = 0usize;
        for c in chunks {
            let nv = c.gt_msk.iter().filter(|&&m| m).count();
            let ng = c.geo_msk.iter().filter(|&&m| m).count();
            let wv = if nv > 0 { 1.0 / (b * nv as f32) } else { 0.0 };
            let wg = if ng > 0 { 1.0 / (b * ng as f32) } else { 0.0 };
            for i in 0..c.len() {
                t.dense_index.push((start + i) as i64);
                t.gt.extend_from_slice(&c.gt_pts[i]);
                t.geo.extend_from_slice(&c.geo_pts[i]);
                t.w_conf.push(if c.gt_msk[i] { wv } else { 0.0 });
                t.w_id.push(if c.geo_msk[i] { wg } else { 0.0 });
            }
            start += c.num_tokens();
        }
        t
    }

    /// Uploads the targets to `device`.
    pub fn upload(&self, device: &Device) -> Targets {
        let d = self.dense_index.len();
        Targets {
            dense_index: Tensor::from_data(TensorData::new(self.dense_index.clone(), [d]), device),
            gt: Tensor::from_data(TensorData::new(self.gt.clone(), [d, 3]), device),
            geo: Tensor::from_data(TensorData::new(self.geo.clone(), [d, 3]), device),
            w_conf: Tensor::from_data(TensorData::new(self.w_conf.clone(), [d]), device),
            w_id: Tensor::from_data(TensorData::new(self.w_id.clone(), [d]), device),
        }
    }
}

/// Device-side targets (see [`HostTargets`]).
#[derive(Debug, Clone)]
pub struct Targets {
    /// `[D]` global token index of the dense tokens.
    pub dense_index: Tensor<1, Int>,
    /// `[D, 3]`.
    pub gt: Tensor<2>,
    /// `[D, 3]`.
    pub geo: Tensor<2>,
    /// `[D]`.
    pub w_conf: Tensor<1>,
    /// `[D]`.
    pub w_id: Tensor<1>,
}

/// The loss and its two terms (batch means, scalars `[1]`).
#[derive(Debug, Clone)]
pub struct LossParts {
    /// `L`.
    pub total: Tensor<1>,
    /// `(1/B) Σ_b L_conf(b)`.
    pub conf: Tensor<1>,
    /// `(1/B) Σ_b L_id(b)`.
    pub id: Tensor<1>,
}

/// `sqrt(Σ_a (a - b)² + DIST_EPS)` per row: `[D, 3] -> [D]`.
pub fn distance(a: Tensor<2>, b: Tensor<2>) -> Tensor<1> {
    let [d, _] = a.dims();
    (a - b)
        .square()
        .sum_dim(1)
        .add_scalar(DIST_EPS)
        .sqrt()
        .reshape([d])
}

/// The loss from the network outputs over all tokens of the batch (`xyz [N, 3]`,
/// `conf [N]`, normalised chunk coordinates) and the batch targets.
pub fn loss(xyz: Tensor<2>, conf: Tensor<1>, t: &Targets) -> LossParts {
    let [d] = t.dense_index.dims();
    let idx3 = t.dense_index.clone().reshape([d, 1]).expand([d, 3]);
    let x = xyz.gather(0, idx3);
    let c = conf.gather(0, t.dense_index.clone());
    let conf_term = (c.clone() * distance(x.clone(), t.gt.clone()) - c.log().mul_scalar(ALPHA))
        * t.w_conf.clone();
    let id_term = distance(x, t.geo.clone()) * t.w_id.clone();
    let conf_sum = conf_term.sum();
    let id_sum = id_term.sum();
    LossParts {
        total: conf_sum.clone() + id_sum.clone().mul_scalar(LAMBDA_ID),
        conf: conf_sum,
        id: id_sum,
    }
}

/// Host reference of [`loss`] in f64 (no epsilon): `(L, L_conf, L_id)` from per-chunk outputs
/// (`xyz[b][i]`, `conf[b][i]` for the dense tokens of chunk `b`).
pub fn loss_host(
    chunks: &[&TrainChunk],
    xyz: &[Vec<[f64; 3]>],
    conf: &[Vec<f64>],
) -> (f64, f64, f64) {
    let b = chunks.len().max(1) as f64;
    let dist = |a: [f64; 3], g: [f32; 3]| {
        ((a[0] - g[0] as f64).powi(2) + (a[1] - g[1] as f64).powi(2) + (a[2] - g[2] as f64).powi(2))
            .sqrt()
    };
    let (mut lc, mut li) = (0.0, 0.0);
    for (k, c) in chunks.iter().enumerate() {
        let (mut sv, mut nv, mut sg, mut ng) = (0.0, 0usize, 0.0, 0usize);
        for i in 0..c.len() {
            if c.gt_msk[i] {
                sv += conf[k][i] * dist(xyz[k][i], c.gt_pts[i]) - ALPHA * conf[k][i].ln();
                nv += 1;
            }
            if c.geo_msk[i] {
                sg += dist(xyz[k][i], c.geo_pts[i]);
                ng += 1;
            }
        }
        if nv > 0 {
            lc += sv / nv as f64;
        }
        if ng > 0 {
            li += sg / ng as f64;
        }
    }
    ((lc + LAMBDA_ID * li) / b, lc / b, li / b)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::chunkset::tests::toy_chunk;
    use ggpt_core::chunk_input::ChunkInput;

    #[allow(deprecated)]
    fn dev() -> Device {
        Device::ndarray()
    }

    fn scalar(t: Tensor<1>) -> f64 {
        t.into_data().convert::<f64>().try_to_vec::<f64>().unwrap()[0]
    }

    /// Hand-computed: chunk A has 3 pixels, chunk B 1 pixel; B has one DLT token (after its
    /// dense token), A has DLT points at pixels 0 and 2.
    #[test]
    fn hand_computed_chunk() {
        let a = TrainChunk {
            scene: 0,
            center: [0.0; 3],
            radius: 1.0,
            pixels: vec![0, 1, 2],
            input: ChunkInput {
                ff_pts: vec![[0.0; 3]; 3],
                ff_conf: vec![1.0; 3],
                geo_pts: vec![[0.0, 0.0, 1.0], [0.0; 3], [0.0, 0.0, 0.0]],
                geo_msk: vec![true, false, true],
            },
            gt_pts: vec![[3.0, 4.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]],
            gt_msk: vec![true, false, true],
        };
        let b = TrainChunk {
            scene: 0,
            center: [0.0; 3],
            radius: 1.0,
            pixels: vec![5],
            input: ChunkInput {
                ff_pts: vec![[0.0; 3]],
                ff_conf: vec![1.0],
                geo_pts: vec![[0.0, 2.0, 0.0]],
                geo_msk: vec![true],
            },
            gt_pts: vec![[0.0; 3]],
            gt_msk: vec![false],
        };
        // token order: A0 A1 A2 A_dlt0 A_dlt2 B0 B_dlt0  (N = 7)
        let xyz = [
            [0.0f32, 0.0, 0.0],
            [9.0, 9.0, 9.0],
            [1.0, 0.0, 1.0],
            [5.0, 5.0, 5.0],
            [5.0, 5.0, 5.0],
            [0.0, 0.0, 0.0],
            [7.0, 7.0, 7.0],
        ];
        let conf = [2.0f32, 3.0, 1.0, 9.0, 9.0, 4.0, 9.0];
        // A: V = {0, 2}: (2*5 - 0.2 ln 2 + 1*1 - 0.2 ln 1) / 2 = (11 - 0.2 ln 2) / 2
        //    G = {0, 2}: (|(0,0,0)-(0,0,1)| + |(1,0,1)-(0,0,0)|) / 2 = (1 + sqrt 2) / 2
        // B: V = {} -> 0; G = {0}: |(0,0,0)-(0,2,0)| = 2
        let lc = (11.0 - 0.2 * 2f64.ln()) / 2.0 / 2.0;
        let li = ((1.0 + 2f64.sqrt()) / 2.0 + 2.0) / 2.0;
        let t = HostTargets::new(&[&a, &b]);
        assert_eq!(t.dense_index, vec![0, 1, 2, 5]);
        let d = dev();
        let parts = loss(
            Tensor::from_data(
                TensorData::new(xyz.iter().flatten().copied().collect::<Vec<f32>>(), [7, 3]),
                &d,
            ),
            Tensor::from_data(TensorData::new(conf.to_vec(), [7]), &d),
            &t.upload(&d),
        );
        assert!((scalar(parts.conf) - lc).abs() < 1e-5);
        assert!((scalar(parts.id) - li).abs() < 1e-5);
        assert!((scalar(parts.total) - (lc + li)).abs() < 1e-5);
        let host = loss_host(
            &[&a, &b],
            &[
                vec![[0.0, 0.0, 0.0], [9.0; 3], [1.0, 0.0, 1.0]],
                vec![[0.0; 3]],
            ],
            &[vec![2.0, 3.0, 1.0], vec![4.0]],
        );
        assert!(
            (host.0 - (lc + li)).abs() < 1e-12
                && (host.1 - lc).abs() < 1e-12
                && (host.2 - li).abs() < 1e-12
        );
    }

    /// Autodiff gradient of the loss w.r.t. the outputs and the confidence logit against
    /// central finite differences of the f64 host reference.
    #[test]
    fn gradient_matches_finite_differences() {
        let c0 = toy_chunk(0, 9, 1);
        let c1 = toy_chunk(0, 6, 2);
        let chunks = [&c0, &c1];
        let n0 = c0.num_tokens();
        let n = n0 + c1.num_tokens();
        // outputs: dense rows near the GT, DLT rows arbitrary; logits h in [-1, 1]
        let mut xyz = vec![0.0f64; 3 * n];
        let mut h = vec![0.0f64; n];
        for (j, v) in xyz.iter_mut().enumerate() {
            *v = ((j * 37 % 17) as f64 / 17.0 - 0.5) * 0.8;
        }
        for (j, v) in h.iter_mut().enumerate() {
            *v = (j * 11 % 7) as f64 / 3.5 - 1.0;
        }
        let split = |xyz: &[f64], h: &[f64]| {
            let mut xs = Vec::new();
            let mut cs = Vec::new();
            for (start, c) in [(0usize, &c0), (n0, &c1)] {
                xs.push(
                    (0..c.len())
                        .map(|i| {
                            [
                                xyz[3 * (start + i)],
                                xyz[3 * (start + i) + 1],
                                xyz[3 * (start + i) + 2],
                            ]
                        })
                        .collect::<Vec<_>>(),
                );
                cs.push(
                    (0..c.len())
                        .map(|i| 1.0 + h[start + i].exp())
                        .collect::<Vec<_>>(),
                );
            }
            (xs, cs)
        };
        let d = dev().autodiff();
        let tx = Tensor::<2>::from_data(
            TensorData::new(xyz.iter().map(|&v| v as f32).collect::<Vec<f32>>(), [n, 3]),
            &d,
        )
        .require_grad();
        let th = Tensor::<1>::from_data(
            TensorData::new(h.iter().map(|&v| v as f32).collect::<Vec<f32>>(), [n]),
            &d,
        )
        .require_grad();
        let conf = th.clone().exp().add_scalar(1.0);
        let parts = loss(tx.clone(), conf, &HostTargets::new(&chunks).upload(&d));
        let grads = parts.total.backward();
        let gx: Vec<f32> = tx.grad(&grads).unwrap().into_data().try_to_vec().unwrap();
        let gh: Vec<f32> = th.grad(&grads).unwrap().into_data().try_to_vec().unwrap();
        let eps = 1e-6;
        let mut worst = 0.0f64;
        for j in 0..3 * n {
            let (mut p, mut m) = (xyz.clone(), xyz.clone());
            p[j] += eps;
            m[j] -= eps;
            let (xp, cp) = split(&p, &h);
            let (xm, cm) = split(&m, &h);
            let fd =
                (loss_host(&chunks, &xp, &cp).0 - loss_host(&chunks, &xm, &cm).0) / (2.0 * eps);
            worst = worst.max((fd - gx[j] as f64).abs());
        }
        for j in 0..n {
            let (mut p, mut m) = (h.clone(), h.clone());
            p[j] += eps;
            m[j] -= eps;
            let (xp, cp) = split(&xyz, &p);
            let (xm, cm) = split(&xyz, &m);
            let fd =
                (loss_host(&chunks, &xp, &cp).0 - loss_host(&chunks, &xm, &cm).0) / (2.0 * eps);
            worst = worst.max((fd - gh[j] as f64).abs());
        }
        assert!(
            worst < 1e-4,
            "max |autodiff - finite difference| = {worst:e}"
        );
        // DLT-token rows get no gradient
        for j in c0.len()..n0 {
            assert_eq!(gx[3 * j], 0.0);
            assert_eq!(gh[j], 0.0);
        }
    }
}
