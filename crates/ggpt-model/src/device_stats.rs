//! Counting what a forward costs a device: host readbacks (each one a device → host
//! synchronisation) and kernel launches (docs/performance.md, "wgpu: launches and syncs").
//!
//! * **Readbacks** are counted by the crate's own readers ([`crate::readback::tensor_into_f32`],
//!   the host kernels' readers): every time the network reads a tensor back, on any backend.
//! * **Kernel launches** are counted through CubeCL's launch observer
//!   (`cubecl_runtime::logging::LaunchObservation`), which sees every kernel the process
//!   issues on a CubeCL backend (wgpu, CUDA). With neither backend compiled there is nothing to
//!   observe, and [`DeviceCounts::launches_observed`] is `false`. The CPU backends (flex,
//!   ndarray) launch no kernels.
//!
//! With [`KernelTiming::Resolved`] every launch also waits for its kernel and reports its
//! duration: the per-kernel table then says where a forward spends its device time, at the
//! price of running the kernels one at a time (the totals are not the pipelined wall time).

use std::sync::atomic::{AtomicU64, Ordering};

/// Host readbacks since the process started (all threads).
static READBACKS: AtomicU64 = AtomicU64::new(0);

/// Counts one device → host readback. Called by every reader of the crate.
pub(crate) fn note_readback() {
    READBACKS.fetch_add(1, Ordering::Relaxed);
}

/// Whether the launches are only counted or also timed one by one.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum KernelTiming {
    /// Count launches only: the pass runs as it normally does.
    #[default]
    CountOnly,
    /// Wait for every kernel and record its duration (serialises the kernels).
    Resolved,
}

/// One kernel (as CubeCL names it) and what the observed pass spent on it.
#[derive(Debug, Clone, PartialEq)]
pub struct KernelCount {
    /// Kernel name, shortened the way CubeCL's profiling log shortens it.
    pub name: String,
    /// Launches of this kernel.
    pub launches: u64,
    /// Summed kernel time in seconds (only with [`KernelTiming::Resolved`]).
    pub seconds: f64,
}

/// What one observed pass cost the device.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct DeviceCounts {
    /// Host readbacks (device → host synchronisations) issued by the network's readers.
    pub readbacks: u64,
    /// Kernel launches (0 when they could not be observed).
    pub launches: u64,
    /// Whether a CubeCL backend is compiled in, so that launches were observed at all.
    pub launches_observed: bool,
    /// Launches per kernel, most launched first.
    pub kernels: Vec<KernelCount>,
}

/// Runs `f` and returns what it cost the device: readbacks, kernel launches and (with
/// `timing = Resolved`) per-kernel device time.
///
/// The launch observer is process-wide: launches from other threads during `f` are counted
/// too, so observe one pass at a time.
pub fn observe<R>(timing: KernelTiming, f: impl FnOnce() -> R) -> (R, DeviceCounts) {
    let readbacks0 = READBACKS.load(Ordering::Relaxed);
    let (out, launches_observed, kernels) = launches::observe(timing, f);
    let mut kernels = kernels;
    kernels.sort_by(|a, b| b.launches.cmp(&a.launches).then(a.name.cmp(&b.name)));
    let counts = DeviceCounts {
        readbacks: READBACKS.load(Ordering::Relaxed) - readbacks0,
        launches: kernels.iter().map(|k| k.launches).sum(),
        launches_observed,
        kernels,
    };
    (out, counts)
}

#[cfg(any(feature = "wgpu", feature = "cuda"))]
mod launches {
    use std::collections::BTreeMap;
    use std::sync::{Arc, Mutex};

    use cubecl_runtime::logging::{
        Duration, LaunchObservation, LaunchObserver, TimingMethod, TimingRequest,
    };

    use super::{KernelCount, KernelTiming};

    /// Launches and summed seconds per kernel name.
    #[derive(Default)]
    struct Counter {
        timing: KernelTiming,
        table: Mutex<BTreeMap<&'static str, (u64, f64)>>,
    }

    impl LaunchObserver for Counter {
        fn launched(&self, kernel: &'static str) {
            if let Ok(mut t) = self.table.lock() {
                t.entry(kernel).or_default().0 += 1;
            }
        }

        fn timing(&self) -> TimingRequest {
            match self.timing {
                KernelTiming::CountOnly => TimingRequest::None,
                KernelTiming::Resolved => TimingRequest::Resolved,
            }
        }

        fn timed(&self, kernel: &'static str, duration: Duration, _method: TimingMethod) {
            if let Ok(mut t) = self.table.lock() {
                t.entry(kernel).or_default().1 += duration.as_secs_f64();
            }
        }
    }

    pub(super) fn observe<R>(
        timing: KernelTiming,
        f: impl FnOnce() -> R,
    ) -> (R, bool, Vec<KernelCount>) {
        let counter = Arc::new(Counter {
            timing,
            table: Mutex::new(BTreeMap::new()),
        });
        let guard = LaunchObservation::new(counter.clone());
        let out = f();
        drop(guard);
        let table = counter.table.lock().map(|t| t.clone()).unwrap_or_default();
        let kernels = table
            .into_iter()
            .map(|(name, (launches, seconds))| KernelCount {
                name: short_name(name),
                launches,
                seconds,
            })
            .collect();
        (out, true, kernels)
    }

    /// `a::b::Kernel<c::D>` -> `Kernel<D>`: the last path segment of every type path.
    fn short_name(name: &str) -> String {
        let mut out = String::with_capacity(name.len());
        let mut word = String::new();
        for ch in name.chars() {
            if ch.is_alphanumeric() || ch == '_' || ch == ':' {
                word.push(ch);
            } else {
                out.push_str(word.rsplit("::").next().unwrap_or(&word));
                word.clear();
                out.push(ch);
            }
        }
        out.push_str(word.rsplit("::").next().unwrap_or(&word));
        out
    }
}

#[cfg(not(any(feature = "wgpu", feature = "cuda")))]
mod launches {
    use super::{KernelCount, KernelTiming};

    pub(super) fn observe<R>(
        _timing: KernelTiming,
        f: impl FnOnce() -> R,
    ) -> (R, bool, Vec<KernelCount>) {
        (f(), false, Vec::new())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn readbacks_are_counted() {
        let ((), c) = observe(KernelTiming::CountOnly, || {
            note_readback();
            note_readback();
        });
        // Other tests may read back concurrently: at least our two.
        assert!(c.readbacks >= 2);
    }
}
