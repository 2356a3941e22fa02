//! Per-pixel fusion of refined chunks (`pipeline.md` §8), streaming: chunks are added one batch
//! at a time, so only the accumulators (`O(P)`) stay in memory, never all chunk outputs.
//!
//! For every pixel `p` covered by `count[p] > 0` chunks (plain mean, the official rule):
//!
//! ```text
//! X_out[p] = (1/count[p]) Σ_k x_k[p]      conf[p] = (1/count[p]) Σ_k conf_k[p]
//! ```
//!
//! Uncovered pixels keep the aligned dense point `X_d[p]` with confidence 0. If no chunk was
//! fused at all, the output is the aligned `X_d` with its feed-forward confidence (the official
//! evaluation's behaviour) and a warning. Sums are accumulated in `f64` (**[project]**; the
//! official code uses `f32`), the result is rounded to `f32`.
//!
//! **Extension ([project], off by default)**: [`FusionMode::ConfidenceWeighted`] weights the
//! points by their confidence, `X_out = Σ c_k x_k / Σ c_k` (plain mean where `Σ c_k = 0`); the
//! output confidence stays the plain mean.

use crate::error::{SceneError, check_len};

/// How overlapping chunk predictions are combined.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FusionMode {
    /// Plain unweighted mean (official).
    #[default]
    Mean,
    /// Confidence-weighted mean of the points (documented extension).
    ConfidenceWeighted,
}

/// Streaming accumulator over `P` pixels.
#[derive(Debug, Clone)]
pub struct FusionAccumulator {
    mode: FusionMode,
    sum: Vec<f64>,
    weighted_sum: Vec<f64>,
    weight: Vec<f64>,
    conf_sum: Vec<f64>,
    count: Vec<u32>,
    chunks: usize,
}

/// Fused output (SfM frame, scene units; pixel order).
#[derive(Debug, Clone, PartialEq)]
pub struct Fused {
    /// `[P, 3]` refined points; aligned `X_d` where uncovered.
    pub points: Vec<f32>,
    /// `[P]` mean refined confidence; 0 where uncovered (ff confidence in the no-chunk fallback).
    pub conf: Vec<f32>,
    /// `[P]` `count > 0`.
    pub covered: Vec<bool>,
    /// `[P]` number of covering chunks.
    pub count: Vec<u32>,
    /// True when no chunk was fused and the output is the aligned feed-forward prediction.
    pub no_chunk_fallback: bool,
}

impl FusionAccumulator {
    /// Empty accumulator over `pixels` pixels.
    pub fn new(pixels: usize, mode: FusionMode) -> Self {
        let weighted = mode == FusionMode::ConfidenceWeighted;
        FusionAccumulator {
            mode,
            sum: vec![0.0; 3 * pixels],
            weighted_sum: if weighted {
                vec![0.0; 3 * pixels]
            } else {
                Vec::new()
            },
            weight: if weighted {
                vec![0.0; pixels]
            } else {
                Vec::new()
            },
            conf_sum: vec![0.0; pixels],
            count: vec![0; pixels],
            chunks: 0,
        }
    }

    /// Number of pixels `P`.
    pub fn pixels(&self) -> usize {
        self.count.len()
    }
    /// Chunks added so far.
    pub fn chunks(&self) -> usize {
        self.chunks
    }

    /// Adds one chunk: `pixels[i]` (scene pixel index) receives `points[i]` (SfM frame, already
    /// un-normalised) with confidence `conf[i]`. Errors on length mismatches, out-of-range pixels
    /// and non-finite values (nothing is added then).
    pub fn add_chunk(
        &mut self,
        pixels: &[u32],
        points: &[[f32; 3]],
        conf: &[f32],
    ) -> Result<(), SceneError> {
        check_len("fusion: chunk points", points.len(), pixels.len())?;
        check_len("fusion: chunk confidences", conf.len(), pixels.len())?;
        let total = self.pixels();
        if let Some(&p) = pixels.iter().find(|&&p| p as usize >= total) {
            return Err(SceneError::Invalid(format!(
                "fusion: pixel {p} out of range ({total} pixels)"
            )));
        }
        if let Some(i) = points.iter().position(|x| !x.iter().all(|v| v.is_finite())) {
            return Err(SceneError::NonFinite {
                what: "fusion: refined chunk points".into(),
                index: i,
                value: f64::NAN,
            });
        }
        if let Some(i) = conf.iter().position(|v| !v.is_finite()) {
            return Err(SceneError::NonFinite {
                what: "fusion: refined chunk confidence".into(),
                index: i,
                value: f64::from(conf[i]),
            });
        }
        for ((&p, x), &c) in pixels.iter().zip(points).zip(conf) {
            let p = p as usize;
            for (s, &v) in self.sum[3 * p..3 * p + 3].iter_mut().zip(x) {
                *s += f64::from(v);
            }
            self.conf_sum[p] += f64::from(c);
            self.count[p] += 1;
            if self.mode == FusionMode::ConfidenceWeighted {
                let w = f64::from(c.max(0.0));
                for (s, &v) in self.weighted_sum[3 * p..3 * p + 3].iter_mut().zip(x) {
                    *s += w * f64::from(v);
                }
                self.weight[p] += w;
            }
        }
        self.chunks += 1;
        Ok(())
    }

