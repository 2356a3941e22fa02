//! Ctrl-C (SIGINT) and SIGTERM as a stop flag, through the `ctrlc` crate (`termination`
//! feature): a long command checks the flag between steps and ends cleanly (a training run
//! writes its checkpoint first).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

/// A flag set by the first Ctrl-C or SIGTERM. A second signal while the flag is already set
/// exits at once with status 130 (the user insists).
///
/// Errors when a handler is already installed in this process.
pub fn stop_flag() -> anyhow::Result<Arc<AtomicBool>> {
    let flag = Arc::new(AtomicBool::new(false));
    let f = flag.clone();
    ctrlc::set_handler(move || {
        if f.swap(true, Ordering::SeqCst) {
            std::process::exit(130);
        }
        tracing::warn!("stop requested: finishing the current step (signal again to abort)");
    })
    .map_err(|e| anyhow::anyhow!("installing the Ctrl-C / SIGTERM handler: {e}"))?;
    Ok(flag)
}

/// [`stop_flag`] as a library stop request ([`ggpt_core::Cancel`]): the first Ctrl-C / SIGTERM
/// ends the run at its next check (between SfM steps, BA iterations, network forwards) with a
/// `cancelled` error; nothing is half-written.
pub fn stop_token() -> anyhow::Result<ggpt_core::Cancel> {
    Ok(ggpt_core::Cancel::from_flag(stop_flag()?))
}
