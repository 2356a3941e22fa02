//! Process memory figures for the per-stage report (Linux `/proc`; `None` elsewhere).
//!
//! `VmHWM` is the peak resident set size of the process; writing `5` to
//! `/proc/self/clear_refs` resets it (Linux ≥ 4.0), which gives per-stage peaks.

use std::time::Instant;

/// Peak resident set size of this process in bytes (`VmHWM`), if readable.
pub fn peak_rss_bytes() -> Option<u64> {
    status_kb("VmHWM:").map(|kb| kb * 1024)
}

/// Current resident set size in bytes (`VmRSS`), if readable.
pub fn current_rss_bytes() -> Option<u64> {
    status_kb("VmRSS:").map(|kb| kb * 1024)
}

/// Resets the peak resident set size to the current one (best effort, silently ignored where
/// unsupported).
pub fn reset_peak_rss() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

fn status_kb(key: &str) -> Option<u64> {
    let text = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = text.lines().find(|l| l.starts_with(key))?;
    line.trim_start_matches(key)
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()
}

/// One timed stage.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct StageTiming {
    /// Stage name.
    pub stage: String,
    /// Wall-clock seconds.
    pub seconds: f64,
    /// Peak resident memory of the process during the stage (MiB), if measurable.
    pub peak_rss_mib: Option<f64>,
}

/// Collects [`StageTiming`]s: each stage starts by resetting the peak RSS and ends by reading it.
#[derive(Debug, Clone)]
pub struct StageLog {
    stages: Vec<StageTiming>,
    current: Option<(String, Instant)>,
}

impl Default for StageLog {
    fn default() -> Self {
        Self::new()
    }
}

/// Bytes -> MiB.
pub fn mib(bytes: u64) -> f64 {
    bytes as f64 / (1024.0 * 1024.0)
}

impl StageLog {
    /// Empty log.
    pub fn new() -> Self {
        StageLog {
            stages: Vec::new(),
            current: None,
        }
    }

    /// Starts `name` (ending the current stage, if any).
    pub fn start(&mut self, name: &str) {
        self.finish();
        reset_peak_rss();
        self.current = Some((name.to_string(), Instant::now()));
    }

    /// Ends the current stage and logs it.
    pub fn finish(&mut self) {
        if let Some((name, t)) = self.current.take() {
            let seconds = t.elapsed().as_secs_f64();
            self.push(&name, seconds, peak_rss_bytes().map(mib));
        }
    }

    /// Records a stage measured elsewhere.
    pub fn push(&mut self, name: &str, seconds: f64, peak_rss_mib: Option<f64>) {
        match peak_rss_mib {
            Some(m) => tracing::info!("stage {name}: {seconds:.3} s, peak RSS {m:.0} MiB"),
            None => tracing::info!("stage {name}: {seconds:.3} s"),
        }
        self.stages.push(StageTiming {
            stage: name.to_string(),
            seconds,
            peak_rss_mib,
        });
    }

    /// The recorded stages, in order.
    pub fn stages(&self) -> &[StageTiming] {
        &self.stages
    }

    /// Consumes the log (finishing the current stage).
    pub fn into_stages(mut self) -> Vec<StageTiming> {
        self.finish();
        self.stages
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stage_log_records_in_order() {
        let mut log = StageLog::new();
        log.start("a");
        log.start("b");
        log.finish();
        log.push("c", 1.5, Some(2.0));
        let stages = log.into_stages();
        let names: Vec<&str> = stages.iter().map(|s| s.stage.as_str()).collect();
        assert_eq!(names, ["a", "b", "c"]);
        assert!(stages.iter().all(|s| s.seconds >= 0.0));
        assert_eq!(stages[2].seconds, 1.5);
        if cfg!(target_os = "linux") {
            assert!(peak_rss_bytes().unwrap() >= current_rss_bytes().unwrap() / 2);
            assert!(stages[0].peak_rss_mib.unwrap() > 0.0);
        }
    }
}
