//! Resolving and loading the network: weights file, model configuration, device.

use std::path::{Path, PathBuf};

use burn::tensor::Device;
use ggpt_model::weights::load_checkpoint;
use ggpt_model::{Ggpt, GgptConfig};

use crate::{InferError, Result};

/// The shipped model folder (`models/ggpt-synth-small/` of the repository): `model.safetensors`
/// (official key names) and `model_config.json` (official model-config JSON).
pub const SHIPPED_MODEL_DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../models/ggpt-synth-small/");
/// Weights file name inside a model folder.
pub const MODEL_WEIGHTS_FILE: &str = "model.safetensors";
/// Model-configuration file name inside a model folder (next to the weights).
pub const MODEL_CONFIG_FILE: &str = "model_config.json";
/// Other weight file names accepted inside a model folder, after [`MODEL_WEIGHTS_FILE`].
const OTHER_WEIGHT_FILES: [&str; 3] = ["model.pth", "model.bpk", "model.step228000.pth"];

/// Where the model configuration came from.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ConfigOrigin {
    /// A JSON file (`--model-config`, or `model_config.json` next to the weights).
    File(PathBuf),
    /// A built-in preset (`--preset`).
    Preset(String),
}

/// A resolved model: weights file and configuration.
#[derive(Debug, Clone)]
pub struct ModelSpec {
    /// Weights file (`.safetensors` / `.pth` official keys, or `.bpk`).
    pub weights: PathBuf,
    /// Network configuration.
    pub config: GgptConfig,
    /// Where the configuration came from.
    pub origin: ConfigOrigin,
}

/// Resolves `weights` (a file, or a model folder holding `model.safetensors`) and the
/// configuration: `model_config` file, else `preset`, else `model_config.json` next to the
/// weights. Missing files give [`InferError::Missing`] naming the path.
pub fn resolve_model(weights: &Path, model_config: Option<&Path>, preset: Option<&str>) -> Result<ModelSpec> {
    let weights = if weights.is_dir() {
        std::iter::once(MODEL_WEIGHTS_FILE)
            .chain(OTHER_WEIGHT_FILES)
            .map(|f| weights.join(f))
            .find(|p| p.is_file())
            .ok_or_else(|| InferError::Missing {
                what: format!("weights ({MODEL_WEIGHTS_FILE} in the model folder)"),
                path: weights.join(MODEL_WEIGHTS_FILE),
            })?
    } else if weights.is_file() {
        weights.to_path_buf()
    } else {
        return Err(InferError::Missing { what: "weights".into(), path: weights.to_path_buf() });
    };
    let (config, origin) = match (model_config, preset) {
        (Some(path), _) => {
            if !path.is_file() {
                return Err(InferError::Missing { what: "model configuration".into(), path: path.to_path_buf() });
            }
            (GgptConfig::from_json_file(path)?, ConfigOrigin::File(path.to_path_buf()))
        }
        (None, Some(name)) => (GgptConfig::preset(name)?, ConfigOrigin::Preset(name.to_string())),
        (None, None) => {
            let path = weights.with_file_name(MODEL_CONFIG_FILE);
            if !path.is_file() {
                return Err(InferError::Missing {
                    what: format!("model configuration (give --model-config FILE or --preset released|small|tiny, or put {MODEL_CONFIG_FILE} next to the weights)"),
                    path,
                });
            }
            (GgptConfig::from_json_file(&path)?, ConfigOrigin::File(path))
        }
    };
    Ok(ModelSpec { weights, config, origin })
}

/// Builds the network on `device` and loads the weights strictly.
pub fn load_model(spec: &ModelSpec, device: &Device) -> Result<Ggpt> {
    Ok(load_checkpoint(Ggpt::new(&spec.config, device), &spec.weights)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resolves_folder_config_and_reports_missing_files() {
        let dir = tempfile::tempdir().unwrap();
        let e = resolve_model(&dir.path().join("nope.safetensors"), None, Some("tiny")).unwrap_err().to_string();
        assert!(e.contains("weights not found") && e.contains("nope.safetensors"), "{e}");
        let e = resolve_model(dir.path(), None, Some("tiny")).unwrap_err().to_string();
        assert!(e.contains("model.safetensors"), "{e}");
        let w = dir.path().join(MODEL_WEIGHTS_FILE);
        std::fs::write(&w, b"x").unwrap();
        let spec = resolve_model(dir.path(), None, Some("tiny")).unwrap();
        assert_eq!(spec.weights, w);
        assert_eq!(spec.origin, ConfigOrigin::Preset("tiny".into()));
        let e = resolve_model(dir.path(), None, None).unwrap_err().to_string();
        assert!(e.contains("model_config.json") && e.contains("--model-config"), "{e}");
        let e = resolve_model(&w, Some(&dir.path().join("c.json")), None).unwrap_err().to_string();
        assert!(e.contains("model configuration not found") && e.contains("c.json"), "{e}");
        assert!(resolve_model(&w, None, Some("huge")).is_err());
    }
}
