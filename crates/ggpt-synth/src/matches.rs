//! Simulated dense matchers.
//!
//! For every ordered pair `(s, t)` and every pixel `k` of view `s`, the ground-truth
//! correspondence is the projection into view `t` of the exact GT point of `(s, k)`, with
//! occlusion decided by a depth test against view `t`'s GT depth. A matcher model then adds
//! location noise, a smooth bias, certainty scores and gross outliers. Output layout is
//! `sfm.md` §2.1: `pred_matches[t, s, k] = (x, y)` in ff pixels (pixel-centre convention) of view
//! `t`, `pred_scores[t, s, k]`; the diagonal is the identity grid with score 1.

use nalgebra::{Matrix3, Point3, Vector2, Vector3};
use rand::Rng;
use rayon::prelude::*;

use ggpt_core::{Cameras, Dims, MatchSet};

use crate::render::Render;
use crate::rng::{SynthRng, Tag, chance, normal2, splitmix64, stream, uniform};

/// Relative depth tolerance of the occlusion test: the point of `(s, k)` is visible in `t` when
/// its depth in `t` is at most `(1 + tol)` times the GT depth of one of the 4 pixel centres
/// around its projection.
pub const OCCLUSION_REL_TOL: f64 = 0.02;

/// Parameters of one simulated matcher.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MatcherModel {
    /// Matcher name stored in the `MatchSet`.
    pub name: String,
    /// Sigma (ff pixels, per axis) of the location noise of confident visible matches.
    pub noise_px: f64,
    /// Amplitude (ff pixels) of a smooth per-pair bias field added to visible matches.
    pub bias_px: f64,
    /// Fraction of non-sky entries replaced by gross outliers (random location, score
    /// uniform in `[0.15, 1)`).
    pub outlier_ratio: f64,
    /// Offset added to the score of visible matches (a less confident matcher is negative).
    pub score_offset: f64,
}

/// The two default matchers: `synthetic-a` (0.15 px, 4 % outliers) and `synthetic-b` (0.3 px +
/// 0.2 px smooth bias, 5 % outliers, slightly lower scores).
pub fn default_matchers() -> Vec<MatcherModel> {
    vec![
        MatcherModel {
            name: "synthetic-a".into(),
            noise_px: 0.15,
            bias_px: 0.0,
            outlier_ratio: 0.04,
            score_offset: 0.0,
        },
        MatcherModel {
            name: "synthetic-b".into(),
            noise_px: 0.3,
            bias_px: 0.2,
            outlier_ratio: 0.05,
            score_offset: -0.03,
        },
    ]
}

/// Ground-truth correspondence class of pixel `k` of view `s` in view `t`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum GtMatch {
    /// `(s, k)` sees no surface.
    Sky,
    /// The point is behind camera `t` (or on its centre plane).
    Behind,
    /// Projects outside view `t`'s image (location unclamped, ff pixels).
    OutOfView(Vector2<f64>),
    /// Projects inside view `t` but is hidden by a nearer surface.
    Occluded(Vector2<f64>),
    /// Visible in `t` at `loc` (ff pixels); `ray_angle_deg` = angle between the two viewing rays.
    Visible {
        /// Location in view `t` (ff pixels).
        loc: Vector2<f64>,
        /// Angle between the two viewing rays (degrees).
        ray_angle_deg: f64,
    },
}

/// Exact ground-truth correspondence of pixel `k` of view `s` in view `t` (views of `render`,
/// GT cameras `cams` in the GT world frame, metres; locations in ff pixels, pixel-centre).
pub fn gt_match(render: &Render, cams: &Cameras, s: usize, t: usize, k: usize) -> GtMatch {
    PairGeometry::new(cams, s, t).classify(render, k)
}

/// Camera quantities of one ordered pair `(s, t)`, precomputed once per pair.
#[derive(Debug, Clone)]
pub struct PairGeometry {
    s: usize,
    t: usize,
    r_t: Matrix3<f64>,
    t_t: Vector3<f64>,
    k_t: Matrix3<f64>,
    c_s: Point3<f64>,
    c_t: Point3<f64>,
}

impl PairGeometry {
    /// Geometry of the pair: source view `s`, target view `t` (GT cameras, world frame).
    pub fn new(cams: &Cameras, s: usize, t: usize) -> Self {
        PairGeometry {
            s,
            t,
            r_t: cams.rotation(t),
            t_t: cams.translation(t),
            k_t: cams.intrinsics[t],
            c_s: cams.center(s),
            c_t: cams.center(t),
        }
    }

