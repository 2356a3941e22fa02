//! The mutation loop: for each case, one seed file of a target is mutated, the target's reader
//! runs on the folder, and the outcome is classified. A case passes when the reader returns the
//! original data, other data (a mutation of payload bytes the format cannot detect), or an
//! error that names the mutated file. It fails on a panic or on an error that does not name the
//! file. An allocation beyond the bound aborts the process, with the case named on stderr
//! ([`crate::alloc`]).

use std::collections::BTreeMap;
use std::hash::{DefaultHasher, Hash, Hasher};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use rand::SeedableRng;
use serde::Serialize;

use crate::mutate::{Mutation, digit_runs, draw};
use crate::{FuzzError, Result};

/// A seed file of a target: path relative to the target's folder, and its bytes.
#[derive(Debug, Clone)]
pub struct SeedFile {
    /// Relative path.
    pub path: PathBuf,
    /// Pristine bytes.
    pub bytes: Vec<u8>,
    /// Whether cases mutate this file (a folder format may hold files that belong to another
    /// target, e.g. the weights next to `inference.json`).
    pub mutate: bool,
}

impl SeedFile {
    /// A file that cases mutate.
    pub fn new(path: impl Into<PathBuf>, bytes: Vec<u8>) -> Self {
        Self {
            path: path.into(),
            bytes,
            mutate: true,
        }
    }

    /// A file that is written but never mutated.
    pub fn fixed(path: impl Into<PathBuf>, bytes: Vec<u8>) -> Self {
        Self {
            path: path.into(),
            bytes,
            mutate: false,
        }
    }
}

/// A reader under test.
pub trait Target: Send + Sync {
    /// Short name (`npy`, `ply`, ...).
    fn name(&self) -> &'static str;
    /// What it reads, for the report.
    fn describe(&self) -> &'static str;
    /// The valid seed files (built once per run, deterministic).
    fn seed(&self) -> Result<Vec<SeedFile>>;
    /// Runs the reader on the folder `dir` holding the (possibly mutated) seed files. `Ok` is
    /// a fingerprint of the decoded data; `Err` is the reader's error message.
    fn read(&self, dir: &Path) -> std::result::Result<u64, String>;
}

/// Fingerprint of a value through its `Debug` text.
pub fn fingerprint_debug(v: &impl std::fmt::Debug) -> u64 {
    let mut h = DefaultHasher::new();
    format!("{v:?}").hash(&mut h);
    h.finish()
}

/// How one case ended.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub enum Outcome {
    /// The reader returned the original data.
    Same,
    /// The reader returned other, well-formed data.
    Different,
    /// The reader returned an error naming the file.
    Rejected,
    /// A defect: panic, or an error that does not name the file.
    Failure(String),
}

/// One failing case, enough to reproduce it.
#[derive(Debug, Clone, Serialize)]
pub struct FailureCase {
    /// Case index.
    pub case: u64,
    /// Mutated file (relative).
    pub file: String,
    /// The mutation.
    pub mutation: String,
    /// What went wrong.
    pub problem: String,
}

/// Result of one target.
#[derive(Debug, Clone, Serialize)]
pub struct TargetReport {
    /// Target name.
    pub target: String,
    /// What it reads.
    pub describe: String,
    /// Cases run.
    pub cases: u64,
    /// Original data back.
    pub same: u64,
    /// Other well-formed data.
    pub different: u64,
    /// Errors naming the file.
    pub rejected: u64,
    /// Defects.
    pub failures: Vec<FailureCase>,
    /// Largest growth of the live heap during one case, bytes.
    pub max_case_heap_bytes: u64,
    /// Seed file sizes, bytes.
    pub seed_bytes: u64,
    /// Wall time, seconds.
    pub seconds: f64,
}

/// Options of a run.
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// Cases per target.
    pub cases: u64,
    /// Base seed.
    pub seed: u64,
    /// Run only this case index (reproduction).
    pub only_case: Option<u64>,
    /// Scratch folder (one subfolder per target).
    pub work_dir: PathBuf,
}

/// The RNG of case `case` of `target` under `seed`: independent of the other cases, so that
/// one case can be rerun alone.
fn case_rng(seed: u64, target: &str, case: u64) -> rand_pcg::Pcg64 {
    let mut h = DefaultHasher::new();
    (seed, target, case).hash(&mut h);
    rand_pcg::Pcg64::seed_from_u64(h.finish())
}

/// Panic messages of the cases (the panic hook stores them here instead of printing them).
type PanicSlot = Arc<Mutex<Option<String>>>;

fn install_quiet_hook(
    slot: PanicSlot,
) -> Box<dyn Fn(&std::panic::PanicHookInfo<'_>) + Sync + Send + 'static> {
    let previous = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let msg = info
            .payload()
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| info.payload().downcast_ref::<String>().cloned())
            .unwrap_or_default();
        let at = info
            .location()
            .map(|l| format!(" at {}:{}", l.file(), l.line()))
            .unwrap_or_default();
        if let Ok(mut s) = slot.lock() {
            *s = Some(format!("panic: {msg}{at}"));
        }
    }));
    previous
}

fn write_file(path: &Path, bytes: &[u8]) -> Result<()> {
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent).map_err(|e| FuzzError::Io {
            path: parent.to_path_buf(),
            source: e,
        })?;
    }
    std::fs::write(path, bytes).map_err(|e| FuzzError::Io {
        path: path.to_path_buf(),
        source: e,
    })
}

