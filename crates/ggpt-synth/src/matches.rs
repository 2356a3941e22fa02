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
    /// Failure modes of real dense matchers (all off in the easy regime).
    #[serde(default)]
    pub failures: FailureModes,
}

/// Failure modes of a real dense matcher (RoMa, UFM) on visible points: where its certainty
/// collapses and its locations go wrong. [`FailureModes::default`] switches every mode off (the
/// easy regime). "Low texture" is measured on the camera images the matcher sees
/// ([`texture_strength`]), the occlusion band on the GT depth ([`crate::render::edge_distance`]),
/// the repeated patterns from the materials ([`crate::texture::Material::period_m`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct FailureModes {
    /// Local grey-level standard deviation (11 x 11 window, images in `[0, 1]`) at which a
    /// surface counts as fully textured; 0 disables the low-texture mode.
    pub texture_ref: f64,
    /// Score drop on a texture-free surface (linear in the missing texture).
    pub texture_penalty: f64,
    /// Extra location sigma (ff pixels) on a texture-free surface (quadratic in the missing
    /// texture): matches slide along plain surfaces.
    pub texture_noise_px: f64,
    /// Width (ff pixels) of the band along depth discontinuities where certainty drops; 0
    /// disables the mode.
    pub edge_band_px: f64,
    /// Score drop on the discontinuity (linear to 0 at the band's outer edge).
    pub edge_penalty: f64,
    /// Extra location sigma (ff pixels) on the discontinuity (linear to 0 at the band's edge).
    pub edge_noise_px: f64,
    /// Extra score drop times `(1 - cos incidence)^2` (grazing angles).
    pub grazing_penalty: f64,
    /// Probability that a block of matches on a periodic texture jumps by one texture period
    /// (a confident false match; blocks of [`REPEAT_BLOCK_PX`] pixels decide together).
    pub repeat_ratio: f64,
    /// Score drop per unit of `|ln s|`, `s` the scale change of the point between the views.
    pub scale_penalty: f64,
    /// Relative growth of the location sigma per unit of `|ln s|`.
    pub scale_noise: f64,
    /// Lower clamp of visible-match scores (the easy regime: 0.2).
    pub score_floor: f64,
}

impl Default for FailureModes {
    fn default() -> Self {
        FailureModes {
            texture_ref: 0.0,
            texture_penalty: 0.0,
            texture_noise_px: 0.0,
            edge_band_px: 0.0,
            edge_penalty: 0.0,
            edge_noise_px: 0.0,
            grazing_penalty: 0.0,
            repeat_ratio: 0.0,
            scale_penalty: 0.0,
            scale_noise: 0.0,
            score_floor: 0.2,
        }
    }
}

impl FailureModes {
    /// Whether any mode that needs a per-pixel map is on.
    fn needs_maps(&self) -> bool {
        self.texture_ref > 0.0 || self.edge_band_px > 0.0 || self.repeat_ratio > 0.0
    }
}

/// Side (ff pixels) of the source-image blocks whose matches on a periodic texture jump
/// together (a false match of a repeated pattern moves a whole patch, not single pixels).
pub const REPEAT_BLOCK_PX: usize = 24;

/// Half-size of the window of [`texture_strength`] (11 x 11 pixels).
pub const TEXTURE_WINDOW_RADIUS: usize = 5;

/// Cap (ff pixels) of the distance map to depth discontinuities.
pub const EDGE_DISTANCE_CAP: f32 = 64.0;

/// The matchers of a regime: [`benchmark_matchers`] or [`easy_matchers`].
pub fn matchers_for(regime: crate::Regime) -> Vec<MatcherModel> {
    match regime {
        crate::Regime::Benchmark => benchmark_matchers(),
        crate::Regime::Easy => easy_matchers(),
    }
}

/// The default matchers: [`benchmark_matchers`].
pub fn default_matchers() -> Vec<MatcherModel> {
    benchmark_matchers()
}

