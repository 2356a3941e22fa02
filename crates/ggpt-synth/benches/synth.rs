//! Release-mode timing and quality table of the synthetic generator.
//!
//! Run: `cargo bench -p ggpt-synth --bench synth -- [--views 8] [--seeds 3] [--regime easy]`.
//! Prints one row per (kind, seed): stage timings (s), the valid-GT fraction, the feed-forward
//! point accuracy (AUC@5/10 cm after the official robust Sim(3) with retries, and after a
//! trimmed least-squares Sim(3)), and the match pass rates of every matcher.

use anyhow::Result;
use clap::Parser;
use nalgebra::Point3;
use rand::SeedableRng;

use ggpt_synth::stats::{match_stats, point_accuracy};
use ggpt_synth::{Regime, SceneKind, SynthConfig, generate};

/// Timing / quality table of the synthetic generator.
#[derive(Debug, Parser)]
#[command(name = "synth")]
struct Args {
    /// Views per scene.
    #[arg(long, default_value_t = 8)]
    views: usize,
    /// Width (multiple of 14).
    #[arg(long, default_value_t = 518)]
    width: usize,
    /// Height (multiple of 14).
    #[arg(long, default_value_t = 392)]
    height: usize,
    /// Number of seeds per kind (0, 1, ...).
    #[arg(long, default_value_t = 2)]
    seeds: u64,
    /// Skip the (slow) match statistics.
    #[arg(long)]
    no_match_stats: bool,
    /// Timings only: skip every quality statistic (for CPU-time measurements with `time`).
    #[arg(long)]
    timings_only: bool,
    /// Simulation regime (`benchmark`, `easy`).
    #[arg(long, default_value = "benchmark")]
    regime: String,
    /// Scene kinds to run (comma separated: room,object).
    #[arg(long, default_value = "room,object")]
    kinds: String,
    /// Passed by `cargo bench`; ignored.
    #[arg(long, hide = true)]
    bench: bool,
}

fn robust_auc(pred: &[f32], gt: &[f32], mask: &[bool]) -> (f64, f64) {
    let idx: Vec<usize> = (0..mask.len()).filter(|&i| mask[i]).collect();
    let p = |v: &[f32], i: usize| {
        Point3::new(v[3 * i] as f64, v[3 * i + 1] as f64, v[3 * i + 2] as f64)
    };
    let src: Vec<Point3<f64>> = idx.iter().map(|&i| p(pred, i)).collect();
    let tgt: Vec<Point3<f64>> = idx.iter().map(|&i| p(gt, i)).collect();
    let mut rng = rand_pcg::Pcg64::seed_from_u64(42);
    let (sim, _) = ggpt_core::sim3::align_with_retries(&src, &tgt, 0.03, &mut rng);
    let errs: Vec<f64> = src
        .iter()
        .zip(&tgt)
        .map(|(a, b)| (sim.apply(a) - b).norm() * 100.0)
        .collect();
    let n = errs.len().max(1) as f64;
    let auc = |tau: usize| {
        (1..=tau)
            .map(|k| errs.iter().filter(|&&e| e < k as f64).count() as f64 / n)
            .sum::<f64>()
            / tau as f64
            * 100.0
    };
    (auc(5), auc(10))
}

fn main() -> Result<()> {
    let args = Args::parse();
    println!(
        "| kind | seed | N | WxH | render s | ff s | matches s | total s | valid % | ff AUC@5/10 robust | ff AUC@5/10 LS | matcher: score>0.6 / BA pass / DLT pass |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    let kinds: Vec<SceneKind> = args
        .kinds
        .split(',')
        .map(|k| match k.trim() {
            "room" => Ok(SceneKind::Room),
            "object" => Ok(SceneKind::Object),
            other => Err(anyhow::anyhow!("unknown kind {other:?} (room, object)")),
        })
        .collect::<Result<_>>()?;
    for kind in kinds {
        for seed in 0..args.seeds {
            let cfg = SynthConfig {
                kind,
                views: args.views,
                width: args.width,
                height: args.height,
                seed,
                ..SynthConfig::for_regime(Regime::parse(&args.regime)?)
            };
            let out = generate(&cfg)?;
            let t = |name: &str| {
                out.timings
                    .iter()
                    .find(|(n, _)| n == name)
                    .map_or(0.0, |(_, s)| *s)
            };
            let s = &out.scene;
            let gt = s.gt.as_ref().ok_or_else(|| anyhow::anyhow!("no gt"))?;
            let ff = s.ff.as_ref().ok_or_else(|| anyhow::anyhow!("no ff"))?;
            let valid =
                gt.mask.iter().filter(|m| **m).count() as f64 / gt.mask.len() as f64 * 100.0;
            let (r5, r10) = if args.timings_only {
                (f64::NAN, f64::NAN)
            } else {
                robust_auc(&ff.points, &gt.points, &gt.mask)
            };
            let ls = if args.timings_only {
                None
            } else {
                point_accuracy(&ff.points, &gt.points, &gt.mask)
            };
            let mut mstats = String::new();
            if !args.no_match_stats && !args.timings_only {
                for ms in &s.matches {
                    let st = match_stats(ms, s.dims);
                    mstats += &format!(
                        "{}: {:.2} / {:.2} / {:.2}; ",
                        ms.matcher, st.score_gt_06, st.ba_pass, st.dlt_pass
                    );
                }
            }
            println!(
                "| {kind} | {seed} | {} | {}x{} | {:.2} | {:.2} | {:.2} | {:.2} | {valid:.1} | {r5:.1} / {r10:.1} | {} | {mstats} |",
                s.dims.n,
                s.dims.w,
                s.dims.h,
                t("render"),
                t("feedforward"),
                t("matches"),
                t("total"),
                ls.map_or("-".into(), |a| format!("{:.1} / {:.1}", a.auc5, a.auc10)),
            );
        }
    }
    Ok(())
}
