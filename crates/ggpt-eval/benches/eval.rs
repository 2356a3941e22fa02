//! Benchmark of the evaluation building blocks (run with `--release`): robust Sim(3), point
//! metrics, depth metrics and camera metrics on synthetic data of increasing size. Prints a table.
//!
//! `cargo bench -p ggpt-eval --bench eval [-- --sizes 100000,1600000 --repeats 3]`

use std::time::Instant;

use anyhow::Result;
use clap::Parser;
use ggpt_core::Cameras;
use ggpt_core::metrics::{EVAL_ALIGN_MAX_ERROR, camera_metrics, depth_metrics, point_metrics};
use ggpt_core::sim3::{RobustSim3Options, Sim3, robust_sim3};
use nalgebra::{Matrix3, Matrix3x4, Point3, Rotation3, Vector3};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

/// Timing table of the evaluation building blocks.
#[derive(Debug, Parser)]
#[command(name = "eval")]
struct Args {
    /// Point counts to benchmark (comma separated).
    #[arg(long, value_delimiter = ',', default_values_t = [10_000usize, 100_000, 1_624_448])]
    sizes: Vec<usize>,
    /// Repetitions per measurement (the minimum is reported).
    #[arg(long, default_value_t = 3)]
    repeats: usize,
    /// Seed of the data and RANSAC generators.
    #[arg(long, default_value_t = 42)]
    seed: u64,
    /// Passed by `cargo bench`; ignored.
    #[arg(long, hide = true)]
    bench: bool,
}

fn time_min<T>(repeats: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut best = f64::INFINITY;
    let mut out = f();
    for _ in 0..repeats.max(1) {
        let t = Instant::now();
        out = f();
        best = best.min(t.elapsed().as_secs_f64());
    }
    (best, out)
}

fn main() -> Result<()> {
    let args = Args::parse();
    let mut rng = Pcg64::seed_from_u64(args.seed);
    let truth = Sim3 {
        scale: 0.4,
        rotation: *Rotation3::from_euler_angles(0.2, -0.5, 1.1).matrix(),
        translation: Vector3::new(0.3, -0.2, 1.0),
    };
    println!(
        "{:>10} {:>14} {:>10} {:>16} {:>14} {:>16}",
        "points", "robust_sim3 ms", "inliers %", "point_metrics ms", "depth ms", "cameras(16) ms"
    );
    for &n in &args.sizes {
        // GT points 2-6 m in front of one camera; prediction = similarity of GT with 1 cm noise
        // on 70 % of the points and gross errors on the rest.
        let gt: Vec<f32> = (0..n)
            .flat_map(|_| {
                [
                    rng.random_range(-2.0..2.0f32),
                    rng.random_range(-1.5..1.5f32),
                    rng.random_range(2.0..6.0f32),
                ]
            })
            .collect();
        let inv = truth.inverse()?;
        let pred: Vec<f32> = gt
            .chunks_exact(3)
            .flat_map(|c| {
                let mut q = Point3::new(c[0] as f64, c[1] as f64, c[2] as f64);
                if rng.random_bool(0.7) {
                    q += Vector3::new(
                        rng.random_range(-0.01..0.01),
                        rng.random_range(-0.01..0.01),
                        rng.random_range(-0.01..0.01),
                    );
                } else {
                    q += Vector3::new(
                        rng.random_range(-0.5..0.5),
                        rng.random_range(-0.5..0.5),
                        rng.random_range(-0.5..0.5),
                    );
                }
                let r = inv.apply(&q);
                [r.x as f32, r.y as f32, r.z as f32]
            })
            .collect();
        let mask = vec![true; n];
        let to_pts = |v: &[f32]| -> Vec<Point3<f64>> {
            v.chunks_exact(3)
                .map(|c| Point3::new(c[0] as f64, c[1] as f64, c[2] as f64))
                .collect()
        };
        let (src, tgt) = (to_pts(&pred), to_pts(&gt));
        let (t_ransac, res) = time_min(args.repeats, || {
            let mut r = Pcg64::seed_from_u64(args.seed);
            robust_sim3(&src, &tgt, &RobustSim3Options::default(), &mut r)
        });
        let inl = res
            .map(|r| 100.0 * r.num_inliers as f64 / n as f64)
            .unwrap_or(f64::NAN);
        let (t_points, ev) = time_min(args.repeats, || {
            let mut r = Pcg64::seed_from_u64(args.seed);
            point_metrics(&pred, &gt, &mask, None, EVAL_ALIGN_MAX_ERROR, &mut r)
        });
        let ev = ev?;
        let cams = Cameras {
            cam_from_world: vec![Matrix3x4::identity()],
            intrinsics: vec![Matrix3::identity()],
        };
        let (t_depth, _) = time_min(args.repeats, || {
            depth_metrics(&pred, &ev.sim3, &cams, &gt, None, &mask)
        });
        let many = Cameras {
            cam_from_world: (0..16)
                .map(|i| {
                    let mut m = Matrix3x4::identity();
                    m[(0, 3)] = i as f64;
                    m
                })
                .collect(),
            intrinsics: vec![Matrix3::identity(); 16],
        };
        let (t_cams, _) = time_min(args.repeats, || camera_metrics(&many, &many));
        println!(
            "{:>10} {:>14.1} {:>10.1} {:>16.1} {:>14.1} {:>16.3}",
            n,
            1e3 * t_ransac,
            inl,
            1e3 * t_points,
            1e3 * t_depth,
            1e3 * t_cams
        );
    }
    Ok(())
}
