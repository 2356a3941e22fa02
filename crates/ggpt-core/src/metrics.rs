//! Evaluation metrics (`pipeline.md` §10): point accuracy after a robust Sim(3) alignment
//! ([`points`]), relative camera accuracy and field-of-view error ([`cameras`]) and depth
//! accuracy in the GT camera frames ([`depth`]). This file holds the shared recall / AUC helpers.
//!
//! Conventions: point errors in **centimetres**, angles in **degrees**; AUC and recall values in
//! the metric structs are **percent**, the low-level helpers return fractions in `[0, 1]`.

pub mod cameras;
pub mod depth;
pub mod points;

pub use cameras::{CameraMetrics, PairError, camera_metrics, fov_errors, relative_pose_errors};
pub use depth::{DepthMetrics, depth_metrics};
pub use points::{PointEvaluation, PointMetrics, point_metrics};

use crate::{CoreError, Result};

/// AUC thresholds reported for points (cm) and cameras (degrees) (`pipeline.md` §10.2, §10.3).
pub const AUC_THRESHOLDS: [usize; 4] = [1, 3, 5, 10];
/// Point recalls are computed at `k = 1..=POINT_RECALL_MAX_CM` cm (`pipeline.md` §10.2).
pub const POINT_RECALL_MAX_CM: usize = 10;
/// Sim(3) RANSAC threshold of the evaluation alignment, metres (`pipeline.md` §10.2).
pub const EVAL_ALIGN_MAX_ERROR: f64 = 0.03;

/// `Recall@k = fraction of errors < k` (strict) for `k = 1..=max_k` (`pipeline.md` §10.2).
/// Errors in any unit; `k` in the same unit. An empty slice gives all zeros.
pub fn recalls_strict(errors: &[f64], max_k: usize) -> Vec<f64> {
    let n = errors.len();
    (1..=max_k)
        .map(|k| {
            if n == 0 {
                return 0.0;
            }
            let kf = k as f64;
            errors.iter().filter(|&&e| e < kf).count() as f64 / n as f64
        })
        .collect()
}

/// `AUC@τ = (1/τ) Σ_{k=1}^{τ} Recall@k` from recalls at `k = 1, 2, ...` (`recalls[k-1]`), as a
/// fraction (`pipeline.md` §10.2). Fails when fewer than `τ` recalls are given or `τ = 0`.
pub fn auc_from_recalls(recalls: &[f64], tau: usize) -> Result<f64> {
    if tau == 0 || recalls.len() < tau {
        return Err(CoreError::Invalid(format!(
            "AUC@{tau} needs {tau} recalls, got {}",
            recalls.len()
        )));
    }
    Ok(recalls.iter().take(tau).sum::<f64>() / tau as f64)
}

/// Camera AUC@τ with the official histogram semantics (`pipeline.md` §10.3): unit bins
/// `[0,1), ..., [τ-1, τ]` (last bin closed, errors above `τ` or negative / NaN not counted),
/// normalised by the number of errors, cumulative sum, mean over the `τ` bins; equivalently
/// `(1/τ) Σ_{k=1}^{τ} frac(e < k)` with `≤` at `k = τ`. Fraction; 0 for an empty slice.
pub fn camera_auc(errors: &[f64], tau: usize) -> f64 {
    let n = errors.len();
    if n == 0 || tau == 0 {
        return 0.0;
    }
    let t = tau as f64;
    let mut bins = vec![0usize; tau];
    for &e in errors {
        if e >= 0.0 && e <= t {
            // e in [b, b+1) -> bin b; e == τ falls in the last (closed) bin.
            let b = (e.floor() as usize).min(tau - 1);
            if let Some(c) = bins.get_mut(b) {
                *c += 1;
            }
        }
    }
    let mut cum = 0.0;
    let mut total = 0.0;
    for c in bins {
        cum += c as f64 / n as f64;
        total += cum;
    }
    total / t
}

/// Median (mean of the two middle values for an even count); NaN for an empty slice.
/// NaN entries sort last.
pub fn median(values: &[f64]) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let mut v = values.to_vec();
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    let hi = v.get(n / 2).copied().unwrap_or(f64::NAN);
    if n % 2 == 1 {
        hi
    } else {
        let lo = v.get(n / 2 - 1).copied().unwrap_or(f64::NAN);
        0.5 * (lo + hi)
    }
}

/// Mean; NaN for an empty slice.
pub fn mean(values: &[f64]) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    values.iter().sum::<f64>() / values.len() as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spec_point_test_vector() {
        let e = [0.4, 0.9, 1.0, 2.5, 4.99, 5.0, 7.2, 11.0];
        let r = recalls_strict(&e, 10);
        let want = [
            0.25, 0.375, 0.5, 0.5, 0.625, 0.75, 0.75, 0.875, 0.875, 0.875,
        ];
        for (a, b) in r.iter().zip(want) {
            assert!((a - b).abs() < 1e-12, "{r:?}");
        }
        let aucs: Vec<f64> = AUC_THRESHOLDS
            .iter()
            .map(|&t| auc_from_recalls(&r, t).unwrap())
            .collect();
        for (a, b) in aucs.iter().zip([0.25, 0.375, 0.45, 0.6375]) {
            assert!((a - b).abs() < 1e-12, "{aucs:?}");
        }
        assert!(auc_from_recalls(&r, 11).is_err());
        assert!(auc_from_recalls(&r, 0).is_err());
    }

    #[test]
    fn spec_camera_test_vector() {
        let pairs = [(0.5, 0.2), (1.5, 0.1), (2.0, 0.3), (4.0, 0.5), (12.0, 0.1)];
        let e: Vec<f64> = pairs.iter().map(|(r, t): &(f64, f64)| r.max(*t)).collect();
        let aucs: Vec<f64> = AUC_THRESHOLDS.iter().map(|&t| camera_auc(&e, t)).collect();
        for (a, b) in aucs.iter().zip([0.2, 0.4, 0.52, 0.66]) {
            assert!((a - b).abs() < 1e-12, "{aucs:?}");
        }
    }

    #[test]
    fn camera_auc_boundaries() {
        // Exactly τ counts at k = τ (closed last bin) but not below; exactly k < τ is not "< k".
        assert!((camera_auc(&[3.0], 3) - 1.0 / 3.0).abs() < 1e-12);
        assert!((camera_auc(&[1.0], 3) - 2.0 / 3.0).abs() < 1e-12);
        assert_eq!(camera_auc(&[3.0000001], 3), 0.0);
        assert_eq!(camera_auc(&[f64::NAN, 1e6], 1), 0.0);
        assert_eq!(camera_auc(&[0.0, 0.0], 10), 1.0);
        assert_eq!(camera_auc(&[], 10), 0.0);
        // Equivalent closed form.
        let e = [0.1, 0.99, 1.0, 2.2, 2.999, 3.0, 7.0, 10.0, 10.5];
        for tau in [1usize, 3, 5, 10] {
            let closed: f64 = (1..=tau)
                .map(|k| {
                    let kf = k as f64;
                    e.iter()
                        .filter(|&&x| if k == tau { x <= kf } else { x < kf })
                        .count() as f64
                        / e.len() as f64
                })
                .sum::<f64>()
                / tau as f64;
            assert!((camera_auc(&e, tau) - closed).abs() < 1e-12, "tau {tau}");
        }
    }

    #[test]
    fn median_and_mean() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0, 2.0, 3.0]), 2.5);
        assert!(median(&[]).is_nan());
        assert_eq!(mean(&[1.0, 2.0, 6.0]), 3.0);
        assert_eq!(recalls_strict(&[], 3), vec![0.0; 3]);
    }
}
