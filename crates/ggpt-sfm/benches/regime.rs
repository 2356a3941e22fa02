//! Synthetic regime benchmark: how hard the `ggpt-synth` scenes are once they go through the
//! real SfM stage (the numbers `docs/synthetic.md` tunes the generator against).
//!
//! `cargo bench -p ggpt-sfm --bench regime -- --scenes 20 --first-seed 0 --views 4,8
//! --kinds room,object [--per-matcher] [--width 518 --height 392] [--threads T]`
//!
//! Scene `i` in `0..scenes` has seed `first_seed + i`, kind `kinds[i % kinds.len()]` and
//! `views[(i / kinds.len()) % views.len()]` views (so every kind meets every view count). Each
//! scene is generated with [`ggpt_synth::generate`], then the SfM stage runs exactly as
//! `ggpt-train`'s `scene_source::synthetic_scene` runs it (benchmark preset, both matchers). Printed
//! (markdown): per scene the feed-forward AUC@5/@10 over all GT pixels, the SfM coverage (GT-valid
//! pixels with a DLT point), the SfM AUC@5 on the covered pixels and over all pixels, optionally
//! the coverage with each matcher alone, and the SfM wall time; then min / median / mean / max
//! over the scenes and how many scenes lie inside the target ranges. A scene whose generation,
//! SfM or metrics fail is printed with its error and the run goes on.

use std::time::Instant;

use anyhow::{Context, Result, anyhow};
use clap::Parser;
use ggpt_core::metrics::{EVAL_ALIGN_MAX_ERROR, PointMetrics, point_metrics};
use ggpt_core::{MatchSet, Scene, SfmResult};
use ggpt_sfm::masks::Preset;
use ggpt_sfm::pipeline::{SfmConfig, run_sfm};
use ggpt_synth::{Regime, SceneKind, SynthConfig};
use rand::SeedableRng;
use rand_pcg::Pcg64;

/// Target range of the SfM coverage (percent of GT-valid pixels).
const TARGET_COVERAGE_PCT: (f64, f64) = (20.0, 70.0);
/// Target range of the SfM all-pixel AUC@5 (percent).
const TARGET_SFM_AUC5: (f64, f64) = (10.0, 45.0);
/// Target range of the feed-forward AUC@5 (percent).
const TARGET_FF_AUC5: (f64, f64) = (15.0, 28.0);

#[derive(Parser, Debug)]
#[command(name = "regime", about = "Synthetic regime through the real SfM stage")]
struct Args {
    /// Number of scenes.
    #[arg(long, default_value_t = 20)]
    scenes: usize,
    /// Seed of the first scene (scene i has seed first_seed + i).
    #[arg(long, default_value_t = 0)]
    first_seed: u64,
    /// View counts, cycled after the kinds.
    #[arg(long, value_delimiter = ',', default_value = "4,8")]
    views: Vec<usize>,
    /// Scene kinds (room, object), cycled per scene.
    #[arg(long, value_delimiter = ',', default_value = "room,object")]
    kinds: Vec<String>,
    /// Simulation regime (`benchmark`, `easy`).
    #[arg(long, default_value = "benchmark")]
    regime: String,
    /// Also run the SfM with each matcher alone and print its coverage.
    #[arg(long)]
    per_matcher: bool,
    /// ff width.
    #[arg(long, default_value_t = 518)]
    width: usize,
    /// ff height.
    #[arg(long, default_value_t = 392)]
    height: usize,
    /// Seed of the Sim(3) RANSAC of the metrics (fresh generator per evaluation, as
    /// `ggpt_eval::evaluate_refinement`; 42 = `ggpt_train`'s held-out evaluation seed).
    #[arg(long, default_value_t = 42)]
    eval_seed: u64,
    /// Rayon threads (default: rayon's default).
    #[arg(long)]
    threads: Option<usize>,
    /// Passed by `cargo bench`; ignored.
    #[arg(long, hide = true)]
    bench: bool,
}

/// Measurements of one scene.
struct Row {
    ff_auc5: f64,
    ff_auc10: f64,
    /// Coverage in percent.
    coverage_pct: f64,
    sfm_auc5_covered: f64,
    sfm_all_auc5: f64,
    sfm_all_auc10: f64,
    /// Per matcher: name and coverage in percent (or the error).
    per_matcher: Vec<(String, Result<f64, String>)>,
    synth_s: f64,
    sfm_s: f64,
}

/// Evaluates `pred` against the scene's GT, with a fresh RANSAC generator (as
/// `ggpt_eval::evaluate_refinement` does).
fn eval(scene: &Scene, pred: &[f32], subset: Option<&[bool]>, seed: u64) -> Result<PointMetrics> {
    let gt = scene
        .gt
        .as_ref()
        .ok_or_else(|| anyhow!("no ground truth"))?;
    let mut rng = Pcg64::seed_from_u64(seed);
    Ok(point_metrics(
        pred,
        &gt.points,
        &gt.mask,
        subset,
        EVAL_ALIGN_MAX_ERROR,
        &mut rng,
    )?
    .metrics)
}

