//! Error type of the network crate.

use std::path::PathBuf;

/// Errors of configuration parsing, weight loading and forward preparation.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    /// A configuration file could not be read or parsed.
    #[error("model config {path}: {message}")]
    Config {
        /// File (or `<preset>` / `<json>`) the configuration came from.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// A chunk-record file (network inputs, `formats.md` chunk records) could not be read or is
    /// malformed.
    #[error("chunk input {path}: {message}")]
    ChunkInput {
        /// Chunk-record file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// A file of a model folder is missing (`what` says which, and how to supply it).
    #[error("{what} not found: {path}")]
    Missing {
        /// What is missing.
        what: String,
        /// Where it was looked for.
        path: PathBuf,
    },
    /// A model's `inference.json` is unreadable or invalid.
    #[error("model inference settings {path}: {message}")]
    Settings {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// A checkpoint could not be read.
    #[error("checkpoint {path}: {message}")]
    CheckpointRead {
        /// Checkpoint file.
        path: PathBuf,
        /// Reader error.
        message: String,
    },
    /// A checkpoint does not match the model (strict loading, network.md §12.3).
    #[error(
        "checkpoint {path} does not match the model: {} missing, {} unused, {} mis-shaped/invalid\n{details}",
        missing.len(), unused.len(), invalid.len()
    )]
    CheckpointMismatch {
        /// Checkpoint file.
        path: PathBuf,
        /// Model parameters without a tensor in the file (official key name where known).
        missing: Vec<String>,
        /// File tensors that no model parameter uses.
        unused: Vec<String>,
        /// Tensors with the wrong shape or dtype, or that failed to convert.
        invalid: Vec<String>,
        /// Human-readable listing of all of the above.
        details: String,
    },
    /// A checkpoint could not be written.
    #[error("writing checkpoint {path}: {message}")]
    CheckpointWrite {
        /// Destination file.
        path: PathBuf,
        /// Writer error.
        message: String,
    },
    /// The batch plan is inconsistent with the model or with itself.
    #[error("batch plan: {0}")]
    Plan(String),
    /// Planning (token encoding, serialization, tables) failed.
    #[error("planning failed: {0}")]
    Planning(String),
    /// Reading a tensor back from the device failed.
    #[error("reading tensor {name} from the device: {message}")]
    Readback {
        /// Tensor name.
        name: String,
        /// Backend message.
        message: String,
    },
    /// An unknown device name.
    #[error(
        "unknown or unavailable device '{0}' (expected cpu, ndarray, flex, wgpu[:N] or cuda[:N])"
    )]
    Device(String),
    /// A known backend that this binary was built without.
    #[error(
        "device '{device}': this binary was built without the `{feature}` backend (rebuild with `--features {feature}`, docs/performance.md)"
    )]
    NotCompiled {
        /// The device asked for.
        device: String,
        /// The cargo feature that adds the backend.
        feature: &'static str,
    },
    /// The CPU thread pool could not be sized (it was already initialised).
    #[error("CPU thread pool: {0}")]
    Threads(String),
}

/// Result alias of this crate.
pub type Result<T, E = ModelError> = std::result::Result<T, E>;
