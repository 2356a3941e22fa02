//! Sim(3) pre-alignment of the dense feed-forward points into the SfM frame (`pipeline.md` §3),
//! and the GT alignment of training / evaluation (`pipeline.md` §11.1).
//!
//! The similarity is fitted robustly (LO-RANSAC + Umeyama with the official retry schedule,
//! [`ggpt_core::sim3::align_with_retries`]) on the pixels that have a DLT point, listed in pixel
//! order (`src = X_d[p]`, `tgt = X_s[p]` for `M_s[p]`). The `f64` estimate is cast to an `f32`
//! 3x4 matrix `[sR | t]` and applied to **every** pixel in `f32` with the summation order
//! `((m_i0 x + m_i1 y) + m_i2 z) + m_i3` (bit-exact with the official pipeline).

use ggpt_core::sim3::{AlignInfo, AlignMethod, Sim3, align_with_retries};
use nalgebra::{Matrix3x4, Point3};
use rand::Rng;

use crate::error::{SceneError, check_len};

/// Default RANSAC inlier threshold `align.max_error` in target-frame units (`pipeline.md` §3).
pub const DEFAULT_ALIGN_MAX_ERROR: f64 = 0.03;

/// Result of a pre-alignment.
#[derive(Debug, Clone)]
pub struct Prealignment {
    /// The fitted `f64` similarity (target frame from source frame).
    pub tgt_from_src: Sim3,
    /// The `f32` matrix `[sR | t]` actually applied.
    pub matrix_f32: Matrix3x4<f32>,
    /// Which branch of the retry schedule was used, inliers.
    pub info: AlignInfo,
    /// Number of correspondences the fit used.
    pub num_pairs: usize,
    /// The transformed points (`[P, 3]`, target frame).
    pub aligned: Vec<f32>,
}

impl Prealignment {
    /// True when the alignment fell back to the identity (everything failed, `pipeline.md` §13).
    pub fn is_identity_fallback(&self) -> bool {
        self.info.method == AlignMethod::Identity
    }
}

/// Applies `m = [sR | t]` (`f32`) to a flat `[P, 3]` `f32` array, returning the transformed copy
/// (summation order `((m_i0 x + m_i1 y) + m_i2 z) + m_i3`, see [`ggpt_core::sim3::apply_matrix_f32`]).
pub fn apply_matrix_f32(m: &Matrix3x4<f32>, points: &[f32]) -> Vec<f32> {
    let mut out = points.to_vec();
    ggpt_core::sim3::apply_matrix_f32(m, &mut out);
    out
}

/// Correspondences `(src[p], tgt[p])` for every pixel with `mask[p]`, in pixel order, as `f64`.
fn pairs(src: &[f32], tgt: &[f32], mask: &[bool]) -> (Vec<Point3<f64>>, Vec<Point3<f64>>) {
    let mut s = Vec::new();
    let mut t = Vec::new();
    for ((a, b), &m) in src.chunks_exact(3).zip(tgt.chunks_exact(3)).zip(mask) {
        if m {
            s.push(Point3::new(
                f64::from(a[0]),
                f64::from(a[1]),
                f64::from(a[2]),
            ));
            t.push(Point3::new(
                f64::from(b[0]),
                f64::from(b[1]),
                f64::from(b[2]),
            ));
        }
    }
    (s, t)
}

/// Fits `tgt ≈ S(src)` over the pixels with `mask` and applies `S` (as `f32`) to all of `src`.
///
/// * `src`: `[P, 3]` points of the source frame; `tgt`: `[P, 3]` points of the target frame;
///   `mask`: `[P]` pixels usable as correspondences.
/// * `max_error`: RANSAC threshold (target units), retried ×3 up to 0.81 by the schedule.
/// * `rng`: the RANSAC sampler (seeded by the caller).
///
/// Never fails on degenerate data (identity fallback with a warning); fails on size mismatches.
pub fn align_points<R: Rng + ?Sized>(
    src: &[f32],
    tgt: &[f32],
    mask: &[bool],
    max_error: f64,
    rng: &mut R,
) -> Result<Prealignment, SceneError> {
    let p = mask.len();
    check_len("align: source points", src.len(), 3 * p)?;
    check_len("align: target points", tgt.len(), 3 * p)?;
    let (s, t) = pairs(src, tgt, mask);
    let (sim, info) = align_with_retries(&s, &t, max_error, rng);
    if info.method == AlignMethod::Identity {
        tracing::warn!(
            "Sim(3) alignment failed on {} correspondences; using the identity",
            s.len()
        );
    }
    let matrix_f32 = sim.to_matrix3x4_f32();
    let aligned = apply_matrix_f32(&matrix_f32, src);
    Ok(Prealignment {
        tgt_from_src: sim,
        matrix_f32,
        info,
        num_pairs: s.len(),
        aligned,
    })
}

/// Pre-alignment of §3: `X_d` (feed-forward frame) -> SfM frame, fitted on `M_s`.
/// `ff_points`, `dlt_points`: `[P, 3]`; `dlt_mask`: `[P]`. The result's `aligned` is the `X_d`
/// used by the rest of the pipeline (the caller keeps the original for the "init" baseline).
pub fn prealign_ff<R: Rng + ?Sized>(
    ff_points: &[f32],
    dlt_points: &[f32],
    dlt_mask: &[bool],
    max_error: f64,
    rng: &mut R,
) -> Result<Prealignment, SceneError> {
    align_points(ff_points, dlt_points, dlt_mask, max_error, rng)
}

