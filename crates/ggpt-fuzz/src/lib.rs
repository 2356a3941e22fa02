//! Deterministic mutation harness for the file readers of ggpt-rs.
//!
//! Every reader that takes a user's file is a [`harness::Target`] with a valid seed written by
//! the workspace's own writer ([`targets::all`]). Each case mutates one seed file
//! ([`mutate::draw`]: truncations, bit flips, byte edits, splices, oversized ASCII numbers and
//! little-endian length words), runs the reader, and requires the original data, other
//! well-formed data, or an error naming the file: never a panic, and, with
//! [`alloc::BoundedAllocator`] installed, never an allocation beyond the bound. Cases are
//! independent and reproducible from `(seed, target, case)`. See `docs/fuzzing.md`.

pub mod alloc;
pub mod harness;
pub mod mutate;
pub mod targets;

use std::path::PathBuf;

/// Errors of the harness itself (not of the readers under test).
#[derive(Debug, thiserror::Error)]
pub enum FuzzError {
    /// I/O on the scratch folder.
    #[error("{path}: {source}")]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// What the operating system said.
        #[source]
        source: std::io::Error,
    },
    /// A target's seed could not be built or does not read back.
    #[error("target {target}: seed: {message}")]
    Seed {
        /// The target's name.
        target: String,
        /// The problem.
        message: String,
    },
    /// Unknown target name.
    #[error("unknown target {0:?} (known: {known})", known = targets::NAMES.join(", "))]
    UnknownTarget(String),
}

/// Result alias of the harness.
pub type Result<T> = std::result::Result<T, FuzzError>;

/// Serialises runs: the harness swaps the process's panic hook while a target runs.
static RUN_LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Runs the targets named in `only` (all when empty) with `options`; `progress(target, done)`
/// is called after every case.
pub fn run(
    only: &[String],
    options: &harness::RunOptions,
    progress: &mut dyn FnMut(&str, u64),
) -> Result<Vec<harness::TargetReport>> {
    for name in only {
        if !targets::NAMES.contains(&name.as_str()) {
            return Err(FuzzError::UnknownTarget(name.clone()));
        }
    }
    alloc::register_targets(targets::NAMES);
    let _guard = RUN_LOCK.lock().unwrap_or_else(|p| p.into_inner());
    let mut reports = Vec::new();
    for (index, target) in targets::all().into_iter().enumerate() {
        if !only.is_empty() && !only.iter().any(|n| n == target.name()) {
            continue;
        }
        let name = target.name();
        reports.push(harness::run_target(
            target.as_ref(),
            index,
            options,
            &mut |done| progress(name, done),
        )?);
    }
    Ok(reports)
}

/// Runs one custom target (tests of the harness itself).
pub fn run_custom(
    target: &dyn harness::Target,
    options: &harness::RunOptions,
) -> Result<harness::TargetReport> {
    let _guard = RUN_LOCK.lock().unwrap_or_else(|p| p.into_inner());
    harness::run_target(target, usize::MAX, options, &mut |_| {})
}