/// Runs the SfM stage on `matches` as `ggpt_train::scene_source::synthetic_scene` does.
fn sfm(scene: &Scene, matches: &[MatchSet]) -> Result<SfmResult> {
    let ff = scene
        .ff
        .as_ref()
        .ok_or_else(|| anyhow!("no feed-forward prediction"))?;
    let cfg = SfmConfig::preset(Preset::Benchmark);
    Ok(run_sfm(ff, &scene.images, scene.dims, matches, &cfg)?.result)
}

/// Fraction of GT-valid pixels covered by the SfM mask (what `PointMetrics::ratio` reports,
/// without the alignment).
fn coverage(scene: &Scene, sfm: &SfmResult) -> Result<f64> {
    let gt = scene
        .gt
        .as_ref()
        .ok_or_else(|| anyhow!("no ground truth"))?;
    let valid = gt.mask.iter().filter(|&&m| m).count();
    let covered = gt
        .mask
        .iter()
        .zip(&sfm.mask)
        .filter(|(g, s)| **g && **s)
        .count();
    Ok(if valid == 0 {
        0.0
    } else {
        covered as f64 / valid as f64
    })
}

fn run_scene(args: &Args, kind: SceneKind, views: usize, seed: u64) -> Result<Row> {
    let cfg = SynthConfig {
        kind,
        views,
        width: args.width,
        height: args.height,
        seed,
        ..SynthConfig::for_regime(Regime::parse(&args.regime)?)
    };
    let t0 = Instant::now();
    let scene = ggpt_synth::generate(&cfg).context("generate")?.scene;
    let synth_s = t0.elapsed().as_secs_f64();
    let ff = scene
        .ff
        .as_ref()
        .ok_or_else(|| anyhow!("no feed-forward prediction"))?;
    let ff_m = eval(&scene, &ff.points, None, args.eval_seed).context("ff metrics")?;

    let t0 = Instant::now();
    let res = sfm(&scene, &scene.matches).context("SfM")?;
    let sfm_s = t0.elapsed().as_secs_f64();
    let sfm_m =
        eval(&scene, &res.points, Some(&res.mask), args.eval_seed).context("SfM metrics")?;
    let cov = sfm_m
        .ratio
        .ok_or_else(|| anyhow!("subset evaluation without a ratio"))?;

    let per_matcher = if args.per_matcher {
        scene
            .matches
            .iter()
            .map(|m| {
                let c = sfm(&scene, std::slice::from_ref(m))
                    .and_then(|r| coverage(&scene, &r))
                    .map(|c| 100.0 * c)
                    .map_err(|e| format!("{e:#}"));
                (m.matcher.clone(), c)
            })
            .collect()
    } else {
        Vec::new()
    };

    // uncovered pixels count as misses, as in every evaluation.json
    let all = ggpt_eval::AllPixelMetrics::from_covered(&sfm_m)
        .ok_or_else(|| anyhow!("SfM covers no GT pixel"))?;
    Ok(Row {
        ff_auc5: ff_m.auc_5,
        ff_auc10: ff_m.auc_10,
        coverage_pct: 100.0 * cov,
        sfm_auc5_covered: sfm_m.auc_5,
        sfm_all_auc5: all.auc_5,
        sfm_all_auc10: all.auc_10,
        per_matcher,
        synth_s,
        sfm_s,
    })
}

/// One summarised column: a value of a row.
type Column = fn(&Row) -> f64;

/// min, median, mean, max of `v` (non-empty).
fn stats(v: &[f64]) -> (f64, f64, f64, f64) {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let n = s.len();
    let median = if n % 2 == 1 {
        s[n / 2]
    } else {
        0.5 * (s[n / 2 - 1] + s[n / 2])
    };
    (s[0], median, s.iter().sum::<f64>() / n as f64, s[n - 1])
}

fn inside(v: f64, (lo, hi): (f64, f64)) -> bool {
    (lo..=hi).contains(&v)
}