/// GT alignment of §11.1 (training / evaluation records): GT points (metres, GT frame) -> SfM
/// frame, fitted on `gt_mask ∧ M_s`, then set to 0 where `gt_mask` is false.
pub fn align_gt<R: Rng + ?Sized>(
    gt_points: &[f32],
    gt_mask: &[bool],
    dlt_points: &[f32],
    dlt_mask: &[bool],
    max_error: f64,
    rng: &mut R,
) -> Result<Prealignment, SceneError> {
    check_len("align_gt: gt mask", gt_mask.len(), dlt_mask.len())?;
    let fit_mask: Vec<bool> = gt_mask
        .iter()
        .zip(dlt_mask)
        .map(|(&g, &d)| g && d)
        .collect();
    let mut res = align_points(gt_points, dlt_points, &fit_mask, max_error, rng)?;
    for (x, &m) in res.aligned.chunks_exact_mut(3).zip(gt_mask) {
        if !m {
            x.fill(0.0);
        }
    }
    Ok(res)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_util::Fixture;
    use rand::SeedableRng;

    fn mat(v: &[f32]) -> Matrix3x4<f32> {
        Matrix3x4::from_row_slice(v)
    }

    #[test]
    fn official_matrix_reproduces_aligned_points_bit_exactly() {
        let steps = Fixture::sfm_steps();
        let inputs = Fixture::sfm_inputs();
        let m = mat(&steps.f32("sim3/ff_sim3d_mat"));
        let got = apply_matrix_f32(&m, &inputs.f32("ff/points"));
        let want = steps.f32("sim3/ff_aligned");
        assert_eq!(got.len(), want.len());
        let bad = got
            .iter()
            .zip(&want)
            .position(|(a, b)| a.to_bits() != b.to_bits());
        assert!(bad.is_none(), "first mismatch at {bad:?}");
        // The f64 official transform cast to f32 is the f32 matrix.
        let m64 = steps.f64("sim3/ff_tgt_from_src_f64");
        let cast: Vec<f32> = m64.iter().map(|&v| v as f32).collect();
        assert_eq!(cast, steps.f32("sim3/ff_sim3d_mat"));
    }

    #[test]
    fn own_estimate_close_to_official() {
        let steps = Fixture::sfm_steps();
        let inputs = Fixture::sfm_inputs();
        let ff = inputs.f32("ff/points");
        let dlt = steps.f32("scatter/points");
        let msk = steps.bool("scatter/point_masks");
        assert_eq!(msk, steps.bool("sim3/ff_mask"));
        let mut rng = rand_pcg::Pcg64::seed_from_u64(42);
        let res = prealign_ff(&ff, &dlt, &msk, DEFAULT_ALIGN_MAX_ERROR, &mut rng).unwrap();
        assert_eq!(res.num_pairs, 7794);
        assert_eq!(res.info.method, AlignMethod::Robust { max_error: 0.03 });
        let want = steps.f32("sim3/ff_sim3d_mat");
        let diff = res
            .matrix_f32
            .iter()
            .zip(mat(&want).iter())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        // Official repeated runs spread by 1.9e-3 (fixture README); this LO-RANSAC's estimates
        // over seeds 0..16 spread 1e-4 .. 4.5e-3 from the official one, always with at least as
        // many inliers (5607..5659 vs 5608): seed 42 gives 2.75e-3. Tolerance: 5e-3.
        assert!(diff < 5e-3, "max |Δ matrix| = {diff}");
        let n_in = res.info.num_inliers.unwrap();
        assert!(
            (5600..5900).contains(&n_in),
            "inliers {n_in} (official 5608)"
        );
    }

    #[test]
    fn gt_alignment_zeroes_invalid_and_is_close() {
        let steps = Fixture::sfm_steps();
        let reference = Fixture::official_reference();
        let gt = reference.f32("gt/points");
        let gt_msk = reference.bool("gt/point_masks");
        let dlt = steps.f32("scatter/points");
        let msk = steps.bool("scatter/point_masks");
        let mut rng = rand_pcg::Pcg64::seed_from_u64(42);
        let res = align_gt(&gt, &gt_msk, &dlt, &msk, DEFAULT_ALIGN_MAX_ERROR, &mut rng).unwrap();
        assert_eq!(res.num_pairs, 7709);
        let want = mat(&steps.f32("sim3/gt_sim3d_mat"));
        let diff = res
            .matrix_f32
            .iter()
            .zip(want.iter())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(diff < 2e-3, "max |Δ matrix| = {diff}");
        for (p, &m) in gt_msk.iter().enumerate() {
            if !m {
                assert_eq!(&res.aligned[3 * p..3 * p + 3], &[0.0; 3]);
            }
        }
    }

    #[test]
    fn synthetic_similarity_recovered_and_degenerate_falls_back() {
        // tgt = 2 Rz(90°) src + (1, 2, 3) on a grid of 27 points.
        let mut src = Vec::new();
        let mut tgt = Vec::new();
        for i in 0..27 {
            let (x, y, z) = ((i % 3) as f32, ((i / 3) % 3) as f32, (i / 9) as f32);
            src.extend([x, y, z]);
            tgt.extend([-2.0 * y + 1.0, 2.0 * x + 2.0, 2.0 * z + 3.0]);
        }
        let mask = vec![true; 27];
        let mut rng = rand_pcg::Pcg64::seed_from_u64(1);
        let r = align_points(&src, &tgt, &mask, 0.03, &mut rng).unwrap();
        for (a, b) in r.aligned.iter().zip(&tgt) {
            assert!((a - b).abs() < 1e-5);
        }
        // No correspondence: identity, points unchanged.
        let none = vec![false; 27];
        let r = align_points(&src, &tgt, &none, 0.03, &mut rng).unwrap();
        assert!(r.is_identity_fallback());
        assert_eq!(r.aligned, src);
        assert!(align_points(&src[..5], &tgt, &mask, 0.03, &mut rng).is_err());
    }
}