    /// Ground-truth correspondence class of pixel `k` of the source view (see [`gt_match`]).
    pub fn classify(&self, render: &Render, k: usize) -> GtMatch {
        let dims = render.dims;
        let p = self.s * dims.hw() + k;
        if !render.valid(p) {
            return GtMatch::Sky;
        }
        let x = render.points[p];
        let xc = self.r_t * x.coords + self.t_t;
        if xc.z <= 1e-9 {
            return GtMatch::Behind;
        }
        let kt = &self.k_t;
        let loc = Vector2::new(
            kt[(0, 0)] * xc.x / xc.z + kt[(0, 2)],
            kt[(1, 1)] * xc.y / xc.z + kt[(1, 2)],
        );
        let (w, h) = (dims.w as f64, dims.h as f64);
        if !(loc.x >= -0.5 && loc.x < w - 0.5 && loc.y >= -0.5 && loc.y < h - 0.5) {
            return GtMatch::OutOfView(loc);
        }
        // Depth test against the 4 pixel centres around the projection (clamped to the image).
        let x0 = loc.x.floor().clamp(0.0, w - 1.0) as usize;
        let y0 = loc.y.floor().clamp(0.0, h - 1.0) as usize;
        let x1 = (x0 + 1).min(dims.w - 1);
        let y1 = (y0 + 1).min(dims.h - 1);
        let base = self.t * dims.hw();
        let visible = [(x0, y0), (x1, y0), (x0, y1), (x1, y1)]
            .iter()
            .any(|&(xx, yy)| {
                let q = base + yy * dims.w + xx;
                render.valid(q) && xc.z <= render.depth[q] * (1.0 + OCCLUSION_REL_TOL)
            });
        if !visible {
            return GtMatch::Occluded(loc);
        }
        GtMatch::Visible {
            loc,
            ray_angle_deg: ray_angle_deg(&x, &self.c_s, &self.c_t),
        }
    }
}

fn ray_angle_deg(x: &Point3<f64>, a: &Point3<f64>, b: &Point3<f64>) -> f64 {
    let u = (a - x).normalize();
    let v = (b - x).normalize();
    u.dot(&v).clamp(-1.0, 1.0).acos().to_degrees()
}

/// Generates the `MatchSet` of one matcher for all ordered pairs. Parallel over pairs, each
/// pair with its own random stream `(seed, matcher_index, t, s)`. `progress` is called once per
/// finished pair.
pub fn generate_matches(
    render: &Render,
    cams: &Cameras,
    model: &MatcherModel,
    matcher_index: usize,
    seed: u64,
    rank_scores: Option<Vec<f32>>,
    progress: &(dyn Fn() + Sync),
) -> MatchSet {
    let dims = render.dims;
    let hw = dims.hw();
    let n = dims.n;
    let mut matches = vec![0f32; 2 * n * n * hw];
    let mut scores = vec![0f32; n * n * hw];
    if hw > 0 {
        matches
            .par_chunks_mut(2 * hw)
            .zip(scores.par_chunks_mut(hw))
            .enumerate()
            .for_each(|(pair, (m, sc))| {
                let t = pair / n;
                let s = pair % n;
                fill_pair(render, cams, model, matcher_index, seed, s, t, m, sc);
                progress();
            });
    }
    MatchSet {
        matcher: model.name.clone(),
        pred_matches: matches,
        pred_scores: scores,
        pred_cycle_error: None,
        rank_scores,
    }
}

