//! A small exact synthetic scene for pipeline tests: `n` cameras on a line looking at a slanted
//! plane, dense matches by ray casting (score 0.9 inside the other image, 0 outside).
#![allow(dead_code)]

use ggpt_core::{Cameras, Dims, FeedForward, MatchSet};
use nalgebra::{Matrix3, Matrix3x4, Rotation3, Vector3};

pub struct Synth {
    pub dims: Dims,
    /// `[N hw]` GT world point of every pixel.
    pub gt_points: Vec<[f64; 3]>,
    pub gt: Cameras,
    pub ff: FeedForward,
    pub images: Vec<f32>,
    pub matches: MatchSet,
}

fn plane_hit(c: &Vector3<f64>, d: &Vector3<f64>) -> Option<Vector3<f64>> {
    // plane z = 5 + 0.2 x and a sphere of radius 0.9 at (0.6, 0.1, 4.0) (world frame): nearest hit
    let denom = d.z - 0.2 * d.x;
    let mut best = if denom.abs() < 1e-9 {
        f64::INFINITY
    } else {
        (5.0 + 0.2 * c.x - c.z) / denom
    };
    if best <= 0.0 {
        best = f64::INFINITY;
    }
    let oc = c - Vector3::new(0.6, 0.1, 4.0);
    let (a, b, cc) = (d.dot(d), 2.0 * oc.dot(d), oc.dot(&oc) - 0.81);
    let disc = b * b - 4.0 * a * cc;
    if disc >= 0.0 {
        let s = (-b - disc.sqrt()) / (2.0 * a);
        if s > 0.0 && s < best {
            best = s;
        }
    }
    if best.is_finite() {
        Some(c + d * best)
    } else {
        None
    }
}

pub fn synth(n: usize, h: usize, w: usize) -> Synth {
    let dims = Dims { n, h, w };
    let f = 0.9 * w as f64;
    let k = Matrix3::new(
        f,
        0.0,
        (w as f64 - 1.0) / 2.0,
        0.0,
        f,
        (h as f64 - 1.0) / 2.0,
        0.0,
        0.0,
        1.0,
    );
    let mut ext = Vec::new();
    for v in 0..n {
        let cx = 0.6 * v as f64;
        let r = Rotation3::from_euler_angles(0.01 * v as f64, -0.08 * v as f64, 0.0).into_inner();
        let c = Vector3::new(cx, 0.05 * v as f64, 0.0);
        let t = -r * c;
        let mut e = Matrix3x4::zeros();
        e.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
        e.set_column(3, &t);
        ext.push(e);
    }
    let gt = Cameras {
        cam_from_world: ext.clone(),
        intrinsics: vec![k; n],
    };
    let hw = h * w;
    // world point of every pixel
    let mut pts = vec![[0f64; 3]; n * hw];
    for v in 0..n {
        let r = gt.rotation(v);
        let c = gt.center(v).coords;
        for kk in 0..hw {
            let (x, y) = ((kk % w) as f64, (kk / w) as f64);
            let dc = Vector3::new((x - k[(0, 2)]) / f, (y - k[(1, 2)]) / f, 1.0);
            let dw = r.transpose() * dc;
            let p = plane_hit(&c, &dw).unwrap_or(Vector3::new(0.0, 0.0, 100.0));
            pts[v * hw + kk] = [p.x, p.y, p.z];
        }
    }
    let mut pm = vec![0f32; 2 * n * n * hw];
    let mut ps = vec![0f32; n * n * hw];
    for t in 0..n {
        for s in 0..n {
            for kk in 0..hw {
                let i = (t * n + s) * hw + kk;
                let p = pts[s * hw + kk];
                let q = gt.project(t, &nalgebra::Point3::new(p[0], p[1], p[2]));
                if let Some(q) = q {
                    // deterministic tiny noise
                    let e = ((kk * 7 + s * 3 + t) % 11) as f64 / 11.0 - 0.5;
                    pm[2 * i] = (q.x + 0.004 * e) as f32;
                    pm[2 * i + 1] = (q.y - 0.003 * e) as f32;
                    let inside =
                        q.x > -0.5 && q.y > -0.5 && q.x < w as f64 - 0.5 && q.y < h as f64 - 0.5;
                    ps[i] = if inside { 0.9 } else { 0.0 };
                } else {
                    pm[2 * i] = -100.0;
                    pm[2 * i + 1] = -100.0;
                }
            }
        }
    }
    // feed-forward: exact points, perturbed cameras and focal
    let points: Vec<f32> = pts
        .iter()
        .flat_map(|p| p.iter().map(|&v| v as f32))
        .collect();
    let mut ff_ext = ext.clone();
    for (v, e) in ff_ext.iter_mut().enumerate().skip(1) {
        let dr = Rotation3::from_euler_angles(0.004 * v as f64, -0.003, 0.002).into_inner();
        let r = dr * e.fixed_view::<3, 3>(0, 0).into_owned();
        e.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
        e[(0, 3)] += 0.01;
    }
    let mut kf = k;
    kf[(0, 0)] *= 1.03;
    kf[(1, 1)] *= 1.03;
    let ff = FeedForward {
        points,
        conf: vec![2.0; n * hw],
        cameras: Cameras {
            cam_from_world: ff_ext,
            intrinsics: vec![kf; n],
        },
    };
    // texture
    let images: Vec<f32> = (0..n * hw)
        .flat_map(|p| {
            let q = pts[p];
            let v = (0.5
                + 0.25 * (q[0] * 13.0).sin() * (q[1] * 17.0).cos()
                + 0.2 * (q[0] * 41.0 + q[1] * 29.0).sin()) as f32;
            [v, v * 0.9, v * 0.8]
        })
        .collect();
    let matches = MatchSet {
        matcher: "synthetic".into(),
        pred_matches: pm,
        pred_scores: ps,
        pred_cycle_error: None,
        rank_scores: None,
    };
    Synth {
        dims,
        gt_points: pts,
        gt,
        ff,
        images,
        matches,
    }
}
