//! Simulation regimes: which world, feed-forward error and matcher models a scene is drawn with.
//!
//! * [`Regime::Benchmark`] (default): calibrated against the paper's evaluation data
//!   (supplementary Table 5, ScanNet++ / ETH3D): rooms with large low-texture walls and floors,
//!   matchers whose certainty collapses on low texture, near occlusion boundaries, at grazing
//!   angles and under scale change, repeated-pattern false matches, a RoMa-like and a denser,
//!   noisier UFM-like matcher, and a feed-forward error that is mostly low-frequency and
//!   structured (VGGT-like). The SfM guidance covers 20-70 % of the pixels.
//! * [`Regime::Easy`]: the first regime (dense, clean matches, i.i.d.-dominated feed-forward
//!   error), kept bit-identical for the reproducibility of earlier numbers.
//!
//! `docs/synthetic.md` documents both and the measured distribution of the benchmark regime.

use crate::SynthError;

/// Simulation regime of a synthetic scene.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Regime {
    /// Realistic failure modes, calibrated to the paper's ranges (the default).
    #[default]
    Benchmark,
    /// The first, easy regime: dense, near-exact SfM guidance.
    Easy,
}

impl Regime {
    /// Both regimes, default first.
    pub const ALL: [Regime; 2] = [Regime::Benchmark, Regime::Easy];

    /// Parses `benchmark` or `easy` (the [`std::fmt::Display`] names).
    pub fn parse(s: &str) -> Result<Self, SynthError> {
        match s {
            "benchmark" => Ok(Regime::Benchmark),
            "easy" => Ok(Regime::Easy),
            other => Err(SynthError::Config(format!(
                "unknown regime {other:?} (benchmark, easy)"
            ))),
        }
    }

    /// The regime of a configuration written before regimes existed (`synth.json` without a
    /// `regime` field): [`Regime::Easy`].
    pub fn before_regimes() -> Self {
        Regime::Easy
    }
}

impl std::fmt::Display for Regime {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Regime::Benchmark => "benchmark",
            Regime::Easy => "easy",
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip() {
        for r in Regime::ALL {
            assert_eq!(Regime::parse(&r.to_string()).ok(), Some(r));
        }
        assert!(Regime::parse("hard").is_err());
        assert_eq!(Regime::default(), Regime::Benchmark);
    }
}
