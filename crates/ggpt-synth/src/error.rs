//! Error type of `ggpt-synth`.

/// Errors of the synthetic scene generator.
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    /// The configuration is invalid (names the parameter and the accepted range).
    #[error("invalid synthetic-scene config: {0}")]
    Config(String),
    /// The generated scene failed validation or a core operation failed.
    #[error(transparent)]
    Core(#[from] ggpt_core::CoreError),
}
