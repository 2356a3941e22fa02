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

/// A cooperative stop request for long library calls (SfM steps, BA iterations, network
/// forwards). Cheap to clone: clones share one flag. A call that sees the request stops at its
/// next check and returns its crate's `Cancelled` error; nothing it would have written is
/// half-written (writes happen after the computation, atomically).
///
/// Two sources, either sufficient: the shared flag ([`Cancel::cancel`], e.g. set by a Ctrl-C
/// handler), and an optional poll function ([`Cancel::with_poll`], e.g. the Python binding's
/// signal check), called at every check; a poll that answers `true` sets the flag.
#[derive(Clone, Default)]
pub struct Cancel {
    flag: std::sync::Arc<std::sync::atomic::AtomicBool>,
    poll: Option<std::sync::Arc<dyn Fn() -> bool + Send + Sync>>,
}

impl std::fmt::Debug for Cancel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Cancel")
            .field(
                "cancelled",
                &self.flag.load(std::sync::atomic::Ordering::Relaxed),
            )
            .field("poll", &self.poll.is_some())
            .finish()
    }
}

/// Tokens compare equal whatever their state: a stop request is not a setting, so option
/// structs that hold one keep a meaningful `==`.
impl PartialEq for Cancel {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl Cancel {
    /// A token that is never cancelled unless [`Cancel::cancel`] is called on it or a clone.
    pub fn new() -> Self {
        Self::default()
    }

    /// A token whose flag is `flag` (shared with its owner, e.g. a signal handler).
    pub fn from_flag(flag: std::sync::Arc<std::sync::atomic::AtomicBool>) -> Self {
        Cancel { flag, poll: None }
    }

    /// The same token with `poll` asked at every check as well.
    pub fn with_poll(self, poll: impl Fn() -> bool + Send + Sync + 'static) -> Self {
        Cancel {
            poll: Some(std::sync::Arc::new(poll)),
            ..self
        }
    }

    /// Requests the stop (seen by every clone).
    pub fn cancel(&self) {
        self.flag.store(true, std::sync::atomic::Ordering::SeqCst);
    }

    /// Whether a stop was requested (asks the poll function when there is one).
    pub fn is_cancelled(&self) -> bool {
        if self.flag.load(std::sync::atomic::Ordering::SeqCst) {
            return true;
        }
        if self.poll.as_ref().is_some_and(|p| p()) {
            self.cancel();
            return true;
        }
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clones_share_the_flag_and_a_poll_sets_it() {
        let c = Cancel::new();
        let d = c.clone();
        assert!(!d.is_cancelled());
        c.cancel();
        assert!(d.is_cancelled());

        let asked = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let a = asked.clone();
        let p = Cancel::new()
            .with_poll(move || a.fetch_add(1, std::sync::atomic::Ordering::SeqCst) >= 1);
        assert!(!p.is_cancelled());
        assert!(p.is_cancelled());
        assert!(p.is_cancelled(), "the flag holds once the poll said yes");
        assert_eq!(asked.load(std::sync::atomic::Ordering::SeqCst), 2);
    }
}
