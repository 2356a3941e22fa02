//! The `ggpt-train` commands, one file each (binary-only code: progress bars, printing,
//! argument handling). The work itself is in the `ggpt_train` library.

pub mod default_run;
pub mod eval;
pub mod export;
pub mod grads;
pub mod plot;
pub mod prepare;
pub mod train;

use anyhow::{Context, Result, bail};
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

/// The weights file to fine-tune from (`--weights`: a checkpoint file, or a model folder holding
/// `model.safetensors`) and, when neither `--model-config` nor `--preset` is given, the
/// configuration stored next to the weights (`model_config.json`; `None` when there is none:
/// the caller's default preset applies).
pub fn resolve_init_weights(
    weights: &std::path::Path,
    model: &ModelArgs,
) -> Result<(std::path::PathBuf, Option<GgptConfig>)> {
    let m = model.normalized();
    let explicit = m.model_config.is_some() || m.preset_name().is_some();
    let file = if weights.is_dir() {
        // the model-folder contract (ggpt_model::model_dir): weights and configuration
        let spec = ggpt_model::model_dir::resolve_model(
            weights,
            m.model_config.as_deref(),
            m.preset_name(),
        )
        .with_context(|| format!("--weights {}", weights.display()))?;
        if !explicit {
            return Ok((spec.weights, Some(spec.config)));
        }
        spec.weights
    } else {
        weights.to_path_buf()
    };
    let beside = file.with_file_name(ggpt_model::model_dir::MODEL_CONFIG_FILE);
    let cfg = if !explicit && beside.is_file() {
        Some(
            GgptConfig::from_json_file(&beside)
                .with_context(|| format!("model configuration {}", beside.display()))?,
        )
    } else {
        None
    };
    Ok((file, cfg))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing
    use super::*;
    use ggpt_cli::ModelPreset;
    use ggpt_model::model_dir::{MODEL_CONFIG_FILE, MODEL_WEIGHTS_FILE, shipped_model_dir};

    #[test]
    fn fine_tuning_takes_a_model_folder_and_its_configuration() {
        let dir = shipped_model_dir().unwrap();
        let stored = GgptConfig::from_json_file(&dir.join(MODEL_CONFIG_FILE)).unwrap();
        let none = ModelArgs::default();
        // the folder: its weights file and its configuration
        let (file, cfg) = resolve_init_weights(&dir, &none).unwrap();
        assert_eq!(file, dir.join(MODEL_WEIGHTS_FILE));
        assert_eq!(cfg.as_ref(), Some(&stored));
        // the weights file: the configuration beside it
        let (file2, cfg2) = resolve_init_weights(&file, &none).unwrap();
        assert_eq!((file2, cfg2.as_ref()), (file.clone(), Some(&stored)));
        // an explicit preset wins (the caller resolves it)
        let preset = ModelArgs {
            preset: Some(ModelPreset::Tiny),
            ..ModelArgs::default()
        };
        let (file3, cfg3) = resolve_init_weights(&dir, &preset).unwrap();
        assert_eq!((file3, cfg3), (file, None));
        // a folder without weights names the missing file
        let empty = tempfile::tempdir().unwrap();
        let err = format!(
            "{:#}",
            resolve_init_weights(empty.path(), &none).unwrap_err()
        );
        assert!(err.contains(MODEL_WEIGHTS_FILE), "{err}");
    }
}
