//! Epipolar filter of the DLT correspondences (`sfm.md` §8), with the BA cameras.
//!
//! For source view `i` and target view `j != i`: `R_rel = R_j R_i^T`, `t_rel = t_j - R_rel t_i`,
//! `E = [t_rel]x R_rel`, `F = K_j^-T E K_i^-1`; a match `q` of pixel `p` is kept when both
//! point-to-epipolar-line distances (ff pixels) are below the threshold. Geometry in f64; the
//! distances are compared in f32 against the f32-rounded threshold, like the official code.

use ggpt_core::Cameras;
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use crate::error::{Result, SfmError};
use crate::matches::Correspondences;

/// Added to the line-normal norm in the distance denominator (`sfm.md` §8).
pub const EPIPOLAR_EPS: f64 = 1e-10;

/// The fundamental matrix mapping pixels of view `i` (ff pixels, pixel-centre convention) to
/// epipolar lines in view `j`: `q~^T F p~ = 0`. Cameras are `cam_from_world` (OpenCV).
pub fn fundamental(cams: &Cameras, i: usize, j: usize) -> Result<Matrix3<f64>> {
    if i >= cams.len()
        || j >= cams.len()
        || i >= cams.intrinsics.len()
        || j >= cams.intrinsics.len()
    {
        return Err(SfmError::Shape(format!(
            "fundamental: views {i}, {j} of {} cameras",
            cams.len()
        )));
    }
    let (ri, ti) = (cams.rotation(i), cams.translation(i));
    let (rj, tj) = (cams.rotation(j), cams.translation(j));
    let r_rel = rj * ri.transpose();
    let t_rel = tj - r_rel * ti;
    let e = t_rel.cross_matrix() * r_rel;
    let ki_inv = cams.intrinsics[i]
        .try_inverse()
        .ok_or_else(|| SfmError::Numeric(format!("intrinsics of view {i} are singular")))?;
    let kj_inv = cams.intrinsics[j]
        .try_inverse()
        .ok_or_else(|| SfmError::Numeric(format!("intrinsics of view {j} are singular")))?;
    Ok(kj_inv.transpose() * e * ki_inv)
}

/// Distances `(d_a, d_b)` (ff pixels) of one correspondence `p -> q` under `f`:
/// `d_a` = distance of `q` to the line `F p~` in view `j`, `d_b` = distance of `p` to `F^T q~`.
#[inline]
pub fn distances(f: &Matrix3<f64>, p: [f64; 2], q: [f64; 2]) -> (f64, f64) {
    let ph = Vector3::new(p[0], p[1], 1.0);
    let qh = Vector3::new(q[0], q[1], 1.0);
    let l = f * ph;
    let lp = f.transpose() * qh;
    let da = l.dot(&qh).abs() / ((l[0] * l[0] + l[1] * l[1]).sqrt() + EPIPOLAR_EPS);
    let db = lp.dot(&ph).abs() / ((lp[0] * lp[0] + lp[1] * lp[1]).sqrt() + EPIPOLAR_EPS);
    (da, db)
}

/// Distances of every pixel `k` of source view `i` to its match in view `j`: `[hw]` pairs.
pub fn pair_distances(
    corr: &Correspondences,
    cams: &Cameras,
    i: usize,
    j: usize,
) -> Result<Vec<(f64, f64)>> {
    corr.validate()?;
    if i >= corr.dims.n || j >= corr.dims.n {
        return Err(SfmError::Shape(format!(
            "epipolar: views {i}, {j} of {} views",
            corr.dims.n
        )));
    }
    let f = fundamental(cams, i, j)?;
    let w = corr.dims.w;
    let base = corr.idx(j, i, 0);
    Ok((0..corr.dims.hw())
        .map(|k| {
            let m = 2 * (base + k);
            distances(
                &f,
                [(k % w) as f64, (k / w) as f64],
                [corr.matches[m] as f64, corr.matches[m + 1] as f64],
            )
        })
        .collect())
}