/// Classifies a reader result for a case that mutated `file`.
fn classify(result: std::result::Result<u64, String>, original: u64, file: &Path) -> Outcome {
    match result {
        Ok(f) if f == original => Outcome::Same,
        Ok(_) => Outcome::Different,
        Err(message) => {
            let name = file
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            if !name.is_empty() && message.contains(&name) {
                Outcome::Rejected
            } else {
                Outcome::Failure(format!("error does not name {}: {message}", file.display()))
            }
        }
    }
}

/// Runs `cases` mutations of `target` (index `index` in the registry, for the abort message).
/// `progress(done)` is called after every case.
pub fn run_target(
    target: &dyn Target,
    index: usize,
    o: &RunOptions,
    progress: &mut dyn FnMut(u64),
) -> Result<TargetReport> {
    let started = Instant::now();
    let seeds = target.seed()?;
    let dir = o.work_dir.join(target.name());
    if dir.exists() {
        std::fs::remove_dir_all(&dir).map_err(|e| FuzzError::Io {
            path: dir.clone(),
            source: e,
        })?;
    }
    for s in &seeds {
        write_file(&dir.join(&s.path), &s.bytes)?;
    }
    let original = target.read(&dir).map_err(|message| FuzzError::Seed {
        target: target.name().to_string(),
        message,
    })?;
    let mutable: Vec<&SeedFile> = seeds.iter().filter(|s| s.mutate).collect();
    if mutable.is_empty() {
        return Err(FuzzError::Seed {
            target: target.name().to_string(),
            message: "no mutable seed file".into(),
        });
    }
    let runs: BTreeMap<&Path, Vec<(usize, usize)>> = mutable
        .iter()
        .map(|s| (s.path.as_path(), digit_runs(&s.bytes)))
        .collect();
    let mut report = TargetReport {
        target: target.name().to_string(),
        describe: target.describe().to_string(),
        cases: 0,
        same: 0,
        different: 0,
        rejected: 0,
        failures: Vec::new(),
        max_case_heap_bytes: 0,
        seed_bytes: seeds.iter().map(|s| s.bytes.len() as u64).sum(),
        seconds: 0.0,
    };
    let slot: PanicSlot = Arc::new(Mutex::new(None));
    let previous = install_quiet_hook(slot.clone());
    let cases: Vec<u64> = match o.only_case {
        Some(c) => vec![c],
        None => (0..o.cases).collect(),
    };
    let mut result = Ok(());
    for case in cases {
        let mut rng = case_rng(o.seed, target.name(), case);
        let file = mutable[rand::Rng::random_range(&mut rng, 0..mutable.len())];
        let mutation: Mutation = draw(&mut rng, &file.bytes, &runs[file.path.as_path()]);
        let mutated = mutation.apply(&file.bytes);
        let path = dir.join(&file.path);
        if let Err(e) = write_file(&path, &mutated) {
            result = Err(e);
            break;
        }
        crate::alloc::set_case(index, case, o.seed);
        let base = crate::alloc::reset_peak();
        let read = catch_unwind(AssertUnwindSafe(|| target.read(&dir)));
        report.max_case_heap_bytes = report
            .max_case_heap_bytes
            .max(crate::alloc::peak_bytes().saturating_sub(base) as u64);
        let outcome = match read {
            Ok(r) => classify(r, original, &path),
            Err(_) => Outcome::Failure(
                slot.lock()
                    .ok()
                    .and_then(|mut s| s.take())
                    .unwrap_or_else(|| "panic".into()),
            ),
        };
        report.cases += 1;
        match outcome {
            Outcome::Same => report.same += 1,
            Outcome::Different => report.different += 1,
            Outcome::Rejected => report.rejected += 1,
            Outcome::Failure(problem) => report.failures.push(FailureCase {
                case,
                file: file.path.display().to_string(),
                mutation: format!("{mutation:?}").chars().take(300).collect(),
                problem: problem.chars().take(600).collect(),
            }),
        }
        // restore the pristine file for the next case
        if let Err(e) = write_file(&path, &file.bytes) {
            result = Err(e);
            break;
        }
        progress(report.cases);
    }
    std::panic::set_hook(previous);
    result?;
    report.seconds = started.elapsed().as_secs_f64();
    Ok(report)
}

/// The report as a Markdown table (one row per target) followed by the failing cases.
pub fn markdown(reports: &[TargetReport], seed: u64) -> String {
    let mut s = String::from(
        "| target | reads | seed bytes | cases | same | other data | rejected | failures | max heap / case | time |\n|---|---|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for r in reports {
        s.push_str(&format!(
            "| `{}` | {} | {} | {} | {} | {} | {} | {} | {:.1} MiB | {:.1} s |\n",
            r.target,
            r.describe,
            r.seed_bytes,
            r.cases,
            r.same,
            r.different,
            r.rejected,
            r.failures.len(),
            r.max_case_heap_bytes as f64 / (1 << 20) as f64,
            r.seconds
        ));
    }
    for r in reports {
        for f in &r.failures {
            s.push_str(&format!(
                "\nFAILURE {} case {} (rerun: ggpt-fuzz --target {} --seed {seed} --case {}): {} mutated by {}: {}\n",
                r.target, f.case, r.target, f.case, f.file, f.mutation, f.problem
            ));
        }
    }
    s
}
