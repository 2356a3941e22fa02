//! The correspondence tensor of `sfm.md` §2.1 (target-major `[t, s, k]` layout) and its diagonal
//! convention.
//!
//! Coordinates are ff pixels in the pixel-centre convention (top-left pixel centre = `(0, 0)`).

use ggpt_core::Dims;

use crate::error::{Result, SfmError};

/// Cycle error written for missing pairs (`sfm.md` §2.2) and for invalid matches (§4).
pub const MISSING_CYCLE_ERROR: f32 = 1e6;

/// Scores below this are invalid matches (`sfm.md` §4 step 1), compared in f32.
pub const INVALID_SCORE: f32 = 1e-5;

/// Dense correspondences of one matcher (or of the ensemble) for all ordered view pairs.
///
/// Layout (`sfm.md` §2.1), all flat, target-major:
/// * `matches[2 * ((t * N + s) * hw + k) + c]`: coordinate `c` (`0 = x`, `1 = y`, ff pixels) in
///   view `t` of pixel `k = y * w + x` of view `s`;
/// * `scores[(t * N + s) * hw + k]`: matcher confidence;
/// * `cycle[(t * N + s) * hw + k]`: forward-backward error (ff pixels, §3).
#[derive(Debug, Clone, PartialEq)]
pub struct Correspondences {
    /// Views and ff resolution.
    pub dims: Dims,
    /// `[N, N, hw, 2]` match locations (ff pixels).
    pub matches: Vec<f32>,
    /// `[N, N, hw]` scores.
    pub scores: Vec<f32>,
    /// `[N, N, hw]` cycle errors (ff pixels).
    pub cycle: Vec<f32>,
}

impl Correspondences {
    /// Flat index of entry `(t, s, k)` into `scores` / `cycle` (multiply by 2 for `matches`).
    #[inline]
    pub fn idx(&self, t: usize, s: usize, k: usize) -> usize {
        (t * self.dims.n + s) * self.dims.hw() + k
    }

    /// Number of `(t, s, k)` entries, `N^2 hw`.
    pub fn entries(&self) -> usize {
        self.dims.n * self.dims.n * self.dims.hw()
    }

    /// Checks the array lengths against `dims`.
    pub fn validate(&self) -> Result<()> {
        let e = self.entries();
        if self.matches.len() != 2 * e || self.scores.len() != e || self.cycle.len() != e {
            return Err(SfmError::Shape(format!(
                "correspondences: {} match values / {} scores / {} cycle errors, expected {} / {e} / {e} for N={} h={} w={}",
                self.matches.len(),
                self.scores.len(),
                self.cycle.len(),
                2 * e,
                self.dims.n,
                self.dims.h,
                self.dims.w
            )));
        }
        Ok(())
    }

    /// Applies the diagonal convention (`sfm.md` §2.1): for `t = s` the match is the pixel centre,
    /// the score 1 and the cycle error 0.
    pub fn apply_diagonal(&mut self) {
        let hw = self.dims.hw();
        let w = self.dims.w;
        for s in 0..self.dims.n {
            let base = self.idx(s, s, 0);
            for k in 0..hw {
                let i = base + k;
                if let (Some(m), Some(sc), Some(c)) = (
                    self.matches.get_mut(2 * i..2 * i + 2),
                    self.scores.get_mut(i),
                    self.cycle.get_mut(i),
                ) {
                    m[0] = (k % w) as f32;
                    m[1] = (k / w) as f32;
                    *sc = 1.0;
                    *c = 0.0;
                }
            }
        }
    }

    /// Replaces non-finite matches / scores / cycle errors by an invalid entry (match kept, score 0,
    /// cycle error [`MISSING_CYCLE_ERROR`]) so that they fail every threshold (documented fallback).
    pub fn sanitize(&mut self) {
        for i in 0..self.scores.len() {
            let bad_match = self
                .matches
                .get(2 * i..2 * i + 2)
                .is_some_and(|m| !m[0].is_finite() || !m[1].is_finite());
            let bad = bad_match
                || !self.scores[i].is_finite()
                || self.cycle.get(i).is_some_and(|c| c.is_nan());
            if bad {
                self.scores[i] = 0.0;
                if let Some(c) = self.cycle.get_mut(i) {
                    *c = MISSING_CYCLE_ERROR;
                }
                if bad_match && let Some(m) = self.matches.get_mut(2 * i..2 * i + 2) {
                    m[0] = -1.0e6;
                    m[1] = -1.0e6;
                }
            }
        }
    }

