//! Analytic ray casting of a [`World`] into ground-truth depth, points and images.
//!
//! One ray per pixel centre: pixel `(x, y)` (pixel-centre convention) of view `v` casts
//! `o = C_v`, `d = R_v^T K_v^-1 (x, y, 1)^T` (world frame, metres), so the ray parameter of the
//! hit is exactly the camera z-depth. All geometry is `f64`.

use nalgebra::{Matrix3, Point3, Vector3};
use rayon::prelude::*;

use ggpt_core::{Cameras, Dims};

use crate::rng::{SynthRng, Tag, normal2, stream, uniform};
use crate::world::World;

/// Primitive id of sky / void pixels.
pub const SKY: u32 = u32::MAX;

/// Relative threshold on the second difference of inverse depth that marks a depth
/// discontinuity (planes have exactly zero second difference of inverse depth).
pub const EDGE_INV_DEPTH_REL: f64 = 0.05;

/// Ray-cast ground truth of all views (GT world frame, metres), pixel order `(n * h + y) * w + x`.
#[derive(Debug, Clone)]
pub struct Render {
    /// Resolution.
    pub dims: Dims,
    /// `[N, h, w]` exact z-depth, 0 on sky.
    pub depth: Vec<f64>,
    /// `[N, h, w]` exact world point, origin on sky.
    pub points: Vec<Point3<f64>>,
    /// `[N, h, w]` index of the primitive hit, [`SKY`] when none.
    pub prim: Vec<u32>,
    /// `[N, h, w]` `|cos|` of the angle between the viewing ray and the surface normal (0 on sky).
    pub cos_incidence: Vec<f32>,
    /// `[N, h, w]` pixel lies within one pixel of a depth discontinuity or of the sky.
    pub near_edge: Vec<bool>,
    /// `[N, h, w, 3]` noiseless shaded colour in `[0, 1]`.
    pub colour: Vec<f32>,
}

impl Render {
    /// True when pixel `p` (flat pixel order) has a surface (GT valid).
    pub fn valid(&self, p: usize) -> bool {
        self.prim.get(p).is_some_and(|&q| q != SKY)
    }
}

/// World-frame ray direction of pixel `(x, y)` of a camera (`R^T K^-1 (x, y, 1)`), unnormalised
/// with unit camera-z component.
pub fn pixel_ray(r_t: &Matrix3<f64>, k: &Matrix3<f64>, x: f64, y: f64) -> Vector3<f64> {
    let dc = Vector3::new(
        (x - k[(0, 2)]) / k[(0, 0)],
        (y - k[(1, 2)]) / k[(1, 1)],
        1.0,
    );
    r_t * dc
}

struct RowOut {
    depth: Vec<f64>,
    points: Vec<Point3<f64>>,
    prim: Vec<u32>,
    cos: Vec<f32>,
    colour: Vec<f32>,
}

/// Ray-casts every pixel of every view. Deterministic (no randomness), parallel over rows.
/// `cams`: GT `cam_from_world` (metres) and K at ff resolution (pixel-centre convention).
pub fn render(world: &World, cams: &Cameras, dims: Dims) -> Render {
    let rows: Vec<RowOut> = (0..dims.n * dims.h)
        .into_par_iter()
        .map(|row| {
            let v = row / dims.h;
            let y = row % dims.h;
            let r_t = cams.rotation(v).transpose();
            let k = cams.intrinsics[v];
            let c = cams.center(v);
            let mut out = RowOut {
                depth: vec![0.0; dims.w],
                points: vec![Point3::origin(); dims.w],
                prim: vec![SKY; dims.w],
                cos: vec![0.0; dims.w],
                colour: vec![0.0; 3 * dims.w],
            };
            for x in 0..dims.w {
                let d = pixel_ray(&r_t, &k, x as f64, y as f64);
                let col = match world.cast(&c, &d) {
                    Some((hit, prim)) => {
                        let p = c + d * hit.t;
                        out.depth[x] = hit.t;
                        out.points[x] = p;
                        out.prim[x] = prim as u32;
                        out.cos[x] = (hit.normal.dot(&d) / d.norm()).abs() as f32;
                        world.shade(&p, &d, &hit.normal, prim)
                    }
                    None => world.sky(&d),
                };
                for a in 0..3 {
                    out.colour[3 * x + a] = col[a] as f32;
                }
            }
            out
        })
        .collect();
    let px = dims.pixels();
    let mut r = Render {
        dims,
        depth: Vec::with_capacity(px),
        points: Vec::with_capacity(px),
        prim: Vec::with_capacity(px),
        cos_incidence: Vec::with_capacity(px),
        near_edge: Vec::new(),
        colour: Vec::with_capacity(3 * px),
    };
    for row in rows {
        r.depth.extend(row.depth);
        r.points.extend(row.points);
        r.prim.extend(row.prim);
        r.cos_incidence.extend(row.cos);
        r.colour.extend(row.colour);
    }
    r.near_edge = near_edges(&r.depth, dims);
    r
}

