//! Simulated feed-forward prediction (`X_d`, `c_d`, cameras) in a VGGT-like feed-forward frame.
//!
//! Frames: the GT world (metres) is mapped to the **feed-forward frame** by the similarity
//! `S0(X) = s0 (R0 X + t0)` where `[R0 | t0]` is the first GT camera's `cam_from_world` (so the
//! first camera becomes the identity) and `s0` makes the mean distance of the valid GT points
//! to the first camera centre equal to 1 (VGGT's normalisation). The prediction is GT mapped by
//! `S0` plus the structured error model documented on [`FfErrorModel`].

use nalgebra::{Matrix3, Matrix3x4, Point3, Rotation3, Vector3};
use rayon::prelude::*;

use ggpt_core::{Cameras, FeedForward};

use crate::render::{Render, pixel_ray};
use crate::rng::{SynthRng, Tag, chance, normal, small_rotation, stream, uniform};

/// Parameters of the feed-forward error model. Relative quantities are fractions (0.01 = 1 %).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FfErrorModel {
    /// Sigma (deg) of the per-view rotation of the view's points about their centroid.
    pub view_rot_deg: f64,
    /// Sigma of the per-view relative scale error of the view's points.
    pub view_scale: f64,
    /// Sigma (ff units, per axis) of the per-view shift of the view's points.
    pub view_shift: f64,
    /// Sigma of the smooth, low-frequency relative depth warp of each view.
    pub warp_amp: f64,
    /// Sigma of the per-pixel relative depth noise along the ray (grows 2.5x at grazing angles).
    pub depth_noise: f64,
    /// Fraction of valid pixels with a gross relative depth error.
    pub gross_ratio: f64,
    /// Range of the gross relative depth error magnitude (random sign).
    pub gross_range: (f64, f64),
    /// Probability that a pixel in the depth-edge band becomes a "flying pixel" (depth blended
    /// between the two sides of the discontinuity).
    pub edge_ratio: f64,
    /// Distance range (metres, before `S0`) of the far points predicted on sky pixels.
    pub sky_distance: (f64, f64),
    /// Sigma (deg) of the camera rotation error (views > 0; view 0 stays the identity).
    pub cam_rot_deg: f64,
    /// Sigma (ff units, per axis) of the camera translation error (views > 0).
    pub cam_trans: f64,
    /// Range of the magnitude of the shared focal-length bias (random sign).
    pub focal_bias: (f64, f64),
    /// Sigma of the per-view, per-axis relative focal jitter.
    pub focal_jitter: f64,
    /// Sigma of the per-view relative depth error per unit of `ln(depth / median depth)`:
    /// errors that grow (or shrink) with depth, as a feed-forward model's depth scale drifts
    /// from near to far. 0 in the easy regime.
    #[serde(default)]
    pub depth_slope: f64,
}

impl Default for FfErrorModel {
    /// [`FfErrorModel::benchmark`].
    fn default() -> Self {
        Self::benchmark()
    }
}

impl FfErrorModel {
    /// The model of a regime.
    pub fn for_regime(regime: crate::Regime) -> Self {
        match regime {
            crate::Regime::Benchmark => Self::benchmark(),
            crate::Regime::Easy => Self::easy(),
        }
    }

    /// The benchmark regime [project, calibrated with `cargo bench -p ggpt-sfm --bench regime`
    /// against the paper's VGGT AUC@5/10 of 19/32 (ScanNet++) and 23/36 (ETH3D),
    /// `docs/synthetic.md`]: mostly low-frequency, structured error (per-view similarity drift,
    /// smooth depth warps, depth-dependent scale drift, flying pixels at discontinuities) with
    /// small i.i.d. noise and few gross errors.
    pub fn benchmark() -> Self {
        FfErrorModel {
            view_rot_deg: 0.5,
            view_scale: 0.012,
            view_shift: 0.005,
            warp_amp: 0.012,
            depth_noise: 0.0015,
            gross_ratio: 0.003,
            gross_range: (0.05, 0.15),
            edge_ratio: 0.6,
            sky_distance: (25.0, 35.0),
            cam_rot_deg: 0.7,
            cam_trans: 0.01,
            focal_bias: (0.02, 0.06),
            focal_jitter: 0.01,
            depth_slope: 0.02,
        }
    }

    /// The easy regime (the first generator's model): i.i.d.-dominated error.
    pub fn easy() -> Self {
        FfErrorModel {
            view_rot_deg: 0.5,
            view_scale: 0.01,
            view_shift: 0.004,
            warp_amp: 0.008,
            depth_noise: 0.004,
            gross_ratio: 0.02,
            gross_range: (0.06, 0.15),
            edge_ratio: 0.5,
            sky_distance: (25.0, 35.0),
            cam_rot_deg: 0.7,
            cam_trans: 0.01,
            focal_bias: (0.02, 0.06),
            focal_jitter: 0.01,
            depth_slope: 0.0,
        }
    }

