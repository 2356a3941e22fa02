//! Error type of the scene pipeline (`pipeline.md` §13). Every variant names what is wrong and,
//! where there is one, the first bad index.

/// Errors of `ggpt-scene`.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// Arrays of inconsistent size, mismatched view counts, missing scene parts.
    #[error("invalid scene input: {0}")]
    Invalid(String),
    /// A NaN / inf value in an input array (`pipeline.md` §13). `index` is the flat index in the
    /// array named by `what` (`[N, h, w, 3]` arrays: `3 * p + axis`).
    #[error("{what}: non-finite value {value} at flat index {index}")]
    NonFinite {
        /// The array.
        what: String,
        /// Flat index of the value.
        index: usize,
        /// The value.
        value: f64,
    },
    /// The SfM stage produced no DLT point (`points_success` false); refinement is impossible.
    #[error(
        "SfM produced no DLT point: nothing to refine (use the allow-unrefined option to export the feed-forward points)"
    )]
    NoDltPoint,
    /// The chunk refiner (the network) failed or returned malformed output.
    #[error("chunk refiner: {0}")]
    Refiner(String),
    /// A numeric procedure failed (degenerate input).
    #[error("numeric failure: {0}")]
    Numeric(String),
    /// Error from `ggpt-core` (file I/O, formats).
    #[error(transparent)]
    Core(#[from] ggpt_core::CoreError),
    /// The caller's [`ggpt_core::Cancel`] token asked the refinement to stop (checked before
    /// every network forward).
    #[error("cancelled")]
    Cancelled,
}

/// Returns the first non-finite entry of `values` as a [`SceneError::NonFinite`].
pub fn check_finite(what: &str, values: &[f32]) -> Result<(), SceneError> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(index) => Err(SceneError::NonFinite {
            what: what.to_string(),
            index,
            value: values.get(index).copied().map_or(f64::NAN, f64::from),
        }),
        None => Ok(()),
    }
}

/// Checks that `len == want`, naming the array on failure.
pub fn check_len(what: &str, len: usize, want: usize) -> Result<(), SceneError> {
    if len == want {
        Ok(())
    } else {
        Err(SceneError::Invalid(format!(
            "{what}: {len} values, expected {want}"
        )))
    }
}