#[allow(clippy::too_many_arguments)]
fn fill_pair(
    render: &Render,
    cams: &Cameras,
    model: &MatcherModel,
    matcher_index: usize,
    seed: u64,
    s: usize,
    t: usize,
    m: &mut [f32],
    sc: &mut [f32],
) {
    let dims = render.dims;
    let (w, h) = (dims.w as f64, dims.h as f64);
    if s == t {
        for k in 0..dims.hw() {
            m[2 * k] = (k % dims.w) as f32;
            m[2 * k + 1] = (k / dims.w) as f32;
            sc[k] = 1.0;
        }
        return;
    }
    let mut rng: SynthRng = stream(
        seed,
        Tag::Matches,
        matcher_index as u64,
        (t * dims.n + s) as u64,
    );
    // Smooth bias field of this pair: two low-frequency waves.
    let fx = uniform(&mut rng, 0.5, 1.5) * std::f64::consts::TAU / w;
    let fy = uniform(&mut rng, 0.5, 1.5) * std::f64::consts::TAU / h;
    let (px, py) = (uniform(&mut rng, 0.0, 6.3), uniform(&mut rng, 0.0, 6.3));
    let random_loc =
        |rng: &mut SynthRng| Vector2::new(uniform(rng, -0.5, w - 0.5), uniform(rng, -0.5, h - 0.5));
    let geom = PairGeometry::new(cams, s, t);
    for k in 0..dims.hw() {
        let gt = geom.classify(render, k);
        let (loc, score) = match gt {
            GtMatch::Sky => (random_loc(&mut rng), 0.0),
            _ if chance(&mut rng, model.outlier_ratio) => {
                (random_loc(&mut rng), uniform(&mut rng, 0.15, 1.0))
            }
            GtMatch::Behind => (random_loc(&mut rng), uniform(&mut rng, 0.0, 0.03)),
            GtMatch::OutOfView(l) => {
                let (a, b) = normal2(&mut rng);
                let c = Vector2::new(l.x.clamp(-0.5, w - 0.5), l.y.clamp(-0.5, h - 0.5));
                (c + Vector2::new(a, b) * 3.0, uniform(&mut rng, 0.0, 0.06))
            }
            GtMatch::Occluded(l) => {
                let (a, b) = normal2(&mut rng);
                (l + Vector2::new(a, b) * 3.0, uniform(&mut rng, 0.0, 0.09))
            }
            GtMatch::Visible { loc, ray_angle_deg } => {
                let p = s * dims.hw() + k;
                let cos = render.cos_incidence[p] as f64;
                let edge = if render.near_edge[p] { 1.0 } else { 0.0 };
                let (n0, _) = normal2(&mut rng);
                let q = 0.93 + model.score_offset
                    - 0.35 * (ray_angle_deg / 60.0).powi(2)
                    - 0.2 * edge
                    - 0.3 * (1.0 - cos).powi(2)
                    + 0.04 * n0;
                let score = q.clamp(0.2, 0.995);
                let sigma = model.noise_px
                    * (1.0 + 2.5 * (0.9 - score).max(0.0))
                    * (1.0 + ray_angle_deg / 40.0);
                let bias =
                    Vector2::new((fx * loc.x + px).cos(), (fy * loc.y + py).sin()) * model.bias_px;
                let (a, b) = normal2(&mut rng);
                (loc + bias + Vector2::new(a, b) * sigma, score)
            }
        };
        m[2 * k] = loc.x as f32;
        m[2 * k + 1] = loc.y as f32;
        sc[k] = score as f32;
    }
}

/// SuperPoint-like ranking score per pixel `[N, h*w]`: smoothed squared gradient magnitude of
/// the grey image plus a tiny deterministic jitter (strictly positive, ties practically
/// impossible). `images`: `[N, h, w, 3]` in `[0, 1]`.
pub fn rank_scores(images: &[f32], dims: Dims, seed: u64) -> Vec<f32> {
    let (h, w) = (dims.h, dims.w);
    let grey: Vec<f32> = images
        .chunks_exact(3)
        .map(|c| 0.299 * c[0] + 0.587 * c[1] + 0.114 * c[2])
        .collect();
    let mut g2 = vec![0f32; dims.pixels()];
    for v in 0..dims.n {
        for y in 0..h {
            for x in 0..w {
                let at =
                    |xx: usize, yy: usize| grey.get(dims.index(v, yy, xx)).copied().unwrap_or(0.0);
                let gx = at((x + 1).min(w - 1), y) - at(x.saturating_sub(1), y);
                let gy = at(x, (y + 1).min(h - 1)) - at(x, y.saturating_sub(1));
                g2[dims.index(v, y, x)] = gx * gx + gy * gy;
            }
        }
    }
    let mut out = vec![0f32; dims.pixels()];
    let mut rng: SynthRng = stream(seed ^ splitmix64(0x5150), Tag::Image, u64::MAX, 0);
    for v in 0..dims.n {
        for y in 0..h {
            for x in 0..w {
                let mut acc = 0.0;
                for yy in y.saturating_sub(1)..(y + 2).min(h) {
                    for xx in x.saturating_sub(1)..(x + 2).min(w) {
                        acc += g2[dims.index(v, yy, xx)];
                    }
                }
                out[dims.index(v, y, x)] = acc / 9.0 + 1e-4 + rng.random::<f32>() * 1e-5;
            }
        }
    }
    out
}
