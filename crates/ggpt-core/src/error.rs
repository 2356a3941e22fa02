//! Error type of `ggpt-core`. Every variant names the file (when there is one) and the problem.

use std::path::PathBuf;

/// Errors of the core crate: I/O, malformed files, invalid scene content.
#[derive(Debug, thiserror::Error)]
pub enum CoreError {
    /// Operating-system I/O error on a file.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What the operating system said.
        #[source]
        source: std::io::Error,
    },
    /// A file is malformed: truncated, wrong header, wrong dtype or shape, bad value.
    /// `key` names the tensor / field / element when there is one (empty otherwise).
    #[error("{path}{}: {message}", if key.is_empty() { String::new() } else { format!(" [{key}]") })]
    Format {
        /// The file.
        path: PathBuf,
        /// The tensor / field / element, or empty.
        key: String,
        /// The problem.
        message: String,
    },
    /// A NaN / inf in an input array: `path` is the file (or the description of in-memory
    /// arrays), `key` the array, `index` the flat C-order index of the first bad value.
    #[error("{path} [{key}]: non-finite value {value} at flat index {index}")]
    NonFinite {
        /// The file or origin.
        path: PathBuf,
        /// The array.
        key: String,
        /// Flat index of the first non-finite value.
        index: usize,
        /// The value.
        value: f64,
    },
    /// Scene content is inconsistent or invalid (not tied to one file).
    #[error("invalid scene: {0}")]
    Invalid(String),
    /// A numeric procedure failed (degenerate input).
    #[error("numeric failure: {0}")]
    Numeric(String),
}

impl CoreError {
    /// Shorthand for [`CoreError::Format`].
    pub fn format(
        path: impl Into<PathBuf>,
        key: impl Into<String>,
        message: impl Into<String>,
    ) -> Self {
        CoreError::Format {
            path: path.into(),
            key: key.into(),
            message: message.into(),
        }
    }

    /// Shorthand for [`CoreError::Io`].
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        CoreError::Io {
            path: path.into(),
            source,
        }
    }
}

/// Result alias of `ggpt-core`.
pub type Result<T> = std::result::Result<T, CoreError>;