    /// The model with every geometric error magnitude (view similarity, warp, noise, gross
    /// range, camera errors) multiplied by `f`; ratios, sky distances and the focal model are kept.
    pub fn scaled(&self, f: f64) -> Self {
        FfErrorModel {
            view_rot_deg: self.view_rot_deg * f,
            view_scale: self.view_scale * f,
            view_shift: self.view_shift * f,
            warp_amp: self.warp_amp * f,
            depth_noise: self.depth_noise * f,
            gross_range: (self.gross_range.0 * f, self.gross_range.1 * f),
            cam_rot_deg: self.cam_rot_deg * f,
            cam_trans: self.cam_trans * f,
            depth_slope: self.depth_slope * f,
            ..self.clone()
        }
    }
}

/// Result of the simulation.
#[derive(Debug, Clone)]
pub struct FfSimulation {
    /// The prediction (feed-forward frame).
    pub ff: FeedForward,
    /// `S0` as a 3x4 matrix `[s0 R0 | s0 t0]` (GT world -> feed-forward frame).
    pub ff_from_world: Matrix3x4<f64>,
    /// GT cameras expressed in the feed-forward frame (unperturbed; translation scaled by `s0`).
    pub gt_cameras_ff: Cameras,
    /// `[N, h, w]` relative depth error `|d_pred / d_gt - 1|` of each valid pixel (0 on sky),
    /// before the per-view similarity.
    pub rel_depth_error: Vec<f32>,
}

/// Applies `S0 = [s0 R0 | s0 t0]` to a world point.
pub fn apply_3x4(m: &Matrix3x4<f64>, p: &Point3<f64>) -> Point3<f64> {
    Point3::from(m.fixed_view::<3, 3>(0, 0) * p.coords + m.column(3))
}

/// Logit of the confidence (`c = 1 + exp(logit)`) on sky pixels.
const SKY_CONF_LOGIT: f64 = -3.5;

