//! The readers under test, one [`Target`](crate::harness::Target) each, with deterministic
//! seeds built by the workspace's own writers.

pub mod core_formats;
pub mod model_formats;
pub mod train_formats;

use std::path::{Path, PathBuf};

use crate::harness::{SeedFile, Target};
use crate::{FuzzError, Result};

/// Every target, in report order.
pub fn all() -> Vec<Box<dyn Target>> {
    vec![
        Box::new(core_formats::Npy),
        Box::new(core_formats::Npz),
        Box::new(core_formats::Ply),
        Box::new(core_formats::Colmap { text: false }),
        Box::new(core_formats::Colmap { text: true }),
        Box::new(core_formats::SceneDir),
        Box::new(core_formats::OfficialBin),
        Box::new(model_formats::ChunkRecord),
        Box::new(model_formats::Weights::new(
            model_formats::WeightsFormat::Safetensors,
        )),
        Box::new(model_formats::Weights::new(
            model_formats::WeightsFormat::Pth,
        )),
        Box::new(model_formats::Weights::new(
            model_formats::WeightsFormat::Burnpack,
        )),
        Box::new(model_formats::ModelConfigJson),
        Box::new(model_formats::InferenceJson),
        Box::new(train_formats::ChunkSetDir),
        Box::new(train_formats::Shard),
        Box::new(train_formats::Checkpoint::new()),
    ]
}

/// The names of [`all`], in order (static, for the allocator's abort message).
pub const NAMES: &[&str] = &[
    "npy",
    "npz",
    "ply",
    "colmap-bin",
    "colmap-txt",
    "scene-dir",
    "official-bin",
    "chunk-record",
    "weights-safetensors",
    "weights-pth",
    "weights-burnpack",
    "model-config-json",
    "inference-json",
    "chunkset",
    "chunkset-shard",
    "train-checkpoint",
];

/// Every file under `dir` as a mutable seed file (relative paths, sorted).
pub fn seed_files_of(dir: &Path) -> Result<Vec<SeedFile>> {
    let mut out = Vec::new();
    let mut stack: Vec<PathBuf> = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let entries = std::fs::read_dir(&d).map_err(|e| FuzzError::Io {
            path: d.clone(),
            source: e,
        })?;
        for e in entries {
            let path = e
                .map_err(|e| FuzzError::Io {
                    path: d.clone(),
                    source: e,
                })?
                .path();
            if path.is_dir() {
                stack.push(path);
            } else {
                let bytes = std::fs::read(&path).map_err(|e| FuzzError::Io {
                    path: path.clone(),
                    source: e,
                })?;
                let rel = path.strip_prefix(dir).map_err(|_| FuzzError::Seed {
                    target: String::new(),
                    message: format!("{} outside {}", path.display(), dir.display()),
                })?;
                out.push(SeedFile::new(rel.to_path_buf(), bytes));
            }
        }
    }
    out.sort_by(|a, b| a.path.cmp(&b.path));
    Ok(out)
}

/// Runs `write(dir)` in a fresh temporary folder and returns what it wrote.
pub fn seed_from_writer(
    target: &str,
    write: impl FnOnce(&Path) -> std::result::Result<(), String>,
) -> Result<Vec<SeedFile>> {
    let tmp = tempfile::tempdir().map_err(|e| FuzzError::Io {
        path: std::env::temp_dir(),
        source: e,
    })?;
    write(tmp.path()).map_err(|message| FuzzError::Seed {
        target: target.to_string(),
        message,
    })?;
    seed_files_of(tmp.path())
}

/// A reader error as text (`Display` of the error and its sources).
pub fn err_text(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut src = e.source();
    while let Some(c) = src {
        s.push_str(": ");
        s.push_str(&c.to_string());
        src = c.source();
    }
    s
}
