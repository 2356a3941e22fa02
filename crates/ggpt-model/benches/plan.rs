//! Host planning benchmark (`ggpt_model::plan`, network.md §3-§8): times the whole
//! `plan_batch` of one synthetic surface-like chunk and its stages (encoding, grid +
//! serialization, neighbour tables, pooling) and prints one table row per size.
//!
//! ```text
//! cargo bench -p ggpt-model --bench plan -- --tokens 100000,400000 --repeat 3
//! ```
//! `--tokens` counts level-0 tokens (pixels + DLT tokens; 30 % of the pixels carry guidance, the
//! cloud of `ggpt_model::bench::surface_chunk`);
//! `--threads` sets the rayon pool size (default: all cores). "CPU s" columns are the mean process
//! CPU time (all threads, 10 ms resolution) per run, meaningful on a machine shared with other
//! jobs; the wall time is the minimum over repeats.

use std::time::Instant;

use clap::Parser;
use ggpt_model::bench::{pixels_for_tokens, surface_chunk};
use ggpt_model::plan::serialize::{compute_codes, orders_and_inverses, serialization_depth};
use ggpt_model::plan::{
    PlanConfig, build_conv_table, encode_chunk, grid_coord, plan_batch, pool_level,
};

/// Host planning benchmark of the GGPT network.
#[derive(Parser, Debug)]
#[command(name = "plan")]
struct Args {
    /// Level-0 tokens per row (comma separated).
    #[arg(long, value_delimiter = ',', default_value = "100000,400000")]
    tokens: Vec<usize>,
    /// Repetitions per measurement.
    #[arg(long, default_value_t = 3)]
    repeat: usize,
    /// Rayon pool size (0: all cores).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Passed by `cargo bench`; ignored.
    #[arg(long, hide = true)]
    bench: bool,
}

/// CPU time (user + system, all threads) of this process in seconds, from `/proc/self/stat`
/// (Linux; 0 elsewhere). Insensitive to other processes competing for the cores.
fn process_cpu_seconds() -> f64 {
    let Ok(stat) = std::fs::read_to_string("/proc/self/stat") else {
        return 0.0;
    };
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let Some(rest) = stat.rsplit_once(')').map(|(_, r)| r) else {
        return 0.0;
    };
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    // rest starts at field 3 (state): field k is index k - 3. Clock ticks are 100 Hz on Linux.
    (ticks(11) + ticks(12)) / 100.0
}

/// Runs `f` `repeat` times: (minimum wall seconds, mean process CPU seconds, last result).
fn time<T>(repeat: usize, mut f: impl FnMut() -> T) -> (f64, f64, T) {
    let cpu0 = process_cpu_seconds();
    let t = Instant::now();
    let mut out = f();
    let mut best = t.elapsed().as_secs_f64();
    for _ in 1..repeat.max(1) {
        let t = Instant::now();
        out = f();
        best = best.min(t.elapsed().as_secs_f64());
    }
    let cpu = (process_cpu_seconds() - cpu0) / repeat.max(1) as f64;
    (best, cpu, out)
}

fn main() {
    let Args {
        tokens,
        repeat,
        threads,
        bench: _,
    } = Args::parse();
    if threads > 0
        && rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build_global()
            .is_err()
    {
        eprintln!("could not set the rayon pool size");
    }
    let cfg = PlanConfig::released();
    println!(
        "| tokens | voxels L0 | conv pairs L0 | threads | CPU s: encode | grid+serialize L0 | conv L0 | pool L0 | plan_batch | wall s: plan_batch | tokens per level |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    for &n in &tokens {
        let chunk = surface_chunk(pixels_for_tokens(n), 42);
        let (_, c_enc, feats) = time(repeat, || encode_chunk(&chunk));
        let feats = feats.unwrap_or_else(|e| {
            eprintln!("encode failed: {e}");
            std::process::exit(1)
        });
        let offsets = [feats.num_tokens];
        let (_, c_ser, (grid, codes, orders, depth)) = time(repeat, || {
            let grid: Vec<[i32; 3]> = feats
                .coord
                .iter()
                .map(|&c| grid_coord(c, cfg.grid_resolution))
                .collect();
            let depth = vec![serialization_depth(&grid)];
            let codes = compute_codes(&grid, &offsets, &depth);
            let (orders, _) = orders_and_inverses(&codes, &offsets);
            (grid, codes, orders, depth)
        });
        let (_, c_conv, table) = time(repeat, || build_conv_table(&grid, &offsets));
        let (_, c_pool, _) = time(repeat, || {
            pool_level(&grid, &codes, &orders[0], &offsets, &depth)
        });
        let (t_plan, cpu_plan, plan) =
            time(repeat, || plan_batch(std::slice::from_ref(&chunk), &cfg));
        let plan = plan.unwrap_or_else(|e| {
            eprintln!("plan failed: {e}");
            std::process::exit(1)
        });
        let sizes: Vec<String> = plan
            .levels
            .iter()
            .map(|l| l.num_tokens.to_string())
            .collect();
        let voxels = {
            let mut g = grid.clone();
            g.sort_unstable();
            g.dedup();
            g.len()
        };
        let pairs: usize = table.taps.iter().map(|t| t.len()).sum();
        println!(
            "| {} | {} | {} | {} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {} |",
            feats.num_tokens,
            voxels,
            pairs,
            rayon::current_num_threads(),
            c_enc,
            c_ser,
            c_conv,
            c_pool,
            cpu_plan,
            t_plan,
            sizes.join(" / ")
        );
    }
}
