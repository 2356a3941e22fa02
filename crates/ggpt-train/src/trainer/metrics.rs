//! `metrics.jsonl`: one JSON line per training step and per validation.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::{Result, TrainError, io_err};
use crate::evaluate::ChunkValidation;

/// One line of `metrics.jsonl`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MetricsLine {
    /// Step (1-based: after this many updates).
    pub step: u64,
    /// `train` or `val`.
    pub kind: String,
    /// Loss.
    pub loss: f64,
    /// `L_conf` part (train lines).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub loss_conf: Option<f64>,
    /// `L_id` part (train lines).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub loss_id: Option<f64>,
    /// Learning rate of the step.
    pub lr: f64,
    /// Gradient global norm (before clipping).
    pub grad_norm: f64,
    /// Chunks per second of this step.
    pub chunks_per_s: f64,
    /// Tokens per second of this step.
    pub tokens_per_s: f64,
    /// Seconds since the run (or resume) started.
    pub elapsed_s: f64,
    /// Validation result (val lines).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub val: Option<ChunkValidation>,
}

pub(super) fn append_metrics(path: &Path, line: &MetricsLine) -> Result<()> {
    use std::io::Write;
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .map_err(io_err(path))?;
    let text = serde_json::to_string(line).map_err(|e| TrainError::Invalid(e.to_string()))?;
    writeln!(f, "{text}").map_err(io_err(path))
}

/// Makes `metrics.jsonl` consistent with a run that continues after `step`: drops every line
/// past `step` (steps re-run after a crash would otherwise appear twice) and any torn line a
/// crash left, atomically (temporary file + rename). Returns the number of lines dropped.
pub fn truncate_metrics(path: &Path, step: u64) -> Result<usize> {
    let text = match std::fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(0),
        Err(e) => return Err(io_err(path)(e)),
    };
    let mut kept = String::with_capacity(text.len());
    let mut dropped = 0;
    for line in text.lines().filter(|l| !l.trim().is_empty()) {
        match serde_json::from_str::<MetricsLine>(line) {
            Ok(m) if m.step <= step => {
                kept.push_str(line);
                kept.push('\n');
            }
            _ => dropped += 1,
        }
    }
    if dropped > 0 {
        ggpt_core::io::atomic::write_bytes_atomic(path, kept.as_bytes())?;
        tracing::info!(
            "{}: dropped {dropped} line(s) past step {step}",
            path.display()
        );
    }
    Ok(dropped)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn metrics_line(step: u64, kind: &str) -> String {
        let l = MetricsLine {
            step,
            kind: kind.into(),
            loss: 1.0 / step as f64,
            loss_conf: None,
            loss_id: None,
            lr: 1e-4,
            grad_norm: 1.0,
            chunks_per_s: 1.0,
            tokens_per_s: 1.0,
            elapsed_s: 0.0,
            val: None,
        };
        serde_json::to_string(&l).unwrap()
    }

    /// Lines past the resume step and a torn last line are dropped; the rest is kept verbatim.
    #[test]
    fn truncate_metrics_drops_lines_past_the_step_and_torn_lines() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.jsonl");
        assert_eq!(
            truncate_metrics(&path, 3).unwrap(),
            0,
            "a missing file is fine"
        );
        let kept: Vec<String> = vec![
            metrics_line(1, "train"),
            metrics_line(2, "train"),
            metrics_line(2, "val"),
            metrics_line(3, "train"),
        ];
        let mut text = kept.join("\n") + "\n";
        text += &(metrics_line(4, "train") + "\n" + &metrics_line(5, "train") + "\n");
        text += &metrics_line(6, "train")[..20]; // torn by a crash
        std::fs::write(&path, &text).unwrap();
        assert_eq!(truncate_metrics(&path, 3).unwrap(), 3);
        assert_eq!(
            std::fs::read_to_string(&path).unwrap(),
            kept.join("\n") + "\n"
        );
        assert_eq!(truncate_metrics(&path, 3).unwrap(), 0, "idempotent");
        assert_eq!(
            truncate_metrics(&path, 0).unwrap(),
            4,
            "a fresh run starts a new file"
        );
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "");
    }
}
