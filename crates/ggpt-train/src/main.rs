//! `ggpt-train`: prepare chunk sets, train the GGPT network, evaluate and export it.
//!
//! Without arguments it builds a small synthetic chunk set and trains the tiny configuration
//! on it for a few steps (a demonstration of the whole loop, seconds to a few minutes on CPU).
//!
//! Argument definitions are in `cli.rs`, one file per command in `commands/`; the work itself
//! is in the `ggpt_train` library.

mod cli;
mod commands;

use anyhow::{Context, Result};
use clap::Parser;

use crate::cli::{Cli, Command};

/// Pins Burn's default device (`BURN_DEVICE`, unless the user set it) to the backend of the
/// requested device, so that a CPU run touches no GPU API: Burn 0.22.1 restores the optimizer
/// state of `--resume` on `Device::default()`, which is a wgpu adapter when wgpu is compiled in
/// (a Vulkan probe, and XDG_RUNTIME_DIR errors on headless machines).
fn pin_default_device(device: &str) {
    if std::env::var_os("BURN_DEVICE").is_none()
        && let Some(name) = ggpt_model::device::default_device_env_name(device)
    {
        // SAFETY: called at the start of `main`, before any other thread exists.
        unsafe { std::env::set_var("BURN_DEVICE", name) };
    }
}

fn main() -> Result<()> {
    ggpt_model::device::tune_allocator();
    let cli = Cli::parse();
    ggpt_cli::init_logging(cli.progress.bars());
    pin_default_device(&cli.main_device());
    ggpt_model::device::init_cpu_threads(cli.threads()).context("configuring the thread pool")?;
    match &cli.command {
        None => commands::default_run::run(&cli.out),
        Some(Command::Prepare(a)) => commands::prepare::run(a),
        Some(Command::Train(a)) => commands::train::run(a),
        Some(Command::Eval(a)) => commands::eval::run(a),
        Some(Command::Export(a)) => commands::export::run(a),
        Some(Command::Plot(a)) => commands::plot::run(a),
        Some(Command::Grads(a)) => commands::grads::run(a),
    }
}
