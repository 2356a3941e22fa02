//! The mutation harness over every reader (`GGPT_FUZZ_CASES` cases per target, default 1500,
//! seed `GGPT_FUZZ_SEED`, default 42), and tests that the harness itself catches panics,
//! errors that do not name the file, and over-bound allocations.
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

use std::path::Path;

use ggpt_fuzz::harness::{RunOptions, SeedFile, Target};

#[global_allocator]
static ALLOCATOR: ggpt_fuzz::alloc::BoundedAllocator = ggpt_fuzz::alloc::BoundedAllocator;

fn env_u64(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn options(cases: u64, dir: &Path) -> RunOptions {
    RunOptions {
        cases,
        seed: env_u64("GGPT_FUZZ_SEED", 42),
        only_case: None,
        work_dir: dir.to_path_buf(),
    }
}

#[test]
fn every_reader_survives_the_mutation_corpus() {
    assert!(
        ggpt_fuzz::alloc::installed(),
        "the bounded allocator is not the global allocator"
    );
    let dir = tempfile::tempdir().unwrap();
    let o = options(env_u64("GGPT_FUZZ_CASES", 1500), dir.path());
    let reports = ggpt_fuzz::run(&[], &o, &mut |_, _| {}).unwrap();
    let table = ggpt_fuzz::harness::markdown(&reports, o.seed);
    eprintln!("{table}");
    assert_eq!(reports.len(), ggpt_fuzz::targets::NAMES.len());
    for r in &reports {
        assert_eq!(r.cases, o.cases, "{}", r.target);
        // every target must reject a good share of its mutations: a reader that accepts
        // everything would not be tested by this harness
        assert!(
            r.rejected * 10 >= r.cases,
            "{}: only {} of {} mutations rejected",
            r.target,
            r.rejected,
            r.cases
        );
    }
    let failures: usize = reports.iter().map(|r| r.failures.len()).sum();
    assert_eq!(failures, 0, "failing cases:\n{table}");
}

/// A reader of `data.bin` that misbehaves on purpose when the first byte is not `b'o'`.
struct Faulty {
    panic: bool,
}

impl Target for Faulty {
    fn name(&self) -> &'static str {
        if self.panic {
            "faulty-panic"
        } else {
            "faulty-unnamed"
        }
    }
    fn describe(&self) -> &'static str {
        "test reader"
    }
    fn seed(&self) -> ggpt_fuzz::Result<Vec<SeedFile>> {
        Ok(vec![SeedFile::new("data.bin", b"ok 123 456".to_vec())])
    }
    fn read(&self, dir: &Path) -> Result<u64, String> {
        let path = dir.join("data.bin");
        let b = std::fs::read(&path).map_err(|e| format!("{}: {e}", path.display()))?;
        match b.first() {
            Some(b'o') => Ok(b.len() as u64),
            _ if self.panic => panic!("deliberate"),
            _ => Err("bad first byte".into()),
        }
    }
}

#[test]
fn the_harness_reports_panics_and_errors_that_do_not_name_the_file() {
    let dir = tempfile::tempdir().unwrap();
    for panic in [true, false] {
        let r = ggpt_fuzz::run_custom(&Faulty { panic }, &options(300, dir.path())).unwrap();
        assert!(
            !r.failures.is_empty(),
            "{}: no failure found in {} cases",
            r.target,
            r.cases
        );
        let want = if panic {
            "panic: deliberate"
        } else {
            "does not name"
        };
        assert!(
            r.failures.iter().all(|f| f.problem.contains(want)),
            "{:?}",
            r.failures.first()
        );
        assert!(r.same + r.different > 0, "{}: every case failed", r.target);
    }
}

/// Child mode of `an_over_bound_allocation_aborts_with_the_case_named`.
#[test]
fn allocation_probe_child() {
    if std::env::var("GGPT_FUZZ_ALLOC_PROBE").as_deref() != Ok("1") {
        return;
    }
    ggpt_fuzz::alloc::register_targets(ggpt_fuzz::targets::NAMES);
    ggpt_fuzz::alloc::set_case(0, 17, 5);
    ggpt_fuzz::alloc::set_limit(1 << 20);
    let v: Vec<u8> = Vec::with_capacity(std::hint::black_box(64 << 20));
    println!("allocated {}", v.capacity());
}

#[test]
fn an_over_bound_allocation_aborts_with_the_case_named() {
    let exe = std::env::current_exe().unwrap();
    let out = std::process::Command::new(exe)
        .args([
            "--exact",
            "allocation_probe_child",
            "--nocapture",
            "--test-threads=1",
        ])
        .env("GGPT_FUZZ_ALLOC_PROBE", "1")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success(),
        "the probe allocated 64 MiB under a 1 MiB bound"
    );
    assert!(stderr.contains("refused an allocation of 67108864 bytes (bound 1048576 bytes) in target npy, case 17, seed 5"), "stderr: {stderr}");
}