    /// Converts a source-major `[s, t, k]` array (as the official `match_dense` returns) to the
    /// target-major `[t, s, k]` layout; `c` values per entry (1 or 2).
    pub fn transpose_pairs<T: Copy>(src: &[T], n: usize, hw: usize, c: usize) -> Result<Vec<T>> {
        if src.len() != n * n * hw * c {
            return Err(SfmError::Shape(format!(
                "pair array: {} values, expected {}",
                src.len(),
                n * n * hw * c
            )));
        }
        let mut out = Vec::with_capacity(src.len());
        for t in 0..n {
            for s in 0..n {
                let b = (s * n + t) * hw * c;
                out.extend_from_slice(&src[b..b + hw * c]);
            }
        }
        Ok(out)
    }

    /// Per source view `s`: number of tracks with at least one valid off-diagonal match (score
    /// `>= 1e-5`, [`INVALID_SCORE`]).
    pub fn valid_matches_per_view(&self) -> Vec<usize> {
        let n = self.dims.n;
        let hw = self.dims.hw();
        let mut out = vec![0usize; n];
        for (s, o) in out.iter_mut().enumerate() {
            *o = (0..hw)
                .filter(|&k| {
                    (0..n).any(|t| t != s && self.scores[self.idx(t, s, k)] >= INVALID_SCORE)
                })
                .count();
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ggpt_core::MatchSet;

    fn dims() -> Dims {
        Dims { n: 2, h: 2, w: 3 }
    }

    #[test]
    fn diagonal_is_identity() {
        let d = dims();
        let e = 4 * 6;
        let mut c = Correspondences {
            dims: d,
            matches: vec![7.0; 2 * e],
            scores: vec![0.5; e],
            cycle: vec![3.0; e],
        };
        c.apply_diagonal();
        let i = c.idx(1, 1, 4);
        assert_eq!((c.matches[2 * i], c.matches[2 * i + 1]), (1.0, 1.0));
        assert_eq!(c.scores[i], 1.0);
        assert_eq!(c.cycle[i], 0.0);
        let j = c.idx(0, 1, 4);
        assert_eq!(c.scores[j], 0.5);
        assert_eq!(c.matches[2 * j], 7.0);
    }

    #[test]
    fn from_match_set_rejects_wrong_shape() {
        let set = MatchSet {
            matcher: "x".into(),
            pred_matches: vec![0.0; 10],
            pred_scores: vec![0.0; 5],
            pred_cycle_error: None,
            rank_scores: None,
        };
        let err = Correspondences::from_match_set(&set, dims()).unwrap_err();
        assert!(err.to_string().contains("expected 48 / 24"), "{err}");
    }

    #[test]
    fn nan_matches_become_invalid() {
        let d = dims();
        let e = 24;
        let mut m = vec![0.5f32; 2 * e];
        m[2 * 6] = f32::NAN; // (t=0, s=1, k=0)
        let set = MatchSet {
            matcher: "x".into(),
            pred_matches: m,
            pred_scores: vec![0.9; e],
            pred_cycle_error: Some(vec![0.1; e]),
            rank_scores: None,
        };
        let c = Correspondences::from_match_set(&set, d).unwrap();
        let i = c.idx(0, 1, 0);
        assert_eq!(c.scores[i], 0.0);
        assert_eq!(c.cycle[i], MISSING_CYCLE_ERROR);
        assert!(c.matches.iter().all(|v| v.is_finite()));
    }

    #[test]
    fn transpose_pairs_swaps_axes() {
        // n = 2, hw = 1, c = 1: src[s, t] = 10 s + t
        let src = [0, 1, 10, 11];
        let out = Correspondences::transpose_pairs(&src, 2, 1, 1).unwrap();
        assert_eq!(out, vec![0, 10, 1, 11]);
    }
}
