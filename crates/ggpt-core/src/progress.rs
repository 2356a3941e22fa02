//! Progress reports of long library calls. Libraries take a `&mut dyn FnMut(Progress)`
//! callback and never draw anything themselves; the binaries turn the reports into progress
//! bars (`ggpt-cli`).

/// `done` of `total` units of the stage `stage` are finished.
///
/// A stage is a named phase of a call (`"sfm"`, `"refine"`, ...); its unit is the stage's own
/// (SfM steps, chunks, scenes). A report with `done == total` ends the stage.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Progress {
    /// Name of the stage, stable across releases (shown next to the bar).
    pub stage: &'static str,
    /// What the unit currently in progress is (e.g. the SfM step's name), if anything.
    pub detail: &'static str,
    /// Units finished so far.
    pub done: u64,
    /// Units of the stage.
    pub total: u64,
}

impl Progress {
    /// A report of stage `stage` with no detail.
    pub fn new(stage: &'static str, done: u64, total: u64) -> Self {
        Progress {
            stage,
            detail: "",
            done,
            total,
        }
    }

    /// The same report with `detail` set.
    pub fn with_detail(self, detail: &'static str) -> Self {
        Progress { detail, ..self }
    }
}

/// A callback that ignores every report.
pub fn ignore(_: Progress) {}