/// Simulates the feed-forward prediction from the GT render. `gt_cams`: GT cameras (world,
/// metres). Deterministic given `seed`; parallel over views.
pub fn simulate_ff(
    render: &Render,
    gt_cams: &Cameras,
    model: &FfErrorModel,
    seed: u64,
) -> FfSimulation {
    let dims = render.dims;
    let (h, w) = (dims.h, dims.w);
    let hw = dims.hw();
    // S0: first camera -> identity, mean distance of valid GT points to it = 1.
    let r0 = gt_cams.rotation(0);
    let t0 = gt_cams.translation(0);
    let (sum, count) = render
        .points
        .iter()
        .zip(&render.prim)
        .filter(|(_, q)| **q != crate::render::SKY)
        .fold((0.0, 0usize), |(s, c), (p, _)| {
            (s + (r0 * p.coords + t0).norm(), c + 1)
        });
    let s0 = if count > 0 && sum > 0.0 {
        count as f64 / sum
    } else {
        1.0
    };
    let mut ff_from_world = Matrix3x4::zeros();
    ff_from_world
        .fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&(r0 * s0));
    ff_from_world.set_column(3, &(t0 * s0));

    // GT cameras in the ff frame: cam_i(world_from_ff(Y)) scaled by s0.
    let mut gt_ff = Cameras {
        cam_from_world: Vec::with_capacity(dims.n),
        intrinsics: gt_cams.intrinsics.clone(),
    };
    for i in 0..dims.n {
        let ri = gt_cams.rotation(i);
        let ti = gt_cams.translation(i);
        let r = ri * r0.transpose();
        let t = (ti - r * t0) * s0;
        gt_ff.cam_from_world.push(compose(&r, &t));
    }
    if let Some(m) = gt_ff.cam_from_world.first_mut() {
        *m = compose(&Matrix3::identity(), &Vector3::zeros());
    }

    let per_view: Vec<(Vec<f32>, Vec<f32>, Vec<f32>)> = (0..dims.n)
        .into_par_iter()
        .map(|v| {
            let mut rng: SynthRng = stream(seed, Tag::FfPoints, v as u64, 0);
            let rot = small_rotation(&mut rng, model.view_rot_deg.to_radians());
            let scale = 1.0 + model.view_scale * normal(&mut rng);
            let shift = Vector3::new(normal(&mut rng), normal(&mut rng), normal(&mut rng))
                * model.view_shift;
            // Severity of this view's rigid error in sigmas (the confidence is lower on worse views).
            let severity = (rot.angle() / model.view_rot_deg.to_radians().max(1e-12)).min(3.0)
                + ((scale - 1.0).abs() / model.view_scale.max(1e-12)).min(3.0);
            let warp = Warp::random(&mut rng, model.warp_amp);
            let base = v * hw;
            // Depth-dependent scale drift (no draw when off: the easy regime stays identical).
            let slope = if model.depth_slope > 0.0 {
                model.depth_slope * normal(&mut rng)
            } else {
                0.0
            };
            // (only the drift needs it: no per-view sort in the easy regime)
            let median_depth = if slope != 0.0 {
                median_valid_depth(render, base, hw)
            } else {
                1.0
            };
            let (mut cen, mut nc) = (Vector3::zeros(), 0usize);
            for p in base..base + hw {
                if render.valid(p) {
                    cen += apply_3x4(&ff_from_world, &render.points[p]).coords;
                    nc += 1;
                }
            }
            let centroid = if nc > 0 {
                cen / nc as f64
            } else {
                Vector3::zeros()
            };
            let r_t = gt_cams.rotation(v).transpose();
            let k = gt_cams.intrinsics[v];
            let c = gt_cams.center(v);
            let mut pts = vec![0f32; 3 * hw];
            let mut conf = vec![0f32; hw];
            let mut rel = vec![0f32; hw];
            for y in 0..h {
                for x in 0..w {
                    let i = y * w + x;
                    let p = base + i;
                    let d = pixel_ray(&r_t, &k, x as f64, y as f64);
                    let (world, logit) = if render.valid(p) {
                        let depth = render.depth[p];
                        let cos = render.cos_incidence[p] as f64;
                        let u = 2.0 * x as f64 / (w.max(2) - 1) as f64 - 1.0;
                        let vv = 2.0 * y as f64 / (h.max(2) - 1) as f64 - 1.0;
                        let mut pred =
                            depth * (1.0 + warp.eval(u, vv) + slope * (depth / median_depth).ln());
                        pred *=
                            1.0 + model.depth_noise * (1.0 + 1.5 * (1.0 - cos)) * normal(&mut rng);
                        let mut penalty = 0.0;
                        if render.near_edge[p] && chance(&mut rng, model.edge_ratio) {
                            let other = far_neighbour(render, v, x, y)
                                .unwrap_or(depth * uniform(&mut rng, 1.2, 2.0));
                            pred += uniform(&mut rng, 0.15, 0.85) * (other - depth);
                            penalty += 0.8;
                        } else if chance(&mut rng, model.gross_ratio) {
                            let sign = if chance(&mut rng, 0.5) { 1.0 } else { -1.0 };
                            pred *= 1.0
                                + sign
                                    * uniform(&mut rng, model.gross_range.0, model.gross_range.1);
                        }
                        let e = (pred / depth - 1.0).abs();
                        rel[i] = e as f32;
                        let sigma_ref = model.depth_noise.hypot(model.warp_amp).max(1e-9);
                        let logit = 3.2
                            - 0.7 * (e / sigma_ref).min(10.0)
                            - 0.8 * (1.0 - cos)
                            - penalty
                            - 0.25 * severity
                            + 0.3 * normal(&mut rng);
                        (c + d * pred.max(1e-6), logit.clamp(-3.0, 4.5))
                    } else {
                        let dist = uniform(&mut rng, model.sky_distance.0, model.sky_distance.1);
                        (
                            c + d.normalize() * dist,
                            SKY_CONF_LOGIT + 0.3 * normal(&mut rng),
                        )
                    };
                    let yff = apply_3x4(&ff_from_world, &world).coords;
                    let out = centroid + rot * ((yff - centroid) * scale) + shift;
                    for a in 0..3 {
                        pts[3 * i + a] = out[a] as f32;
                    }
                    conf[i] = (1.0 + logit.exp()) as f32;
                }
            }
            (pts, conf, rel)
        })
        .collect();
    let mut points = Vec::with_capacity(3 * dims.pixels());
    let mut conf = Vec::with_capacity(dims.pixels());
    let mut rel = Vec::with_capacity(dims.pixels());
    for (p, c, r) in per_view {
        points.extend(p);
        conf.extend(c);
        rel.extend(r);
    }
    let cameras = perturb_cameras(&gt_ff, model, seed);
    FfSimulation {
        ff: FeedForward {
            points,
            conf,
            cameras,
        },
        ff_from_world,
        gt_cameras_ff: gt_ff,
        rel_depth_error: rel,
    }
}

/// Median GT depth of the valid pixels `base..base + hw` (1 when there is none).
fn median_valid_depth(render: &Render, base: usize, hw: usize) -> f64 {
    let mut d: Vec<f64> = (base..base + hw)
        .filter(|&p| render.valid(p))
        .map(|p| render.depth[p])
        .collect();
    if d.is_empty() {
        return 1.0;
    }
    let mid = d.len() / 2;
    d.select_nth_unstable_by(mid, f64::total_cmp);
    d[mid].max(1e-9)
}

