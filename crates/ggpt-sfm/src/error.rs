//! Error type of `ggpt-sfm`. Every variant names what is wrong and, where there is one, the file
//! and the tensor key.

use std::path::PathBuf;

/// Errors of the SfM stage.
#[derive(Debug, thiserror::Error)]
pub enum SfmError {
    /// Array sizes do not agree with each other or with the scene dimensions.
    #[error("shape mismatch: {0}")]
    Shape(String),
    /// Invalid input values (NaN cameras, all-zero scores, bad thresholds, ...).
    #[error("invalid input: {0}")]
    Invalid(String),
    /// A numeric procedure failed (singular system, degenerate geometry).
    #[error("numeric failure: {0}")]
    Numeric(String),
    /// A file is malformed or misses a tensor. `key` names the tensor (empty when none).
    #[error("{path}{}: {message}", if key.is_empty() { String::new() } else { format!(" [{key}]") })]
    Format {
        /// The file.
        path: PathBuf,
        /// The tensor / field.
        key: String,
        /// What is wrong.
        message: String,
    },
    /// Operating-system I/O error on a file.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// Error from `ggpt-core` (file formats, scene validation).
    #[error(transparent)]
    Core(#[from] ggpt_core::CoreError),
    /// The caller's [`ggpt_core::Cancel`] token asked the stage to stop (checked between SfM
    /// steps and between BA iterations).
    #[error("cancelled")]
    Cancelled,
}

impl SfmError {
    /// Shorthand for [`SfmError::Format`].
    pub fn format(
        path: impl Into<PathBuf>,
        key: impl Into<String>,
        message: impl Into<String>,
    ) -> Self {
        SfmError::Format {
            path: path.into(),
            key: key.into(),
            message: message.into(),
        }
    }
}

/// Result alias of `ggpt-sfm`.
pub type Result<T> = std::result::Result<T, SfmError>;