    /// Final fused arrays. `fallback_points` is the aligned `X_d` (`[P, 3]`, SfM frame) and
    /// `fallback_conf` its feed-forward confidence (`[P]`, used only when no chunk was added).
    pub fn finish(
        self,
        fallback_points: &[f32],
        fallback_conf: &[f32],
    ) -> Result<Fused, SceneError> {
        let n = self.pixels();
        check_len("fusion: fallback points", fallback_points.len(), 3 * n)?;
        check_len("fusion: fallback confidence", fallback_conf.len(), n)?;
        if self.chunks == 0 {
            tracing::warn!(
                "no chunk was refined: output = aligned feed-forward points with their feed-forward confidence"
            );
            return Ok(Fused {
                points: fallback_points.to_vec(),
                conf: fallback_conf.to_vec(),
                covered: vec![false; n],
                count: self.count,
                no_chunk_fallback: true,
            });
        }
        let mut points = fallback_points.to_vec();
        let mut conf = vec![0.0f32; n];
        for p in 0..n {
            let k = self.count[p];
            if k == 0 {
                continue;
            }
            let kf = f64::from(k);
            let w = self.weight.get(p).copied().unwrap_or(0.0);
            for a in 0..3 {
                let v = if self.mode == FusionMode::ConfidenceWeighted && w > 0.0 {
                    self.weighted_sum[3 * p + a] / w
                } else {
                    self.sum[3 * p + a] / kf
                };
                points[3 * p + a] = v as f32;
            }
            conf[p] = (self.conf_sum[p] / kf) as f32;
        }
        let covered = self.count.iter().map(|&c| c > 0).collect();
        Ok(Fused {
            points,
            conf,
            covered,
            count: self.count,
            no_chunk_fallback: false,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plain_mean_and_uncovered_fallback() {
        let fallback = [9.0, 9.0, 9.0, 8.0, 8.0, 8.0, 7.0, 7.0, 7.0];
        let ff_conf = [5.0, 5.0, 5.0];
        let mut acc = FusionAccumulator::new(3, FusionMode::Mean);
        acc.add_chunk(&[0, 1], &[[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]], &[1.0, 10.0])
            .unwrap();
        acc.add_chunk(&[1], &[[2.0, 4.0, 6.0]], &[20.0]).unwrap();
        let f = acc.finish(&fallback, &ff_conf).unwrap();
        assert_eq!(f.points, vec![1.0, 2.0, 3.0, 1.0, 2.0, 3.0, 7.0, 7.0, 7.0]);
        assert_eq!(f.conf, vec![1.0, 15.0, 0.0]);
        assert_eq!(f.covered, vec![true, true, false]);
        assert_eq!(f.count, vec![1, 2, 0]);
        assert!(!f.no_chunk_fallback);
    }

    #[test]
    fn confidence_weighted_extension() {
        let fallback = [0.0f32; 6];
        let mut acc = FusionAccumulator::new(2, FusionMode::ConfidenceWeighted);
        acc.add_chunk(&[0, 1], &[[0.0; 3], [1.0; 3]], &[1.0, 0.0])
            .unwrap();
        acc.add_chunk(&[0, 1], &[[4.0; 3], [3.0; 3]], &[3.0, 0.0])
            .unwrap();
        let f = acc.finish(&fallback, &[0.0; 2]).unwrap();
        assert_eq!(&f.points[..3], &[3.0; 3]); // (1*0 + 3*4) / 4
        assert_eq!(&f.points[3..], &[2.0; 3]); // zero weights -> plain mean
        assert_eq!(f.conf, vec![2.0, 0.0]);
    }

    #[test]
    fn no_chunk_fallback_and_errors() {
        let fallback = [1.0f32, 2.0, 3.0];
        let acc = FusionAccumulator::new(1, FusionMode::Mean);
        let f = acc.finish(&fallback, &[4.0]).unwrap();
        assert!(f.no_chunk_fallback);
        assert_eq!(f.conf, vec![4.0]);
        assert_eq!(f.covered, vec![false]);
        let mut acc = FusionAccumulator::new(1, FusionMode::Mean);
        assert!(acc.add_chunk(&[1], &[[0.0; 3]], &[1.0]).is_err());
        assert!(
            acc.add_chunk(&[0], &[[f32::NAN, 0.0, 0.0]], &[1.0])
                .is_err()
        );
        assert!(acc.add_chunk(&[0], &[[0.0; 3]], &[]).is_err());
        assert_eq!(acc.chunks(), 0);
    }
}