/// The benchmark regime's matchers [project, calibrated with `cargo bench -p ggpt-sfm --bench
/// regime`, `docs/synthetic.md`]: `roma-like` (precise, 0.2 px, certainty collapses on low
/// texture) and `ufm-like` (denser on weak texture but noisier: 0.45 px + 0.3 px bias, more
/// outliers, larger slide on plain surfaces).
pub fn benchmark_matchers() -> Vec<MatcherModel> {
    vec![
        MatcherModel {
            name: "roma-like".into(),
            noise_px: 0.2,
            bias_px: 0.1,
            outlier_ratio: 0.05,
            score_offset: 0.0,
            failures: FailureModes {
                texture_ref: 0.05,
                texture_penalty: 1.1,
                texture_noise_px: 8.0,
                edge_band_px: 6.0,
                edge_penalty: 0.5,
                edge_noise_px: 3.0,
                grazing_penalty: 0.8,
                repeat_ratio: 0.15,
                scale_penalty: 0.4,
                scale_noise: 1.5,
                score_floor: 0.0,
            },
        },
        MatcherModel {
            name: "ufm-like".into(),
            noise_px: 0.45,
            bias_px: 0.3,
            outlier_ratio: 0.08,
            score_offset: -0.02,
            failures: FailureModes {
                texture_ref: 0.05,
                texture_penalty: 0.7,
                texture_noise_px: 5.0,
                edge_band_px: 8.0,
                edge_penalty: 0.4,
                edge_noise_px: 4.0,
                grazing_penalty: 0.6,
                repeat_ratio: 0.2,
                scale_penalty: 0.3,
                scale_noise: 2.0,
                score_floor: 0.0,
            },
        },
    ]
}

