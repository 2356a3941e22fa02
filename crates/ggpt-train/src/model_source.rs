//! A model from any of the forms the `ggpt-train` commands accept: a training run directory
//! (its newest checkpoint), a checkpoint directory (`state.json` + `model.bpk`), a model folder
//! (`model.safetensors` + `model_config.json` [+ `inference.json`]) or a weight file with a
//! configuration.

use std::path::{Path, PathBuf};

use burn::tensor::Device;
use ggpt_core::chunking::ChunkingSettings;
use ggpt_model::model_dir::{MODEL_WEIGHTS_FILE, load_model, resolve_model};
use ggpt_model::{Ggpt, GgptConfig};

use crate::chunkset::ChunkSet;
use crate::error::{Result, TrainError};
use crate::trainer::{list_checkpoints, load_checkpoint};

/// The checkpoint's or model folder's chunk-sampler settings and the file they come from (a
/// model folder's `inference.json`, or a checkpoint's chunk-set directory).
#[derive(Debug, Clone, PartialEq)]
pub struct TrainingChunking {
    /// Where the settings were read.
    pub path: PathBuf,
    /// The settings (`None`: the file has no chunk-sampler section).
    pub settings: Option<ChunkingSettings>,
}

/// A loaded model with its configuration.
#[derive(Debug)]
pub struct LoadedModel {
    /// The network (inference mode for weight files; a checkpoint's model as trained).
    pub model: Ggpt,
    /// Its configuration.
    pub config: GgptConfig,
    /// The chunk sampler it was trained with, when known.
    pub chunking: Option<TrainingChunking>,
    /// The checkpoint directory it came from, if any.
    pub checkpoint: Option<PathBuf>,
}

/// A checkpoint directory: `path` itself when it holds `state.json`, else the newest complete
/// checkpoint of the run directory `path`; `None` when `path` is neither (e.g. a model folder).
pub fn find_checkpoint(path: &Path) -> Result<Option<PathBuf>> {
    if path.join("state.json").is_file() {
        return Ok(Some(path.to_path_buf()));
    }
    if path.is_dir() && !path.join(MODEL_WEIGHTS_FILE).is_file() {
        return Ok(list_checkpoints(path)?.last().map(|(_, d)| d.clone()));
    }
    Ok(None)
}

/// Like [`find_checkpoint`], but a run directory without any checkpoint is an error naming it.
pub fn require_checkpoint(path: &Path) -> Result<PathBuf> {
    find_checkpoint(path)?.ok_or_else(|| {
        TrainError::Invalid(format!(
            "{}: neither a checkpoint directory (state.json) nor a run directory with checkpoints",
            path.display()
        ))
    })
}

/// Loads a model from `path` on `device`: a run or checkpoint directory (configuration from its
/// `state.json`, sampler settings from its chunk set's manifest), or a model folder / weight
/// file resolved by [`ggpt_model::model_dir::resolve_model`] with `model_config` or `preset`
/// (default: `model_config.json` next to the weights).
pub fn load_model_source(
    path: &Path,
    model_config: Option<&Path>,
    preset: Option<&str>,
    device: &Device,
) -> Result<LoadedModel> {
    if let Some(dir) = find_checkpoint(path)? {
        let (model, _, state) = load_checkpoint(&dir, device)?;
        let chunking = ChunkSet::open(&state.data)
            .ok()
            .map(|set| TrainingChunking {
                path: state.data.clone(),
                settings: crate::export::training_chunking(&set.manifest.provenance),
            });
        return Ok(LoadedModel {
            model,
            config: state.options.model,
            chunking,
            checkpoint: Some(dir),
        });
    }
    let spec = resolve_model(path, model_config, preset)?;
    let model = load_model(&spec, device)?;
    let chunking = spec.inference.map(|i| TrainingChunking {
        path: i.path,
        settings: i.settings.chunking,
    });
    Ok(LoadedModel {
        model,
        config: spec.config,
        chunking,
        checkpoint: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_folder_without_checkpoints_is_named() {
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(find_checkpoint(dir.path()).unwrap(), None);
        let e = require_checkpoint(dir.path()).unwrap_err().to_string();
        assert!(e.contains(&dir.path().display().to_string()), "{e}");
        let state = dir.path().join("ck");
        std::fs::create_dir_all(&state).unwrap();
        std::fs::write(state.join("state.json"), "{}").unwrap();
        assert_eq!(find_checkpoint(&state).unwrap(), Some(state.clone()));
    }
}
