//! Error type of the `ggpt-infer` library.

use std::path::PathBuf;

/// Errors of whole-scene inference. Every variant names the file or stage and the problem.
#[derive(Debug, thiserror::Error)]
pub enum InferError {
    /// Invalid input or option.
    #[error("invalid input: {0}")]
    Invalid(String),
    /// File I/O or format error from `ggpt-core`.
    #[error(transparent)]
    Core(#[from] ggpt_core::CoreError),
    /// Scene pipeline error (alignment, chunking, fusion, export).
    #[error(transparent)]
    Scene(#[from] ggpt_scene::SceneError),
    /// SfM stage error.
    #[error("SfM stage: {0}")]
    Sfm(#[from] ggpt_sfm::SfmError),
    /// Network error (configuration, checkpoint, planning).
    #[error(transparent)]
    Model(#[from] ggpt_model::ModelError),

    /// Evaluation against the ground truth failed.
    #[error("evaluation: {0}")]
    Eval(#[from] ggpt_eval::EvalError),
    /// Synthetic scene generation error.
    #[error("synthetic scene: {0}")]
    Synth(#[from] ggpt_synth::SynthError),
    /// Writing an output file failed.
    #[error("writing {path}: {message}")]
    Write {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
}

/// Result alias of this crate.
pub type Result<T> = std::result::Result<T, InferError>;
