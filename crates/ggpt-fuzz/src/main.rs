//! `ggpt-fuzz`: runs the mutation harness over every reader (or the `--target`s given) and
//! prints a Markdown table; exits 1 when a case failed. An over-bound allocation aborts with the
//! case named on stderr.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Parser;
use ggpt_cli::{Bar, ProgressArgs};
use ggpt_fuzz::harness::RunOptions;

#[global_allocator]
static ALLOCATOR: ggpt_fuzz::alloc::BoundedAllocator = ggpt_fuzz::alloc::BoundedAllocator;

/// Mutation harness of every ggpt-rs file reader.
#[derive(Parser, Debug)]
#[command(version, about)]
struct Args {
    /// Cases per target.
    #[arg(long, default_value_t = 2000)]
    cases: u64,
    /// Base seed (a case is reproducible from seed, target and case index).
    #[arg(long, default_value_t = 42)]
    seed: u64,
    /// Run only these targets (repeatable; default all). Names: see `--list`.
    #[arg(long = "target")]
    targets: Vec<String>,
    /// Run only this case index (reproduce a reported failure).
    #[arg(long)]
    case: Option<u64>,
    /// Bound of one allocation, MiB.
    #[arg(long, default_value_t = (ggpt_fuzz::alloc::DEFAULT_LIMIT_BYTES >> 20) as u64)]
    max_alloc_mib: u64,
    /// Scratch folder (default: a temporary folder, removed at the end).
    #[arg(long)]
    work_dir: Option<PathBuf>,
    /// Also write the report as JSON here.
    #[arg(long)]
    report: Option<PathBuf>,
    /// List the targets and exit.
    #[arg(long)]
    list: bool,
    #[command(flatten)]
    progress: ProgressArgs,
}

fn main() -> Result<()> {
    // Burn's optimizer-record loading uses `Device::default()`; pin it to the CPU backend the
    // targets use, so that no GPU API is probed (`ggpt-train` does the same).
    if std::env::var_os("BURN_DEVICE").is_none()
        && let Some(name) = ggpt_model::device::default_device_env_name("ndarray")
    {
        // SAFETY: first statement of `main`, before any other thread exists.
        unsafe { std::env::set_var("BURN_DEVICE", name) };
    }
    let a = Args::parse();
    ggpt_cli::init_logging(a.progress.bars());
    if a.list {
        for t in ggpt_fuzz::targets::all() {
            println!("{:22} {}", t.name(), t.describe());
        }
        return Ok(());
    }
    ggpt_fuzz::alloc::set_limit(
        usize::try_from(a.max_alloc_mib.saturating_mul(1 << 20)).unwrap_or(usize::MAX),
    );
    let tmp = tempfile::tempdir().context("creating a scratch folder")?;
    let work_dir = a
        .work_dir
        .clone()
        .unwrap_or_else(|| tmp.path().to_path_buf());
    let options = RunOptions {
        cases: a.cases,
        seed: a.seed,
        only_case: a.case,
        work_dir,
    };
    let per_target = if a.case.is_some() { 1 } else { a.cases };
    let count = if a.targets.is_empty() {
        ggpt_fuzz::targets::NAMES.len()
    } else {
        a.targets.len()
    } as u64;
    let bar = Bar::new("cases", per_target * count);
    let mut last = String::new();
    let mut done_before = 0;
    let mut current = 0;
    let reports = ggpt_fuzz::run(&a.targets, &options, &mut |name, done| {
        if name != last {
            done_before += current;
            last = name.to_string();
            bar.set_message(name);
        }
        current = done;
        bar.set_position(done_before + done);
    })?;
    bar.finish();
    print!("{}", ggpt_fuzz::harness::markdown(&reports, a.seed));
    if let Some(path) = &a.report {
        let text = serde_json::to_string_pretty(&reports).context("serialising the report")?;
        ggpt_core::io::atomic::write_bytes_atomic(path, text.as_bytes())
            .with_context(|| format!("writing {}", path.display()))?;
    }
    let failures: usize = reports.iter().map(|r| r.failures.len()).sum();
    if failures > 0 {
        anyhow::bail!("{failures} failing case(s)");
    }
    Ok(())
}