fn main() -> Result<()> {
    let args = Args::parse();
    if let Some(t) = args.threads {
        rayon::ThreadPoolBuilder::new()
            .num_threads(t)
            .build_global()
            .context("rayon thread pool")?;
    }
    if args.scenes == 0 || args.views.is_empty() || args.kinds.is_empty() {
        anyhow::bail!("--scenes, --views and --kinds must be non-empty");
    }
    let kinds = args
        .kinds
        .iter()
        .map(|k| SceneKind::parse(k.trim()))
        .collect::<Result<Vec<_>, _>>()?;

    println!(
        "Synthetic {} regime through the SfM stage (benchmark preset), {}x{} ff pixels, {} rayon threads, eval seed {}",
        args.regime,
        args.width,
        args.height,
        rayon::current_num_threads(),
        args.eval_seed
    );
    println!();

    // One coverage column per matcher of the synthetic scenes (the `MatchSet` names).
    let matcher_names: Vec<String> = if args.per_matcher {
        SynthConfig::for_regime(Regime::parse(&args.regime)?)
            .matchers
            .iter()
            .map(|m| m.name.clone())
            .collect()
    } else {
        Vec::new()
    };
    let mut h = String::from(
        "| kind | seed | views | ff AUC@5 | ff AUC@10 | coverage % | SfM AUC@5 (covered) | SfM AUC@5 (all) | SfM AUC@10 (all) |",
    );
    let mut sep = String::from("|---|---|---|---|---|---|---|---|---|");
    for n in &matcher_names {
        h.push_str(&format!(" coverage % {n} only |"));
        sep.push_str("---|");
    }
    h.push_str(" synth s | SfM s |");
    sep.push_str("---|---|");
    println!("{h}\n{sep}");

    let mut rows: Vec<Row> = Vec::new();
    let mut failed = 0usize;
    for i in 0..args.scenes {
        let seed = args.first_seed + i as u64;
        let kind = kinds[i % kinds.len()];
        let views = args.views[(i / kinds.len()) % args.views.len()];
        let res = run_scene(&args, kind, views, seed);
        match res {
            Ok(r) => {
                let mut line = format!(
                    "| {kind} | {seed} | {views} | {:.2} | {:.2} | {:.1} | {:.2} | {:.2} | {:.2} |",
                    r.ff_auc5,
                    r.ff_auc10,
                    r.coverage_pct,
                    r.sfm_auc5_covered,
                    r.sfm_all_auc5,
                    r.sfm_all_auc10
                );
                for name in &matcher_names {
                    match r.per_matcher.iter().find(|(n, _)| n == name) {
                        Some((_, Ok(c))) => line.push_str(&format!(" {c:.1} |")),
                        Some((_, Err(e))) => line.push_str(&format!(" error: {e} |")),
                        None => line.push_str(" - |"),
                    }
                }
                line.push_str(&format!(" {:.2} | {:.2} |", r.synth_s, r.sfm_s));
                println!("{line}");
                rows.push(r);
            }
            Err(e) => {
                failed += 1;
                println!("| {kind} | {seed} | {views} | error: {e:#} |");
            }
        }
    }

    println!();
    println!(
        "Summary over {} scenes ({failed} failed)",
        rows.len() + failed
    );
    if rows.is_empty() {
        return Ok(());
    }
    println!();
    println!("| metric | min | median | mean | max |");
    println!("|---|---|---|---|---|");
    let cols: [(&str, Column); 6] = [
        ("ff AUC@5", |r| r.ff_auc5),
        ("ff AUC@10", |r| r.ff_auc10),
        ("coverage %", |r| r.coverage_pct),
        ("SfM AUC@5 (all)", |r| r.sfm_all_auc5),
        ("SfM AUC@10 (all)", |r| r.sfm_all_auc10),
        ("SfM s", |r| r.sfm_s),
    ];
    for (name, f) in cols {
        let v: Vec<f64> = rows.iter().map(f).collect();
        let (lo, med, mean, hi) = stats(&v);
        println!("| {name} | {lo:.2} | {med:.2} | {mean:.2} | {hi:.2} |");
    }
    let n = rows.len();
    let count = |f: &dyn Fn(&Row) -> bool| rows.iter().filter(|r| f(r)).count();
    let in_cov = count(&|r| inside(r.coverage_pct, TARGET_COVERAGE_PCT));
    let in_sfm = count(&|r| inside(r.sfm_all_auc5, TARGET_SFM_AUC5));
    let in_ff = count(&|r| inside(r.ff_auc5, TARGET_FF_AUC5));
    let in_all = count(&|r| {
        inside(r.coverage_pct, TARGET_COVERAGE_PCT)
            && inside(r.sfm_all_auc5, TARGET_SFM_AUC5)
            && inside(r.ff_auc5, TARGET_FF_AUC5)
    });
    println!();
    println!("Scenes inside the target ranges (of {n} evaluated):");
    println!(
        "- coverage {}-{} %: {in_cov}",
        TARGET_COVERAGE_PCT.0, TARGET_COVERAGE_PCT.1
    );
    println!(
        "- SfM all-pixel AUC@5 {}-{}: {in_sfm}",
        TARGET_SFM_AUC5.0, TARGET_SFM_AUC5.1
    );
    println!(
        "- ff AUC@5 {}-{}: {in_ff}",
        TARGET_FF_AUC5.0, TARGET_FF_AUC5.1
    );
    println!("- all three: {in_all}");
    Ok(())
}
