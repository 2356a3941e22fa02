//! Cycle-consistency (forward-backward) error (`sfm.md` §3).
//!
//! `e_{A->B}(p) = || sample(B->A, A->B(p)) - p ||`, `p` the pixel centre of `A` (ff pixels),
//! `sample` = bilinear interpolation with zero padding (PyTorch `grid_sample`, `align_corners =
//! false`, `padding = zeros`). Computed in f32 through the official normalised coordinates.

use ggpt_core::{Dims, MatchSet};
use rayon::prelude::*;

use crate::error::{Result, SfmError};

use crate::matches::Correspondences;

/// The constructor of [`Correspondences`] from stored matches lives beside the cycle error it
/// computes when the file has none.
impl Correspondences {
    /// Builds correspondences from a stored [`MatchSet`] (`formats.md` §5.2 layout, ff pixels):
    /// checks the lengths, computes the cycle error (`sfm.md` §3) when it is absent and applies the
    /// diagonal convention. Non-finite match coordinates get score 0 and the missing-pair cycle error.
    pub fn from_match_set(set: &MatchSet, dims: Dims) -> Result<Self> {
        let e = dims.n * dims.n * dims.hw();
        if set.pred_matches.len() != 2 * e || set.pred_scores.len() != e {
            return Err(SfmError::Shape(format!(
                "matcher {}: {} match values / {} scores, expected {} / {e} for the images' N={} h={} w={}",
                set.matcher,
                set.pred_matches.len(),
                set.pred_scores.len(),
                2 * e,
                dims.n,
                dims.h,
                dims.w
            )));
        }
        if let Some(c) = &set.pred_cycle_error
            && c.len() != e
        {
            return Err(SfmError::Shape(format!(
                "matcher {}: {} cycle errors, expected {e}",
                set.matcher,
                c.len()
            )));
        }
        let mut corr = Correspondences {
            dims,
            matches: set.pred_matches.clone(),
            scores: set.pred_scores.clone(),
            cycle: vec![0.0; e],
        };
        corr.apply_diagonal();
        match &set.pred_cycle_error {
            Some(c) => corr.cycle.copy_from_slice(c),
            None => compute_cycle_errors(&mut corr)?,
        }
        corr.sanitize();
        corr.apply_diagonal();
        Ok(corr)
    }
}

/// Bilinear sample with zero padding of a 2-channel `h x w` image `img` (`[h*w, 2]`, interleaved)
/// at ff-pixel location `(x, y)` (pixel-centre convention), in f32, through the normalised
/// coordinates `x_n = 2x / w - 1 + 1/w` and `grid_sample`'s un-normalisation `((x_n + 1) w - 1) / 2`.
#[inline]
pub fn sample_zero_padded(img: &[f32], h: usize, w: usize, x: f32, y: f32) -> [f32; 2] {
    let (wf, hf) = (w as f32, h as f32);
    let xn = 2.0 * x / wf - 1.0 + 1.0 / wf;
    let yn = 2.0 * y / hf - 1.0 + 1.0 / hf;
    let ix = ((xn + 1.0) * wf - 1.0) / 2.0;
    let iy = ((yn + 1.0) * hf - 1.0) / 2.0;
    if !ix.is_finite() || !iy.is_finite() {
        return [0.0, 0.0];
    }
    let x0 = ix.floor();
    let y0 = iy.floor();
    let x1 = x0 + 1.0;
    let y1 = y0 + 1.0;
    // grid_sample's weights: nw = (x1 - ix)(y1 - iy), ne = (ix - x0)(y1 - iy), sw = (x1 - ix)(iy - y0), se = (ix - x0)(iy - y0)
    let nw = (x1 - ix) * (y1 - iy);
    let ne = (ix - x0) * (y1 - iy);
    let sw = (x1 - ix) * (iy - y0);
    let se = (ix - x0) * (iy - y0);
    let get = |xx: f32, yy: f32| -> Option<[f32; 2]> {
        if xx >= 0.0 && yy >= 0.0 && xx < wf && yy < hf {
            let i = yy as usize * w + xx as usize;
            img.get(2 * i..2 * i + 2).map(|v| [v[0], v[1]])
        } else {
            None
        }
    };
    let mut out = [0.0f32; 2];
    for (cx, cy, wt) in [(x0, y0, nw), (x1, y0, ne), (x0, y1, sw), (x1, y1, se)] {
        if let Some(v) = get(cx, cy) {
            out[0] += v[0] * wt;
            out[1] += v[1] * wt;
        }
    }
    out
}

