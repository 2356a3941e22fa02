//! Opt-in wall-clock profile by building block: the forward's parts, and the phases of a
//! recomputing training step (`step.*`, [`crate::recompute`]) (docs/performance.md).
//!
//! Disabled by default: [`scope`] then costs one relaxed atomic load. When enabled
//! ([`set_enabled`]), every scope adds its wall time to a process-wide table keyed by name,
//! read with [`take_report`]. Only meaningful on the eager CPU backends (flex, ndarray), where
//! an op has finished when it returns; on wgpu the times measure kernel *submission*.

use std::collections::BTreeMap;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

static ENABLED: AtomicBool = AtomicBool::new(false);
static TABLE: Mutex<BTreeMap<String, (f64, u64)>> = Mutex::new(BTreeMap::new());

/// Turns profiling on or off for the whole process.
pub fn set_enabled(on: bool) {
    ENABLED.store(on, Ordering::Relaxed);
}

/// Whether profiling is on.
pub fn is_enabled() -> bool {
    ENABLED.load(Ordering::Relaxed)
}

/// Runs `f`, adding its wall time to entry `name()` when profiling is on.
pub fn scope<T>(name: impl FnOnce() -> String, f: impl FnOnce() -> T) -> T {
    let _timer = Timer::start(name);
    f()
}

/// A scope that ends when dropped (for bodies with early exits): adds its wall time to entry
/// `name` when profiling was on at [`Timer::start`].
#[derive(Debug)]
pub struct Timer {
    name: Option<String>,
    t0: Instant,
}

impl Timer {
    /// Starts timing entry `name()` (not evaluated when profiling is off).
    pub fn start(name: impl FnOnce() -> String) -> Self {
        Self {
            name: is_enabled().then(name),
            t0: Instant::now(),
        }
    }
}

impl Drop for Timer {
    fn drop(&mut self) {
        let Some(name) = self.name.take() else { return };
        let dt = self.t0.elapsed().as_secs_f64();
        if let Ok(mut table) = TABLE.lock() {
            let e = table.entry(name).or_insert((0.0, 0));
            e.0 += dt;
            e.1 += 1;
        }
    }
}

/// One profile entry: total seconds and number of calls.
#[derive(Debug, Clone, PartialEq)]
pub struct ProfileEntry {
    /// Scope name (`"L0.conv"`, `"L2.attn.core"`, ...).
    pub name: String,
    /// Total wall seconds.
    pub seconds: f64,
    /// Number of calls.
    pub calls: u64,
}

/// Returns the accumulated entries (sorted by name) and clears the table.
pub fn take_report() -> Vec<ProfileEntry> {
    let Ok(mut table) = TABLE.lock() else {
        return Vec::new();
    };
    std::mem::take(&mut *table)
        .into_iter()
        .map(|(name, (seconds, calls))| ProfileEntry {
            name,
            seconds,
            calls,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scope_accumulates_only_when_enabled() {
        // Single test touching the global table (tests run in parallel threads).
        let _ = take_report();
        assert_eq!(scope(|| "test.off".into(), || 3), 3);
        set_enabled(true);
        assert_eq!(scope(|| "test.on".into(), || 4), 4);
        assert_eq!(scope(|| "test.on".into(), || 5), 5);
        set_enabled(false);
        let report = take_report();
        let on: Vec<_> = report
            .iter()
            .filter(|e| e.name.starts_with("test."))
            .collect();
        assert_eq!(on.len(), 1);
        assert_eq!(on[0].name, "test.on");
        assert_eq!(on[0].calls, 2);
        assert!(on[0].seconds >= 0.0);
    }
}