/// Applies the epipolar test to the DLT mask `m_dlt` (`[t, s, k]` like `corr`):
/// `m_dlt[j, i, k] &= d_a < τ && d_b < τ` for `j != i`; the diagonal is kept.
/// Returns the number of mask entries switched off.
pub fn epipolar_filter(
    corr: &Correspondences,
    m_dlt: &mut [bool],
    cams: &Cameras,
    max_error: f64,
) -> Result<usize> {
    corr.validate()?;
    let n = corr.dims.n;
    let hw = corr.dims.hw();
    if m_dlt.len() != corr.entries() {
        return Err(SfmError::Shape(format!(
            "epipolar: DLT mask of {} entries, expected {}",
            m_dlt.len(),
            corr.entries()
        )));
    }
    if cams.len() != n || cams.intrinsics.len() != n {
        return Err(SfmError::Shape(format!(
            "epipolar: {} cameras for {n} views",
            cams.len()
        )));
    }
    if !cams.is_finite() {
        return Err(SfmError::Invalid(
            "epipolar: non-finite camera entry".into(),
        ));
    }
    let thr = max_error as f32;
    let removed: Vec<usize> = m_dlt
        .par_chunks_mut(hw)
        .enumerate()
        .map(|(pair, mask)| -> Result<usize> {
            let (j, i) = (pair / n, pair % n);
            if i == j {
                return Ok(0);
            }
            let d = pair_distances(corr, cams, i, j)?;
            let mut removed = 0;
            for (m, (da, db)) in mask.iter_mut().zip(d) {
                let keep = (da as f32) < thr && (db as f32) < thr;
                if *m && !keep {
                    *m = false;
                    removed += 1;
                }
            }
            Ok(removed)
        })
        .collect::<Result<Vec<usize>>>()?;
    Ok(removed.iter().sum())
}

#[cfg(test)]
mod tests {
    use super::*;
    use ggpt_core::Dims;
    use nalgebra::Matrix3x4;

    fn spec_cameras() -> Cameras {
        let k = Matrix3::new(100.0, 0.0, 1.5, 0.0, 100.0, 1.0, 0.0, 0.0, 1.0);
        let c0 = Matrix3x4::identity();
        let mut c1 = Matrix3x4::identity();
        c1[(0, 3)] = -1.0;
        Cameras {
            cam_from_world: vec![c0, c1],
            intrinsics: vec![k, k],
        }
    }

    /// Test vector of `sfm.md` §8.
    #[test]
    fn spec_test_vector() {
        let cams = spec_cameras();
        let dims = Dims { n: 2, h: 3, w: 4 };
        let e = 4 * 12;
        let mut matches = vec![0f32; 2 * e];
        for t in 0..2 {
            for s in 0..2 {
                for k in 0..12 {
                    let i = (t * 2 + s) * 12 + k;
                    let (x, y) = ((k % 4) as f32, (k / 4) as f32);
                    matches[2 * i] = x - 20.0;
                    matches[2 * i + 1] = y + 0.7;
                }
            }
        }
        let mut corr = Correspondences {
            dims,
            matches,
            scores: vec![1.0; e],
            cycle: vec![0.0; e],
        };
        corr.apply_diagonal();
        let d = pair_distances(&corr, &cams, 0, 1).unwrap();
        for (k, (da, db)) in d.iter().enumerate() {
            assert!(
                (da - 0.7).abs() < 1e-6 && (db - 0.7).abs() < 1e-6,
                "pixel {k}: {da} {db}"
            );
        }
        let mut m = vec![true; e];
        assert_eq!(epipolar_filter(&corr, &mut m, &cams, 0.71).unwrap(), 0);
        // threshold below 0.7: both off-diagonal pairs fail the (0 -> 1) direction; (1 -> 0) displaced by -20 too
        let removed = epipolar_filter(&corr, &mut m, &cams, 0.69).unwrap();
        assert!(removed >= 12, "{removed}");
        assert!(m[corr.idx(0, 0, 5)] && m[corr.idx(1, 1, 5)]);
        assert!(!m[corr.idx(1, 0, 5)]);
    }

    #[test]
    fn zero_baseline_passes_and_nan_cameras_error() {
        let mut cams = spec_cameras();
        cams.cam_from_world[1] = Matrix3x4::identity();
        let f = fundamental(&cams, 0, 1).unwrap();
        assert!(f.iter().all(|v| v.abs() < 1e-12));
        let (da, db) = distances(&f, [1.0, 1.0], [30.0, 2.0]);
        assert!(da < 1e-6 && db < 1e-6);
        cams.cam_from_world[1][(0, 0)] = f64::NAN;
        let dims = Dims { n: 2, h: 1, w: 1 };
        let corr = Correspondences {
            dims,
            matches: vec![0.0; 8],
            scores: vec![1.0; 4],
            cycle: vec![0.0; 4],
        };
        let mut m = vec![true; 4];
        assert!(epipolar_filter(&corr, &mut m, &cams, 4.0).is_err());
    }
}