/// Depth of the 8-neighbour whose depth differs most from pixel `(x, y)` of view `v`; `None`
/// when that neighbour is sky (or there is none).
fn far_neighbour(render: &Render, v: usize, x: usize, y: usize) -> Option<f64> {
    let dims = render.dims;
    let p = dims.index(v, y, x);
    let d = render.depth[p];
    let mut best: Option<(f64, f64)> = None;
    let mut sky = false;
    for yy in y.saturating_sub(1)..(y + 2).min(dims.h) {
        for xx in x.saturating_sub(1)..(x + 2).min(dims.w) {
            let q = dims.index(v, yy, xx);
            if !render.valid(q) {
                sky = true;
                continue;
            }
            let diff = (render.depth[q] - d).abs();
            if best.is_none_or(|(b, _)| diff > b) {
                best = Some((diff, render.depth[q]));
            }
        }
    }
    match best {
        Some((diff, dq)) if diff > 0.02 * d => Some(dq),
        _ if sky => None,
        _ => Some(d),
    }
}

/// Smooth per-view relative depth warp over normalised image coordinates `u, v in [-1, 1]`.
struct Warp {
    poly: [f64; 5],
    waves: [(f64, f64, f64, f64); 2], // (amplitude, frequency x, frequency y, phase)
}

impl Warp {
    fn random(rng: &mut SynthRng, amp: f64) -> Self {
        let mut poly = [0.0; 5];
        for c in &mut poly {
            *c = 0.5 * amp * normal(rng);
        }
        let mut wave = || {
            let dir = uniform(rng, 0.0, std::f64::consts::TAU);
            let f = uniform(rng, 0.4, 1.2) * std::f64::consts::PI;
            (
                0.5 * amp * normal(rng),
                f * dir.cos(),
                f * dir.sin(),
                uniform(rng, 0.0, std::f64::consts::TAU),
            )
        };
        let waves = [wave(), wave()];
        Warp { poly, waves }
    }

    fn eval(&self, u: f64, v: f64) -> f64 {
        let p = &self.poly;
        let mut f = p[0] * u
            + p[1] * v
            + p[2] * u * v
            + p[3] * (u * u - 1.0 / 3.0)
            + p[4] * (v * v - 1.0 / 3.0);
        for (a, fx, fy, ph) in &self.waves {
            f += a * (fx * u + fy * v + ph).cos();
        }
        f
    }
}

fn compose(r: &Matrix3<f64>, t: &Vector3<f64>) -> Matrix3x4<f64> {
    let mut m = Matrix3x4::zeros();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(r);
    m.set_column(3, t);
    m
}

/// Feed-forward cameras: GT cameras in the ff frame with rotation / translation noise (view 0
/// stays exactly the identity, as VGGT's reference view) and focal lengths off by a shared bias
/// plus per-view jitter; the principal point is the GT one here ([`crate::generate`] then sets the
/// configured [`crate::PrincipalPoint`] convention).
fn perturb_cameras(gt_ff: &Cameras, model: &FfErrorModel, seed: u64) -> Cameras {
    let mut rng: SynthRng = stream(seed, Tag::FfCameras, 0, 0);
    let sign = if chance(&mut rng, 0.5) { 1.0 } else { -1.0 };
    let bias = sign * uniform(&mut rng, model.focal_bias.0, model.focal_bias.1);
    let mut out = Cameras {
        cam_from_world: Vec::with_capacity(gt_ff.len()),
        intrinsics: Vec::with_capacity(gt_ff.len()),
    };
    for i in 0..gt_ff.len() {
        let dr = small_rotation(&mut rng, model.cam_rot_deg.to_radians());
        let dt =
            Vector3::new(normal(&mut rng), normal(&mut rng), normal(&mut rng)) * model.cam_trans;
        if i == 0 {
            out.cam_from_world
                .push(compose(&Matrix3::identity(), &Vector3::zeros()));
        } else {
            let r: Rotation3<f64> = dr * Rotation3::from_matrix_unchecked(gt_ff.rotation(i));
            out.cam_from_world
                .push(compose(r.matrix(), &(gt_ff.translation(i) + dt)));
        }
        let mut k = gt_ff.intrinsics[i];
        k[(0, 0)] *= (1.0 + bias) * (1.0 + model.focal_jitter * normal(&mut rng));
        k[(1, 1)] *= (1.0 + bias) * (1.0 + model.focal_jitter * normal(&mut rng));
        out.intrinsics.push(k);
    }
    out
}