/// Depth-discontinuity band: a pixel is an edge when the second difference of inverse depth
/// along x or y exceeds [`EDGE_INV_DEPTH_REL`] of its inverse depth, or when sky and surface meet
/// among its 4-neighbours; the edge set is dilated by one pixel (8-neighbourhood).
pub fn near_edges(depth: &[f64], dims: Dims) -> Vec<bool> {
    let (h, w) = (dims.h, dims.w);
    let inv = |d: f64| if d > 0.0 { 1.0 / d } else { 0.0 };
    let mut edge = vec![false; dims.pixels()];
    for v in 0..dims.n {
        for y in 0..h {
            for x in 0..w {
                let p = dims.index(v, y, x);
                let dp = depth[p];
                let mut e = false;
                let nb = [
                    (x > 0, p.wrapping_sub(1)),
                    (x + 1 < w, p + 1),
                    (y > 0, p.wrapping_sub(w)),
                    (y + 1 < h, p + w),
                ];
                for (ok, q) in nb {
                    if ok && ((depth[q] > 0.0) != (dp > 0.0)) {
                        e = true;
                    }
                }
                if !e && dp > 0.0 {
                    let ip = inv(dp);
                    if x > 0 && x + 1 < w && depth[p - 1] > 0.0 && depth[p + 1] > 0.0 {
                        e |= (inv(depth[p - 1]) + inv(depth[p + 1]) - 2.0 * ip).abs()
                            > EDGE_INV_DEPTH_REL * ip;
                    }
                    if y > 0 && y + 1 < h && depth[p - w] > 0.0 && depth[p + w] > 0.0 {
                        e |= (inv(depth[p - w]) + inv(depth[p + w]) - 2.0 * ip).abs()
                            > EDGE_INV_DEPTH_REL * ip;
                    }
                }
                edge[p] = e;
            }
        }
    }
    let mut out = edge.clone();
    for v in 0..dims.n {
        for y in 0..h {
            for x in 0..w {
                if !edge[dims.index(v, y, x)] {
                    continue;
                }
                for yy in y.saturating_sub(1)..(y + 2).min(h) {
                    for xx in x.saturating_sub(1)..(x + 2).min(w) {
                        out[dims.index(v, yy, xx)] = true;
                    }
                }
            }
        }
    }
    out
}

/// Distance (pixels) of every pixel to the nearest pixel of the `near_edge` band of its view,
/// capped at `cap`: a two-pass chamfer transform (steps 1 and sqrt 2, within 8 % of the
/// Euclidean distance), `[N, h, w]`. 0 on the band.
pub fn edge_distance(near_edge: &[bool], dims: Dims, cap: f32) -> Vec<f32> {
    let (h, w) = (dims.h, dims.w);
    let mut d: Vec<f32> = near_edge
        .iter()
        .map(|&e| if e { 0.0 } else { cap })
        .collect();
    let diag = std::f32::consts::SQRT_2;
    d.par_chunks_mut(dims.hw().max(1)).for_each(|view| {
        for y in 0..h {
            for x in 0..w {
                let mut v = view[y * w + x];
                if x > 0 {
                    v = v.min(view[y * w + x - 1] + 1.0);
                }
                if y > 0 {
                    v = v.min(view[(y - 1) * w + x] + 1.0);
                    if x > 0 {
                        v = v.min(view[(y - 1) * w + x - 1] + diag);
                    }
                    if x + 1 < w {
                        v = v.min(view[(y - 1) * w + x + 1] + diag);
                    }
                }
                view[y * w + x] = v;
            }
        }
        for y in (0..h).rev() {
            for x in (0..w).rev() {
                let mut v = view[y * w + x];
                if x + 1 < w {
                    v = v.min(view[y * w + x + 1] + 1.0);
                }
                if y + 1 < h {
                    v = v.min(view[(y + 1) * w + x] + 1.0);
                    if x + 1 < w {
                        v = v.min(view[(y + 1) * w + x + 1] + diag);
                    }
                    if x > 0 {
                        v = v.min(view[(y + 1) * w + x - 1] + diag);
                    }
                }
                view[y * w + x] = v;
            }
        }
    });
    d
}

/// Images as a camera would record them: per-view exposure gain (±4 %), Gaussian pixel noise
/// (sigma 1/255... 2/255) and 8-bit quantisation (values `k / 255`), `[N, h, w, 3]` in `[0, 1]`.
pub fn camera_images(render: &Render, seed: u64) -> Vec<f32> {
    let hw3 = 3 * render.dims.hw();
    let mut out = vec![0f32; render.colour.len()];
    out.par_chunks_mut(hw3.max(1))
        .zip(render.colour.par_chunks(hw3.max(1)))
        .enumerate()
        .for_each(|(v, (dst, src))| {
            let mut rng: SynthRng = stream(seed, Tag::Image, v as u64, 0);
            let gain = uniform(&mut rng, 0.96, 1.04);
            let sigma = uniform(&mut rng, 1.0, 2.0) / 255.0;
            for (pair_d, pair_s) in dst.chunks_mut(2).zip(src.chunks(2)) {
                let (n0, n1) = normal2(&mut rng);
                let noise = [n0, n1];
                for i in 0..pair_d.len() {
                    let val = (pair_s[i] as f64 * gain + sigma * noise[i]).clamp(0.0, 1.0);
                    pair_d[i] = ((val * 255.0).round() / 255.0) as f32;
                }
            }
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn edge_distance_is_zero_on_the_band_and_grows_away_from_it() {
        let dims = Dims { n: 2, h: 5, w: 7 };
        let mut edge = vec![false; dims.pixels()];
        edge[dims.index(0, 2, 3)] = true; // view 0: one edge pixel in the middle; view 1: none
        let d = edge_distance(&edge, dims, 50.0);
        assert_eq!(d[dims.index(0, 2, 3)], 0.0);
        assert_eq!(d[dims.index(0, 2, 4)], 1.0);
        assert_eq!(d[dims.index(0, 2, 0)], 3.0);
        assert!((d[dims.index(0, 3, 4)] - std::f32::consts::SQRT_2).abs() < 1e-6);
        assert!((d[dims.index(0, 0, 0)] - (1.0 + 2.0 * std::f32::consts::SQRT_2)).abs() < 1e-6);
        // views are independent; without an edge everything stays at the cap
        assert!(d[dims.hw()..].iter().all(|v| *v == 50.0));
    }
}
