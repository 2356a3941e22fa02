//! Synthetic bundle-adjustment problems with exact ground truth (`sfm.md` §12.2, §13): cameras on
//! an arc looking at a cloud of points, perturbed poses / points / focal, noisy observations.
//! Used by the tests and by the `ba` bench target (which can export them for pycolmap).

use nalgebra::{Matrix3, Matrix3x4, Point3, Rotation3, Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

use super::{BaObservation, BaProblem, CameraModel, LossFunction, project};

/// Parameters of a synthetic problem. Units: metres, pixels (pixel-centre convention), degrees.
#[derive(Debug, Clone)]
pub struct SyntheticConfig {
    /// Number of views.
    pub views: usize,
    /// Number of points (tracks).
    pub points: usize,
    /// Views observing each point (`≤ views`; consecutive views starting at a random one).
    pub track_length: usize,
    /// Image size `(h, w)`.
    pub image_size: (usize, usize),
    /// Ground-truth focal length (pixels, `fx = fy`).
    pub focal: f64,
    /// Rotation perturbation of the initial poses (degrees, about a random axis).
    pub rotation_noise_deg: f64,
    /// Translation perturbation of the initial poses (metres, random direction).
    pub translation_noise: f64,
    /// Perturbation of the initial points (metres, per coordinate standard deviation).
    pub point_noise: f64,
    /// Relative perturbation of the initial focal length (e.g. 0.02 = 2 %).
    pub focal_noise: f64,
    /// Observation noise (pixels, per coordinate standard deviation).
    pub pixel_noise: f64,
    /// Perturb view 0's initial pose as well (otherwise it is the ground truth).
    pub perturb_first_view: bool,
    /// Random seed.
    pub seed: u64,
}

impl Default for SyntheticConfig {
    /// `sfm.md` §12.2: pinhole `f = 1280` at 1024x768, poses perturbed 0.5° / 5 cm, points
    /// 5 cm, observations 0.5 px.
    fn default() -> Self {
        SyntheticConfig {
            views: 4,
            points: 2048,
            track_length: 4,
            image_size: (768, 1024),
            focal: 1280.0,
            rotation_noise_deg: 0.5,
            translation_noise: 0.05,
            point_noise: 0.05,
            focal_noise: 0.0,
            pixel_noise: 0.5,
            perturb_first_view: false,
            seed: 42,
        }
    }
}

/// A synthetic problem and its ground truth.
#[derive(Debug, Clone)]
pub struct SyntheticBa {
    /// The problem (initial values perturbed). Camera model `PINHOLE`, shared camera, focal
    /// refined, Cauchy loss of scale 0.1 px (GGPT's configuration); change the fields as needed.
    pub problem: BaProblem,
    /// Ground-truth cameras (world -> OpenCV camera).
    pub gt_cam_from_world: Vec<Matrix3x4<f64>>,
    /// Ground-truth focal length (pixels).
    pub gt_focal: f64,
    /// Ground-truth points (world frame, metres).
    pub gt_points: Vec<Point3<f64>>,
}

fn gaussian(rng: &mut Pcg64) -> f64 {
    // Box–Muller.
    let u1: f64 = rng.random::<f64>().max(f64::MIN_POSITIVE);
    let u2: f64 = rng.random::<f64>();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

fn random_unit(rng: &mut Pcg64) -> Vector3<f64> {
    loop {
        let v = Vector3::new(gaussian(rng), gaussian(rng), gaussian(rng));
        let n = v.norm();
        if n > 1e-6 {
            return v / n;
        }
    }
}

/// Camera looking from `centre` at `target` (OpenCV axes, world y down).
fn look_at(centre: &Vector3<f64>, target: &Vector3<f64>) -> Matrix3x4<f64> {
    let z = (target - centre).normalize();
    let down = Vector3::new(0.0, 1.0, 0.0);
    let x = down.cross(&z).normalize();
    let y = z.cross(&x);
    let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
    let t = -r * centre;
    let mut m = Matrix3x4::zeros();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    m.set_column(3, &t);
    m
}

/// Generates a problem: views on a 60° arc of radius 5 m (heights alternating over 2 m) around points in a 4 x 3 x 3 m box;
/// every point is observed by `track_length` consecutive views (cyclically) in which it projects
/// inside the image (resampled otherwise).
pub fn generate(cfg: &SyntheticConfig) -> SyntheticBa {
    let mut rng = Pcg64::seed_from_u64(cfg.seed);
    let n = cfg.views.max(1);
    let track = cfg.track_length.clamp(1, n);
    let (h, w) = cfg.image_size;
    let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    let gt_cams: Vec<Matrix3x4<f64>> = (0..n)
        .map(|v| {
            let a = if n > 1 {
                (-30.0 + 60.0 * v as f64 / (n - 1) as f64).to_radians()
            } else {
                0.0
            };
            let centre = Vector3::new(
                5.0 * a.sin(),
                -1.5 + 1.0 * (v % 3) as f64,
                -5.0 * a.cos() + 5.0,
            );
            look_at(&centre, &Vector3::new(0.0, 0.0, 5.0))
        })
        .collect();
    let mut gt_points = Vec::with_capacity(cfg.points);
    let mut observations = Vec::with_capacity(cfg.points * track);
    let mut tries = 0usize;
    while gt_points.len() < cfg.points && tries < cfg.points * 100 {
        tries += 1;
        let x = Vector3::new(
            rng.random_range(-2.0..2.0),
            rng.random_range(-1.5..1.5),
            5.0 + rng.random_range(-1.5..1.5),
        );
        let first = rng.random_range(0..n);
        let views: Vec<usize> = (0..track).map(|k| (first + k) % n).collect();
        let mut obs = Vec::with_capacity(track);
        for &v in &views {
            let m = &gt_cams[v];
            let p = m.fixed_view::<3, 3>(0, 0) * x + m.column(3);
            match project(&p, cfg.focal, cfg.focal, cx, cy) {
                Some(uv)
                    if uv.x > 0.0
                        && uv.y > 0.0
                        && uv.x < w as f64 - 1.0
                        && uv.y < h as f64 - 1.0 =>
                {
                    obs.push((v, uv));
                }
                _ => break,
            }
        }
        if obs.len() != views.len() {
            continue;
        }
        let j = gt_points.len();
        for (v, uv) in obs {
            let noise = Vector2::new(gaussian(&mut rng), gaussian(&mut rng)) * cfg.pixel_noise;
            observations.push(BaObservation {
                view: v,
                point: j,
                xy: uv + noise,
            });
        }
        gt_points.push(Point3::from(x));
    }
    let init_cams = gt_cams
        .iter()
        .enumerate()
        .map(|(v, m)| {
            if v == 0 && !cfg.perturb_first_view {
                return *m;
            }
            let dr = Rotation3::new(random_unit(&mut rng) * cfg.rotation_noise_deg.to_radians());
            let dt = random_unit(&mut rng) * cfg.translation_noise;
            let mut out = *m;
            let r = dr.matrix() * m.fixed_view::<3, 3>(0, 0);
            out.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
            out.set_column(3, &(m.column(3) + dt));
            out
        })
        .collect();
    let points = gt_points
        .iter()
        .map(|p| {
            p + Vector3::new(gaussian(&mut rng), gaussian(&mut rng), gaussian(&mut rng))
                * cfg.point_noise
        })
        .collect();
    let f0 = cfg.focal * (1.0 + cfg.focal_noise);
    let k = Matrix3::new(f0, 0.0, cx, 0.0, f0, cy, 0.0, 0.0, 1.0);
    SyntheticBa {
        problem: BaProblem {
            cam_from_world: init_cams,
            intrinsics: vec![k; n],
            points,
            observations,
            model: CameraModel::Pinhole,
            shared_camera: true,
            refine_focal: true,
            loss: LossFunction::Cauchy { scale: 0.1 },
            image_size: cfg.image_size,
        },
        gt_cam_from_world: gt_cams,
        gt_focal: cfg.focal,
        gt_points,
    }
}
