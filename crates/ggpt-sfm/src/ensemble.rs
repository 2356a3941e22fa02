//! Multi-matcher ensembling (`sfm.md` §4): per `(t, s, k)` the matcher with the smallest cycle
//! error wins, after invalid matches (score `< 1e-5`) had their cycle error replaced by `1e6`.

use crate::error::{Result, SfmError};
use crate::matches::{Correspondences, INVALID_SCORE, MISSING_CYCLE_ERROR};

/// Marks invalid matches: cycle error := `1e6` where score `< 1e-5` (f32, strict).
/// Applied for every matcher, also when there is only one ([project], identical masks).
pub fn mark_invalid(corr: &mut Correspondences) {
    for (c, s) in corr.cycle.iter_mut().zip(&corr.scores) {
        if *s < INVALID_SCORE {
            *c = MISSING_CYCLE_ERROR;
        }
    }
}

/// Ensembles `sets` (all with the same dims, listed in config order). Returns the ensembled
/// correspondences and the winning matcher index per `(t, s, k)` entry (target-major).
/// Ties go to the matcher listed first. Invalid matches of every input are marked first.
pub fn ensemble(sets: &[Correspondences]) -> Result<(Correspondences, Vec<u8>)> {
    let first = sets
        .first()
        .ok_or_else(|| SfmError::Invalid("ensemble: no matcher given".into()))?;
    if sets.len() > u8::MAX as usize {
        return Err(SfmError::Invalid(format!(
            "ensemble: {} matchers (at most 255)",
            sets.len()
        )));
    }
    for (i, s) in sets.iter().enumerate() {
        s.validate()?;
        if s.dims != first.dims {
            return Err(SfmError::Shape(format!(
                "ensemble: matcher {i} has dims {:?}, matcher 0 {:?}",
                s.dims, first.dims
            )));
        }
    }
    let mut marked: Vec<Correspondences> = sets.to_vec();
    for m in &mut marked {
        mark_invalid(m);
    }
    let e = first.entries();
    let mut out = marked[0].clone();
    let mut sel = vec![0u8; e];
    for (mi, m) in marked.iter().enumerate().skip(1) {
        for (i, s) in sel.iter_mut().enumerate().take(e) {
            if m.cycle[i] < out.cycle[i] {
                out.cycle[i] = m.cycle[i];
                out.scores[i] = m.scores[i];
                out.matches[2 * i] = m.matches[2 * i];
                out.matches[2 * i + 1] = m.matches[2 * i + 1];
                *s = mi as u8;
            }
        }
    }
    Ok((out, sel))
}

#[cfg(test)]
mod tests {
    use super::*;
    use ggpt_core::Dims;

    fn set(score: f32, cycle: f32, x: f32) -> Correspondences {
        let dims = Dims { n: 1, h: 1, w: 1 };
        Correspondences {
            dims,
            matches: vec![x, 0.0],
            scores: vec![score],
            cycle: vec![cycle],
        }
    }

    #[test]
    fn smallest_cycle_wins_ties_first() {
        let (o, s) = ensemble(&[set(0.5, 1.0, 1.0), set(0.6, 0.5, 2.0)]).unwrap();
        assert_eq!(
            (o.scores[0], o.cycle[0], o.matches[0], s[0]),
            (0.6, 0.5, 2.0, 1)
        );
        let (o, s) = ensemble(&[set(0.5, 1.0, 1.0), set(0.6, 1.0, 2.0)]).unwrap();
        assert_eq!((o.matches[0], s[0]), (1.0, 0));
    }

    #[test]
    fn invalid_scores_lose_and_keep_1e6() {
        let (o, s) = ensemble(&[set(9e-6, 0.1, 1.0), set(0.2, 3.0, 2.0)]).unwrap();
        assert_eq!((o.cycle[0], s[0]), (3.0, 1));
        let (o, s) = ensemble(&[set(0.0, 0.1, 1.0), set(0.0, 0.0, 2.0)]).unwrap();
        assert_eq!((o.cycle[0], s[0]), (1e6, 0));
        // exactly 1e-5 (f32) is valid
        let (o, _) = ensemble(&[set(1e-5, 0.1, 1.0)]).unwrap();
        assert_eq!(o.cycle[0], 0.1);
    }

    #[test]
    fn rejects_empty_and_mismatched() {
        assert!(ensemble(&[]).is_err());
        let mut b = set(0.5, 1.0, 1.0);
        b.dims = Dims { n: 1, h: 1, w: 2 };
        b.matches = vec![0.0; 4];
        b.scores = vec![0.0; 2];
        b.cycle = vec![0.0; 2];
        assert!(ensemble(&[set(0.5, 1.0, 1.0), b]).is_err());
    }
}