/// The easy regime's matchers: `synthetic-a` (0.15 px, 4 % outliers) and `synthetic-b` (0.3 px +
/// 0.2 px smooth bias, 5 % outliers, slightly lower scores), no failure modes.
pub fn easy_matchers() -> Vec<MatcherModel> {
    vec![
        MatcherModel {
            name: "synthetic-a".into(),
            noise_px: 0.15,
            bias_px: 0.0,
            outlier_ratio: 0.04,
            score_offset: 0.0,
            failures: FailureModes::default(),
        },
        MatcherModel {
            name: "synthetic-b".into(),
            noise_px: 0.3,
            bias_px: 0.2,
            outlier_ratio: 0.05,
            score_offset: -0.03,
            failures: FailureModes::default(),
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
        /// Scale change `(f_t / z_t) / (f_s / z_s)` of the point's image from `s` to `t`.
        scale: f64,
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
    focal_s: f64,
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
            focal_s: cams.intrinsics[s][(0, 0)],
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
        let scale = (kt[(0, 0)] / xc.z) / (self.focal_s / render.depth[p]).max(1e-300);
        GtMatch::Visible {
            loc,
            ray_angle_deg: ray_angle_deg(&x, &self.c_s, &self.c_t),
            scale,
        }
    }
}

fn ray_angle_deg(x: &Point3<f64>, a: &Point3<f64>, b: &Point3<f64>) -> f64 {
    let u = (a - x).normalize();
    let v = (b - x).normalize();
    u.dot(&v).clamp(-1.0, 1.0).acos().to_degrees()
}

/// Per-pixel maps of the source views that the failure modes read (`[N, h, w]` each).
#[derive(Debug, Clone)]
pub struct SceneMaps {
    /// [`texture_strength`] of the camera images.
    pub texture: Vec<f32>,
    /// Distance (ff pixels, capped at [`EDGE_DISTANCE_CAP`]) to the nearest depth discontinuity
    /// ([`crate::render::edge_distance`]).
    pub edge_distance: Vec<f32>,
    /// Period (metres) of the pixel's repeating texture, 0 when aperiodic or sky.
    pub period_m: Vec<f32>,
}

impl SceneMaps {
    /// The maps of a rendered scene: `images` `[N, h, w, 3]` in `[0, 1]` as the matcher sees
    /// them, `period_of(prim)` the texture period (metres) of a primitive.
    pub fn new(render: &Render, images: &[f32], period_of: impl Fn(usize) -> Option<f64>) -> Self {
        let period_m = render
            .prim
            .iter()
            .map(|&q| {
                if q == crate::render::SKY {
                    0.0
                } else {
                    period_of(q as usize).unwrap_or(0.0) as f32
                }
            })
            .collect();
        SceneMaps {
            texture: texture_strength(images, render.dims, TEXTURE_WINDOW_RADIUS),
            edge_distance: crate::render::edge_distance(
                &render.near_edge,
                render.dims,
                EDGE_DISTANCE_CAP,
            ),
            period_m,
        }
    }

    /// Whether a matcher needs these maps.
    pub fn needed_by(model: &MatcherModel) -> bool {
        model.failures.needs_maps()
    }
}

/// Generates the `MatchSet` of one matcher for all ordered pairs. Parallel over pairs, each
/// pair with its own random stream `(seed, matcher_index, t, s)`. `maps` are required when the
/// matcher has failure modes that read them ([`SceneMaps::needed_by`]; without them those modes
/// are off). `progress` is called once per finished pair.
#[allow(clippy::too_many_arguments)]
pub fn generate_matches(
    render: &Render,
    cams: &Cameras,
    model: &MatcherModel,
    matcher_index: usize,
    seed: u64,
    rank_scores: Option<Vec<f32>>,
    maps: Option<&SceneMaps>,
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
                let job = PairJob {
                    render,
                    cams,
                    model,
                    maps,
                    matcher_index,
                    seed,
                    s,
                    t,
                };
                job.fill(m, sc);
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

/// One ordered pair `(s, t)` of one matcher.
struct PairJob<'a> {
    render: &'a Render,
    cams: &'a Cameras,
    model: &'a MatcherModel,
    maps: Option<&'a SceneMaps>,
    matcher_index: usize,
    seed: u64,
    s: usize,
    t: usize,
}

/// Per-block decision of the repeated-pattern mode: `Some(angle)` = the block's matches on a
/// periodic texture jump one period in direction `angle` (radians, target image).
fn repeat_blocks(job: &PairJob<'_>) -> (usize, Vec<Option<f64>>) {
    let dims = job.render.dims;
    let bw = dims.w.div_ceil(REPEAT_BLOCK_PX);
    let bh = dims.h.div_ceil(REPEAT_BLOCK_PX);
    let ratio = job.model.failures.repeat_ratio;
    if ratio <= 0.0 || job.maps.is_none() {
        return (bw, Vec::new());
    }
    // A stream of its own, so that the per-pixel stream is the same with or without this mode.
    let mut rng: SynthRng = stream(
        job.seed ^ splitmix64(0x4E9E_A7ED),
        Tag::Matches,
        job.matcher_index as u64,
        (job.t * dims.n + job.s) as u64,
    );
    let blocks = (0..bw * bh)
        .map(|_| {
            let jump = chance(&mut rng, ratio);
            let angle = uniform(&mut rng, 0.0, std::f64::consts::TAU);
            jump.then_some(angle)
        })
        .collect();
    (bw, blocks)
}

impl PairJob<'_> {
    fn fill(&self, m: &mut [f32], sc: &mut [f32]) {
        let (render, model, s, t) = (self.render, self.model, self.s, self.t);
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
            self.seed,
            Tag::Matches,
            self.matcher_index as u64,
            (t * dims.n + s) as u64,
        );
        // Smooth bias field of this pair: two low-frequency waves.
        let fx = uniform(&mut rng, 0.5, 1.5) * std::f64::consts::TAU / w;
        let fy = uniform(&mut rng, 0.5, 1.5) * std::f64::consts::TAU / h;
        let (px, py) = (uniform(&mut rng, 0.0, 6.3), uniform(&mut rng, 0.0, 6.3));
        let random_loc = |rng: &mut SynthRng| {
            Vector2::new(uniform(rng, -0.5, w - 0.5), uniform(rng, -0.5, h - 0.5))
        };
        let f = &model.failures;
        let (blocks_w, blocks) = repeat_blocks(self);
        let focal_t = self.cams.intrinsics[t][(0, 0)];
        let geom = PairGeometry::new(self.cams, s, t);
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
                GtMatch::Visible {
                    loc,
                    ray_angle_deg,
                    scale,
                } => {
                    let p = s * dims.hw() + k;
                    let cos = render.cos_incidence[p] as f64;
                    let edge = if render.near_edge[p] { 1.0 } else { 0.0 };
                    // Failure modes (all zero in the easy regime).
                    let (mut drop, mut extra_px) = (0.0, 0.0);
                    if let Some(maps) = self.maps {
                        if f.texture_ref > 0.0 {
                            let missing = (1.0 - maps.texture[p] as f64 / f.texture_ref).max(0.0);
                            drop += f.texture_penalty * missing;
                            extra_px += f.texture_noise_px * missing * missing;
                        }
                        if f.edge_band_px > 0.0 {
                            let near =
                                (1.0 - maps.edge_distance[p] as f64 / f.edge_band_px).max(0.0);
                            drop += f.edge_penalty * near;
                            extra_px += f.edge_noise_px * near;
                        }
                    }
                    let log_scale = scale.max(1e-9).ln().abs();
                    drop += f.grazing_penalty * (1.0 - cos).powi(2) + f.scale_penalty * log_scale;
                    let (n0, _) = normal2(&mut rng);
                    let q = 0.93 + model.score_offset
                        - 0.35 * (ray_angle_deg / 60.0).powi(2)
                        - 0.2 * edge
                        - 0.3 * (1.0 - cos).powi(2)
                        - drop
                        + 0.04 * n0;
                    let score = q.clamp(f.score_floor, 0.995);
                    let sigma = model.noise_px
                        * (1.0 + 2.5 * (0.9 - score).max(0.0))
                        * (1.0 + ray_angle_deg / 40.0)
                        * (1.0 + f.scale_noise * log_scale)
                        + extra_px;
                    let bias = Vector2::new((fx * loc.x + px).cos(), (fy * loc.y + py).sin())
                        * model.bias_px;
                    let (a, b) = normal2(&mut rng);
                    let mut out = loc + bias + Vector2::new(a, b) * sigma;
                    // Repeated pattern: the whole block jumps one period (a confident mistake).
                    if let (Some(maps), false) = (self.maps, blocks.is_empty()) {
                        let period = maps.period_m[p] as f64;
                        let (x, y) = (k % dims.w, k / dims.w);
                        let block = (y / REPEAT_BLOCK_PX) * blocks_w + x / REPEAT_BLOCK_PX;
                        if let (true, Some(Some(angle))) = (period > 0.0, blocks.get(block)) {
                            // depth of the point in t = f_t / (scale * f_s / z_s)
                            let z_t = focal_t / (scale * geom.focal_s / render.depth[p]);
                            let jump = period * focal_t / z_t.max(1e-9);
                            out += Vector2::new(angle.cos(), angle.sin()) * jump;
                        }
                    }
                    (out, score)
                }
            };
            m[2 * k] = loc.x as f32;
            m[2 * k + 1] = loc.y as f32;
            sc[k] = score as f32;
        }
    }
}

