//! Error type of the training crate.

use std::path::PathBuf;

/// Errors of chunk-set I/O, preparation, training and checkpointing.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// Operating-system I/O error on a file.
    #[error("{path}: {source}")]
    Io {
        /// File concerned.
        path: PathBuf,
        /// Underlying error.
        #[source]
        source: std::io::Error,
    },
    /// A chunk-set shard is corrupt, truncated or inconsistent with the manifest.
    #[error("chunk shard {path}: {message}")]
    Shard {
        /// The shard file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The manifest or another JSON file is malformed.
    #[error("{path}: {message}")]
    Format {
        /// File concerned.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// Invalid input or option.
    #[error("{0}")]
    Invalid(String),
    /// Error from the core crate (I/O of scenes, metrics).
    #[error(transparent)]
    Core(#[from] ggpt_core::CoreError),
    /// Error from the scene pipeline.
    #[error(transparent)]
    Scene(#[from] ggpt_scene::SceneError),
    /// Error from the model crate.
    #[error(transparent)]
    Model(#[from] ggpt_model::ModelError),
    /// Error from the synthetic generator.
    #[error(transparent)]
    Synth(#[from] ggpt_synth::SynthError),

    /// Evaluation against the ground truth failed.
    #[error("evaluation: {0}")]
    Eval(#[from] ggpt_eval::EvalError),
    /// Error from the SfM stage.
    #[error("SfM: {0}")]
    Sfm(String),
    /// Checkpoint read / write failure.
    #[error("checkpoint {path}: {message}")]
    Checkpoint {
        /// File or directory concerned.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}

/// Result alias of the crate.
pub type Result<T> = std::result::Result<T, TrainError>;

/// Shorthand for [`TrainError::Io`].
pub fn io_err(path: impl Into<PathBuf>) -> impl FnOnce(std::io::Error) -> TrainError {
    let path = path.into();
    move |source| TrainError::Io { path, source }
}