/// Cycle error of every pixel of `A` (`[h*w]`, ff pixels) given the warps `ab` (`A->B`, `[h*w, 2]`
/// locations in `B` of the pixels of `A`) and `ba` (`B->A`, `[h*w, 2]`).
pub fn cycle_error_pair(ab: &[f32], ba: &[f32], h: usize, w: usize) -> Result<Vec<f32>> {
    let hw = h * w;
    if ab.len() != 2 * hw || ba.len() != 2 * hw {
        return Err(SfmError::Shape(format!(
            "cycle error: warps of {} / {} values for {h}x{w}",
            ab.len(),
            ba.len()
        )));
    }
    Ok((0..hw)
        .map(|k| {
            let p = [(k % w) as f32, (k / w) as f32];
            let q = sample_zero_padded(ba, h, w, ab[2 * k], ab[2 * k + 1]);
            let dx = q[0] - p[0];
            let dy = q[1] - p[1];
            (dx * dx + dy * dy).sqrt()
        })
        .collect())
}

/// Fills `corr.cycle[t, s, k] = e_{s->t}(k)` for every ordered pair `s != t` (`A = s`, `B = t`)
/// from `corr.matches`; the diagonal gets 0. Runs the pairs in parallel.
pub fn compute_cycle_errors(corr: &mut Correspondences) -> Result<()> {
    corr.validate()?;
    let n = corr.dims.n;
    let (h, w) = (corr.dims.h, corr.dims.w);
    let hw = h * w;
    let matches = &corr.matches;
    let pairs: Vec<(usize, usize)> = (0..n).flat_map(|t| (0..n).map(move |s| (t, s))).collect();
    let errs: Vec<Result<Vec<f32>>> = pairs
        .par_iter()
        .map(|&(t, s)| {
            if t == s {
                return Ok(vec![0.0; hw]);
            }
            let ab_start = 2 * ((t * n + s) * hw);
            let ba_start = 2 * ((s * n + t) * hw);
            cycle_error_pair(
                &matches[ab_start..ab_start + 2 * hw],
                &matches[ba_start..ba_start + 2 * hw],
                h,
                w,
            )
        })
        .collect();
    for (i, e) in errs.into_iter().enumerate() {
        let e = e?;
        corr.cycle[i * hw..(i + 1) * hw].copy_from_slice(&e);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Test vector of `sfm.md` §3 (values as printed in the spec).
    #[test]
    #[allow(clippy::approx_constant)]
    fn spec_test_vector() {
        let (h, w) = (3, 4);
        let mut ab = Vec::new();
        let mut ba = Vec::new();
        for k in 0..h * w {
            let (x, y) = ((k % w) as f32, (k / w) as f32);
            ab.extend([x + 0.5, y + 0.25]);
            ba.extend([x - 0.5, y]);
        }
        let e = cycle_error_pair(&ab, &ba, h, w).unwrap();
        let want = [
            0.25, 0.25, 0.25, 1.754459, //
            0.25, 0.25, 0.25, 1.789728, //
            0.5, 0.559017, 0.707107, 2.411723,
        ];
        for (k, (a, b)) in e.iter().zip(want).enumerate() {
            assert!((a - b).abs() < 2e-6, "pixel {k}: {a} vs {b}");
        }
        // the worked example: (3, 0) samples (1.25, 0.125)
        let q = sample_zero_padded(&ba, h, w, 3.5, 0.25);
        assert!(
            (q[0] - 1.25).abs() < 1e-6 && (q[1] - 0.125).abs() < 1e-6,
            "{q:?}"
        );
    }

    #[test]
    fn far_outside_samples_zero() {
        let img = vec![5.0f32; 2 * 6];
        assert_eq!(sample_zero_padded(&img, 2, 3, -5.0, 1.0), [0.0, 0.0]);
        assert_eq!(sample_zero_padded(&img, 2, 3, f32::NAN, 1.0), [0.0, 0.0]);
        assert_eq!(sample_zero_padded(&img, 2, 3, 1.0, 1.0), [5.0, 5.0]);
    }
}
