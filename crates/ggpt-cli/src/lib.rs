//! Command-line support shared by the ggpt-rs binaries (`ggpt-infer`, `ggpt-train`, `ggpt-sfm`,
//! `ggpt-eval`, `ggpt-synth`, `ggpt-fuzz` and the bench binaries).
//!
//! Everything a binary needs that a library must not contain lives here:
//! * [`logging`]: the `tracing` subscriber (stderr, `RUST_LOG`), drawn through
//!   `tracing-indicatif` so that log lines never tear a progress bar;
//! * [`progress`]: progress bars, and the adapter from the libraries' [`ggpt_core::Progress`]
//!   callbacks to bars;
//! * [`args`]: the `clap` argument groups that several binaries share (model, device, chunk
//!   sampler, SfM preset, scene kind, progress), each `serde`-serialisable so that a run can
//!   record it in its `config.json`, with the same flag spelling everywhere;
//! * [`signals`]: Ctrl-C / SIGTERM as a stop flag (the `ctrlc` crate).
//!
//! Library crates never depend on this crate. It depends only on `ggpt-core`, so that every
//! binary of the workspace, including those of the lower crates, can use it.

pub mod args;
pub mod logging;
pub mod progress;
pub mod signals;

pub use args::{
    ChunkingArgs, DeviceArg, DeviceArgs, ModelArgs, ModelPreset, ProgressArgs, RegimeArg,
    SceneKindArg, SfmPresetArg,
};
pub use logging::init_logging;
pub use progress::{Bar, StageBars, SyncStageBars, println_above};
