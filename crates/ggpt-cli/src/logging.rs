//! Logging of every binary: `tracing` events to stderr, filtered by `RUST_LOG` (default
//! `info`), written through `tracing-indicatif` so that they are printed above the progress
//! bars instead of through them. Colours only when stderr is a terminal.

use std::io::IsTerminal;

use tracing_indicatif::IndicatifLayer;
use tracing_indicatif::filter::{IndicatifFilter, hide_indicatif_span_fields};
use tracing_subscriber::EnvFilter;
use tracing_subscriber::fmt::format::DefaultFields;
use tracing_subscriber::layer::{Layer, SubscriberExt};
use tracing_subscriber::util::SubscriberInitExt;

/// Installs the global subscriber. With `progress` false (`--quiet`) no bar is ever drawn:
/// [`crate::Bar`]s become silent and logs go straight to stderr.
///
/// Calling it twice is harmless (the second call keeps the first subscriber).
pub fn init_logging(progress: bool) {
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    if progress {
        let indicatif = IndicatifLayer::new()
            .with_span_field_formatter(hide_indicatif_span_fields(DefaultFields::new()));
        let fmt = tracing_subscriber::fmt::layer()
            .with_ansi(std::io::stderr().is_terminal())
            .with_writer(indicatif.get_stderr_writer())
            .with_filter(filter);
        let _ = tracing_subscriber::registry()
            .with(fmt)
            .with(indicatif.with_filter(IndicatifFilter::new(false)))
            .try_init();
    } else {
        let fmt = tracing_subscriber::fmt::layer()
            .with_ansi(std::io::stderr().is_terminal())
            .with_writer(std::io::stderr)
            .with_filter(filter);
        let _ = tracing_subscriber::registry().with(fmt).try_init();
    }
}
