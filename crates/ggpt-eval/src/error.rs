//! The error type of the evaluation library.

/// What can go wrong while evaluating.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// The scene or a prediction does not allow the evaluation (missing GT, wrong shape, ...).
    #[error("{0}")]
    Invalid(String),
    /// Reading an input failed (`what` names it, e.g. "prediction out/x.npy").
    #[error("{what}: {source}")]
    Input {
        /// What was being read.
        what: String,
        /// The cause.
        #[source]
        source: ggpt_core::CoreError,
    },
    /// A metric could not be computed (`what` names it).
    #[error("{what}: {source}")]
    Metric {
        /// Which metric.
        what: String,
        /// The cause.
        #[source]
        source: ggpt_core::CoreError,
    },
    /// Writing a report failed.
    #[error(transparent)]
    Core(#[from] ggpt_core::CoreError),
}

/// Result alias of the evaluation library.
pub type Result<T, E = EvalError> = std::result::Result<T, E>;

/// Returns early with [`EvalError::Invalid`] built by `format!`.
macro_rules! invalid {
    ($($arg:tt)*) => {
        return Err($crate::error::EvalError::Invalid(format!($($arg)*)))
    };
}
pub(crate) use invalid;