/// Texture strength seen by a matcher: the local standard deviation of the grey image in a
/// `(2 r + 1)^2` window (clamped at the borders), `[N, h*w]`. `images`: `[N, h, w, 3]` in
/// `[0, 1]`. Plain painted surfaces give about the camera noise (~0.006), textured ones 0.03-0.2.
pub fn texture_strength(images: &[f32], dims: Dims, r: usize) -> Vec<f32> {
    let (h, w) = (dims.h, dims.w);
    let mut out = vec![0f32; dims.pixels()];
    out.par_chunks_mut(dims.hw().max(1))
        .enumerate()
        .for_each(|(v, dst)| {
            // integral images of the grey values and their squares (f64)
            let stride = w + 1;
            let mut s1 = vec![0f64; (h + 1) * stride];
            let mut s2 = vec![0f64; (h + 1) * stride];
            for y in 0..h {
                let (mut r1, mut r2) = (0.0, 0.0);
                for x in 0..w {
                    let i = 3 * dims.index(v, y, x);
                    let g = images.get(i..i + 3).map_or(0.0, |c| {
                        0.299 * c[0] as f64 + 0.587 * c[1] as f64 + 0.114 * c[2] as f64
                    });
                    r1 += g;
                    r2 += g * g;
                    s1[(y + 1) * stride + x + 1] = s1[y * stride + x + 1] + r1;
                    s2[(y + 1) * stride + x + 1] = s2[y * stride + x + 1] + r2;
                }
            }
            for y in 0..h {
                let (y0, y1) = (y.saturating_sub(r), (y + r + 1).min(h));
                for x in 0..w {
                    let (x0, x1) = (x.saturating_sub(r), (x + r + 1).min(w));
                    let box_sum = |s: &[f64]| {
                        s[y1 * stride + x1] - s[y0 * stride + x1] - s[y1 * stride + x0]
                            + s[y0 * stride + x0]
                    };
                    let n = ((y1 - y0) * (x1 - x0)) as f64;
                    let mean = box_sum(&s1) / n;
                    let var = (box_sum(&s2) / n - mean * mean).max(0.0);
                    dst[y * w + x] = var.sqrt() as f32;
                }
            }
        });
    out
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn texture_strength_is_the_local_grey_deviation() {
        let dims = Dims { n: 1, h: 20, w: 30 };
        let mut img = vec![0.5f32; 3 * dims.pixels()];
        // right half: a 1-pixel checker of grey 0.4 / 0.6 (standard deviation 0.1)
        for y in 0..dims.h {
            for x in 15..dims.w {
                let g = if (x + y) % 2 == 0 { 0.4 } else { 0.6 };
                img[3 * (y * dims.w + x)..3 * (y * dims.w + x) + 3].fill(g);
            }
        }
        let t = texture_strength(&img, dims, 2);
        assert!(t[10 * dims.w + 3] < 1e-6, "flat: {}", t[10 * dims.w + 3]);
        let c = t[10 * dims.w + 25];
        assert!((c - 0.1).abs() < 0.01, "checker: {c}");
        // across the boundary the window mixes both halves
        assert!(t[10 * dims.w + 14] > 0.0 && t[10 * dims.w + 14] < c);
    }

    #[test]
    fn easy_matchers_have_no_failure_modes() {
        for m in easy_matchers() {
            assert_eq!(m.failures, FailureModes::default());
            assert!(!SceneMaps::needed_by(&m));
        }
        assert!(benchmark_matchers().iter().all(SceneMaps::needed_by));
    }
}
