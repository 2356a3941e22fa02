//! DLT throughput benchmark (`sfm.md` §12.2 target: ≥ 1M tracks/s per core).
//!
//! `cargo bench -p ggpt-sfm --bench dlt [-- --views 4,8,16 --width 518 --height 392 --reps 3]`
//! builds a synthetic scene (cameras on an arc looking at points 4–6 units away, every pixel a
//! track visible in its source view and in each other view with probability 1/2, 0.3 px noise),
//! runs [`ggpt_sfm::dlt::triangulate_tracks`] and prints a table of tracks per second, plus the
//! time of the following [`ggpt_sfm::scatter::scatter`] of the kept tracks.

use std::time::Instant;

use anyhow::Result;
use clap::Parser;
use ggpt_core::{Cameras, Dims};
use ggpt_sfm::dlt::{DltOptions, triangulate_tracks};
use ggpt_sfm::matches::Correspondences;
use ggpt_sfm::scatter::{ScatterOptions, scatter};
use nalgebra::{Matrix3, Matrix3x4, Point3, Rotation3, Vector3};

#[derive(Parser, Debug)]
#[command(name = "dlt", about = "DLT triangulation throughput benchmark")]
struct Args {
    /// View counts to benchmark.
    #[arg(long, value_delimiter = ',', default_value = "4,8,16")]
    views: Vec<usize>,
    /// ff width.
    #[arg(long, default_value_t = 518)]
    width: usize,
    /// ff height.
    #[arg(long, default_value_t = 392)]
    height: usize,
    /// Repetitions (the best time is reported).
    #[arg(long, default_value_t = 3)]
    reps: usize,
    /// Seed of the synthetic scene.
    #[arg(long, default_value_t = 42)]
    seed: u64,
    /// Passed by `cargo bench`; ignored.
    #[arg(long, hide = true)]
    bench: bool,
}

/// SplitMix64: a tiny deterministic generator for the synthetic data.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E3779B97F4A7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58476D1CE4E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D049BB133111EB);
        z ^ (z >> 31)
    }
    fn uniform(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }
}

fn scene(n: usize, h: usize, w: usize, seed: u64) -> (Correspondences, Vec<bool>, Cameras) {
    let mut rng = Rng(seed);
    let f = 0.8 * w as f64;
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
        let a = 0.05 * v as f64;
        let r = Rotation3::from_euler_angles(0.0, -a, 0.0).into_inner();
        let c = Vector3::new(5.0 * a.sin(), 0.0, 5.0 - 5.0 * a.cos());
        let mut e = Matrix3x4::zeros();
        e.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
        e.set_column(3, &(-r * c));
        ext.push(e);
    }
    let cams = Cameras {
        cam_from_world: ext,
        intrinsics: vec![k; n],
    };
    let hw = h * w;
    let nt = n * hw;
    let dims = Dims { n, h, w };
    let mut matches = vec![0f32; 2 * n * nt];
    let mut vis = vec![false; n * nt];
    for s in 0..n {
        let r = cams.rotation(s);
        let c = cams.center(s).coords;
        for kk in 0..hw {
            let (x, y) = ((kk % w) as f64, (kk / w) as f64);
            let d = r.transpose() * Vector3::new((x - k[(0, 2)]) / f, (y - k[(1, 2)]) / f, 1.0);
            let p = Point3::from(c + d * (4.0 + 2.0 * rng.uniform()));
            let j = s * hw + kk;
            for t in 0..n {
                let visible = t == s || rng.uniform() < 0.5;
                let q = cams.project(t, &p).unwrap_or_default();
                let i = t * nt + j;
                matches[2 * i] = (q.x + 0.3 * (rng.uniform() - 0.5)) as f32;
                matches[2 * i + 1] = (q.y + 0.3 * (rng.uniform() - 0.5)) as f32;
                vis[i] = visible;
            }
        }
    }
    let e = n * nt;
    (
        Correspondences {
            dims,
            matches,
            scores: vec![1.0; e],
            cycle: vec![0.0; e],
        },
        vis,
        cams,
    )
}

/// Process CPU time (user + system, seconds) from `/proc/self/stat` (Linux; `None` elsewhere).
/// Reported because the wall time on a shared machine depends on the load.
fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    let rest = stat.rsplit_once(')')?.1;
    let f: Vec<&str> = rest.split_whitespace().collect();
    let utime: f64 = f.get(11)?.parse().ok()?;
    let stime: f64 = f.get(12)?.parse().ok()?;
    Some((utime + stime) / 100.0)
}

fn main() -> Result<()> {
    let args = Args::parse();
    let opts = DltOptions {
        max_reproj_error: 4.0,
        min_tri_angle_deg: 3.0,
        cheirality: false,
    };
    println!(
        "DLT throughput, {}x{} ff pixels, {} rayon threads",
        args.width,
        args.height,
        rayon::current_num_threads()
    );
    println!(
        "| views | tracks (>= 2 views) | mean views/track | best wall time (s) | tracks/s (wall) | CPU time (s) | tracks per CPU-second | kept | scatter wall (s) | scatter CPU (s) |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for &n in &args.views {
        let (corr, vis, cams) = scene(n, args.height, args.width, args.seed);
        let mut best = f64::INFINITY;
        let mut best_cpu = f64::INFINITY;
        let mut last = None;
        for _ in 0..args.reps.max(1) {
            let c0 = cpu_seconds();
            let t0 = Instant::now();
            let out = triangulate_tracks(&corr, &vis, &cams, &opts)?;
            best = best.min(t0.elapsed().as_secs_f64());
            if let (Some(a), Some(b)) = (c0, cpu_seconds()) {
                best_cpu = best_cpu.min(b - a);
            }
            last = Some(out);
        }
        let out = last.ok_or_else(|| anyhow::anyhow!("no run"))?;
        let (mut sc_best, mut sc_cpu) = (f64::INFINITY, f64::INFINITY);
        for _ in 0..args.reps.max(1) {
            let c0 = cpu_seconds();
            let t0 = Instant::now();
            let sc = scatter(&corr, &vis, &out, &ScatterOptions::default())?;
            sc_best = sc_best.min(t0.elapsed().as_secs_f64());
            if let (Some(a), Some(b)) = (c0, cpu_seconds()) {
                sc_cpu = sc_cpu.min(b - a);
            }
            std::hint::black_box(sc.observations);
        }
        let tracks = out.tracks.len();
        let views: f64 =
            out.tracks.iter().map(|t| t.num_views as f64).sum::<f64>() / tracks.max(1) as f64;
        println!(
            "| {n} | {tracks} | {views:.2} | {best:.3} | {:.0} | {best_cpu:.2} | {:.0} | {} | {sc_best:.3} | {sc_cpu:.2} |",
            tracks as f64 / best,
            tracks as f64 / best_cpu,
            out.counts()[4]
        );
    }
    Ok(())
}
