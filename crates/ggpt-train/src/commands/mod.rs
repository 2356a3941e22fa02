//! The `ggpt-train` commands, one file each (binary-only code: progress bars, printing,
//! argument handling). The work itself is in the `ggpt_train` library.

pub mod default_run;
pub mod eval;
pub mod export;
pub mod grads;
pub mod plot;
pub mod prepare;
pub mod train;

use anyhow::{Result, bail};
use ggpt_cli::ModelArgs;
use ggpt_model::GgptConfig;

/// The network configuration of `--model-config FILE` / `--preset NAME` (old: `--config`);
/// `default_preset` when neither is given (`None`: an error naming the flags).
pub fn model_config(model: &ModelArgs, default_preset: Option<&str>) -> Result<GgptConfig> {
    let m = model.normalized();
    Ok(
        match (&m.model_config, m.preset_name().or(default_preset)) {
            (Some(path), _) => GgptConfig::from_json_file(path)?,
            (None, Some(name)) => GgptConfig::preset(name)?,
            (None, None) => bail!("give --model-config FILE or --preset released|small|tiny"),
        },
    )
}
