//! Progress bars of the binaries, drawn by `tracing-indicatif` (see [`crate::logging`]): a
//! [`Bar`] is a `tracing` span with a bar attached, so log lines are printed above it.
//!
//! Libraries report progress through [`ggpt_core::Progress`] callbacks; [`StageBars`] turns
//! such reports into one bar per stage.

use std::io::Write;
use std::sync::Mutex;

use ggpt_core::Progress;
use indicatif::ProgressStyle;
use tracing::Span;
use tracing_indicatif::span_ext::IndicatifSpanExt;

/// The one bar template of the project: `name [bar] pos/len message [elapsed < eta]`.
fn style(name: &str) -> ProgressStyle {
    // `{` and `}` in a name would be read as template keys.
    let name = name.replace(['{', '}'], "");
    ProgressStyle::with_template(&format!(
        "{name} {{bar:30}} {{pos}}/{{len}} {{msg}} [{{elapsed_precise}} < {{eta_precise}}]"
    ))
    .unwrap_or_else(|_| ProgressStyle::default_bar())
}

/// A progress bar on stderr; silent when logging was initialised without bars (`--quiet`) or
/// not at all. The bar disappears when the value is dropped or [`Bar::finish`]ed.
pub struct Bar {
    span: Span,
}

impl Bar {
    /// A bar named `name` (shown on its left) over `len` units.
    pub fn new(name: &str, len: u64) -> Self {
        let span = tracing::info_span!("progress", indicatif.pb_show = tracing::field::Empty);
        span.pb_set_style(&style(name));
        span.pb_set_length(len);
        span.pb_start();
        Bar { span }
    }

    /// Sets the number of units.
    pub fn set_length(&self, len: u64) {
        self.span.pb_set_length(len);
    }

    /// Sets the units done.
    pub fn set_position(&self, pos: u64) {
        self.span.pb_set_position(pos);
    }

    /// Adds `delta` units done.
    pub fn inc(&self, delta: u64) {
        self.span.pb_inc(delta);
    }

    /// Sets the text after the counter.
    pub fn set_message(&self, msg: &str) {
        self.span.pb_set_message(msg);
    }

    /// Removes the bar.
    pub fn finish(self) {}
}

/// Prints one line to stdout without tearing the bars (a result line while bars are drawn).
pub fn println_above(line: &str) {
    tracing_indicatif::suspend_tracing_indicatif(|| {
        let mut out = std::io::stdout().lock();
        let _ = writeln!(out, "{line}");
        let _ = out.flush();
    });
}

/// One bar per stage of a library call's [`Progress`] reports: a report of a new stage ends
/// the previous stage's bar and starts a new one.
#[derive(Default)]
pub struct StageBars {
    current: Option<(&'static str, Bar)>,
}

impl StageBars {
    /// No bar yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Takes one report (pass `&mut |p| bars.report(p)` as the library's callback).
    pub fn report(&mut self, p: Progress) {
        let same = matches!(&self.current, Some((stage, _)) if *stage == p.stage);
        if !same {
            self.current = Some((p.stage, Bar::new(p.stage, p.total)));
        }
        if let Some((_, bar)) = &self.current {
            bar.set_length(p.total);
            bar.set_position(p.done);
            if !p.detail.is_empty() {
                bar.set_message(p.detail);
            }
        }
    }

    /// Ends the current bar.
    pub fn finish(&mut self) {
        self.current = None;
    }
}

/// [`StageBars`] behind a mutex, for library callbacks called from several threads
/// (`&(dyn Fn(Progress) + Sync)`).
#[derive(Default)]
pub struct SyncStageBars(Mutex<StageBars>);

impl SyncStageBars {
    /// No bar yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Takes one report (pass `&|p| bars.report(p)` as the library's callback).
    pub fn report(&self, p: Progress) {
        if let Ok(mut b) = self.0.lock() {
            b.report(p);
        }
    }

    /// Ends the current bar.
    pub fn finish(&self) {
        if let Ok(mut b) = self.0.lock() {
            b.finish();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stage_bars_switch_on_a_new_stage() {
        crate::init_logging(true);
        let mut bars = StageBars::new();
        bars.report(Progress::new("sfm", 0, 3).with_detail("cycle"));
        assert_eq!(bars.current.as_ref().map(|c| c.0), Some("sfm"));
        bars.report(Progress::new("sfm", 2, 3));
        bars.report(Progress::new("refine", 1, 10));
        assert_eq!(bars.current.as_ref().map(|c| c.0), Some("refine"));
        bars.finish();
        assert!(bars.current.is_none());
        let shared = SyncStageBars::new();
        std::thread::scope(|s| {
            for i in 0..4 {
                let shared = &shared;
                s.spawn(move || shared.report(Progress::new("matches", i, 4)));
            }
        });
        shared.finish();
    }

    #[test]
    fn names_with_braces_still_give_a_template() {
        let _ = style("a{b}c");
        let bar = Bar::new("{x}", 2);
        bar.inc(1);
        bar.set_message("m");
        bar.finish();
    }
}
