//! Point accuracy (`pipeline.md` §10.2): robust Sim(3) alignment of a prediction to the ground
//! truth over the evaluated pixels, per-pixel error in centimetres, Recall@1..10 cm, AUC@1/3/5/10.

use nalgebra::Point3;
use rand::Rng;

use super::{AUC_THRESHOLDS, POINT_RECALL_MAX_CM, auc_from_recalls, mean, median, recalls_strict};
use crate::sim3::{AlignInfo, AlignMethod, Sim3, align_with_retries};
use crate::{CoreError, Result};

/// Metres -> centimetres.
const CM_PER_M: f64 = 100.0;

/// Summary of point accuracy. Recalls and AUCs are in percent.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PointMetrics {
    /// Number of evaluated pixels (GT-valid and in the subset).
    pub num_points: usize,
    /// Recall@k cm for k = 1..=10 (percent, strict `<`).
    pub recall_pct: Vec<f64>,
    /// AUC@1 cm (percent).
    pub auc_1: f64,
    /// AUC@3 cm (percent).
    pub auc_3: f64,
    /// AUC@5 cm (percent).
    pub auc_5: f64,
    /// AUC@10 cm (percent).
    pub auc_10: f64,
    /// Mean error (cm).
    pub mean_cm: f64,
    /// Median error (cm; mean of the two middle values for an even count).
    pub median_cm: f64,
    /// With a subset mask (SfM-style evaluation): evaluated pixels / GT-valid pixels (`points/ratio`).
    pub ratio: Option<f64>,
    /// Alignment branch used (`pipeline.md` §3.1 retry schedule).
    pub align: AlignMethod,
    /// RANSAC inliers of the alignment (robust branch only).
    pub align_inliers: Option<usize>,
    /// The alignment `gt_from_pred` as a row-major 3x4 matrix `[s R | t]`.
    pub gt_from_pred: [[f64; 4]; 3],
}

/// Full result of [`point_metrics`].
#[derive(Debug, Clone, PartialEq)]
pub struct PointEvaluation {
    /// Summary.
    pub metrics: PointMetrics,
    /// Alignment `gt_from_pred` (prediction frame -> GT frame, metres).
    pub sim3: Sim3,
    /// Details of the alignment.
    pub align: AlignInfo,
    /// Per-pixel error in cm over the evaluated pixels, pixel order.
    pub errors_cm: Vec<f64>,
    /// Evaluated pixels (GT mask ∧ subset), `[N, h, w]`.
    pub mask: Vec<bool>,
}

fn point_at(points: &[f32], p: usize) -> Option<Point3<f64>> {
    let s = points.get(3 * p..3 * p + 3)?;
    Some(Point3::new(
        f64::from(s[0]),
        f64::from(s[1]),
        f64::from(s[2]),
    ))
}

/// Evaluates a predicted point map against the ground truth (`pipeline.md` §10.2).
///
/// * `pred`: `[N, h, w, 3]` predicted points (any frame, any scale), pixel order.
/// * `gt_points`: `[N, h, w, 3]` GT points (GT world frame, metres); `gt_mask`: `[N, h, w]` valid GT.
/// * `subset`: optional `[N, h, w]` mask restricting the evaluation (e.g. the SfM mask `M_s`);
///   the metrics then also report `ratio` = evaluated / GT-valid pixels.
/// * `max_error`: Sim(3) RANSAC threshold in metres (0.03 officially); `rng`: RANSAC draws.
///
/// The prediction is aligned to the GT over the evaluated pixels with
/// [`align_with_retries`], then `e_p = 100 ||S(pred_p) - gt_p||` cm. Fails on mismatched sizes,
/// no evaluated pixel, or a non-finite predicted / GT point among the evaluated pixels.
pub fn point_metrics<R: Rng + ?Sized>(
    pred: &[f32],
    gt_points: &[f32],
    gt_mask: &[bool],
    subset: Option<&[bool]>,
    max_error: f64,
    rng: &mut R,
) -> Result<PointEvaluation> {
    let n_px = gt_mask.len();
    if pred.len() != 3 * n_px || gt_points.len() != 3 * n_px {
        return Err(CoreError::Invalid(format!(
            "point_metrics: prediction has {} values, GT points {}, GT mask {} pixels (need 3 values per pixel)",
            pred.len(),
            gt_points.len(),
            n_px
        )));
    }
    if let Some(s) = subset
        && s.len() != n_px
    {
        return Err(CoreError::Invalid(format!(
            "point_metrics: subset mask has {} pixels, GT mask {n_px}",
            s.len()
        )));
    }
    let mask: Vec<bool> = gt_mask
        .iter()
        .enumerate()
        .map(|(p, &v)| v && subset.is_none_or(|s| s.get(p).copied().unwrap_or(false)))
        .collect();
    let mut src = Vec::new();
    let mut tgt = Vec::new();
    for (p, _) in mask.iter().enumerate().filter(|(_, m)| **m) {
        let (Some(a), Some(b)) = (point_at(pred, p), point_at(gt_points, p)) else {
            return Err(CoreError::Invalid(format!(
                "point_metrics: pixel {p} out of range"
            )));
        };
        if !a.coords.iter().all(|v| v.is_finite()) {
            return Err(CoreError::Invalid(format!(
                "point_metrics: non-finite predicted point at pixel {p}"
            )));
        }
        if !b.coords.iter().all(|v| v.is_finite()) {
            return Err(CoreError::Invalid(format!(
                "point_metrics: non-finite GT point at pixel {p}"
            )));
        }
        src.push(a);
        tgt.push(b);
    }
    if src.is_empty() {
        return Err(CoreError::Invalid(
            "point_metrics: no pixel to evaluate (empty GT mask ∧ subset)".into(),
        ));
    }
    let (sim3, align) = align_with_retries(&src, &tgt, max_error, rng);
    let errors_cm: Vec<f64> = src
        .iter()
        .zip(tgt.iter())
        .map(|(a, b)| (sim3.apply(a) - b).norm() * CM_PER_M)
        .collect();
    let n_valid = gt_mask.iter().filter(|&&v| v).count();
    let ratio = subset.map(|_| {
        if n_valid == 0 {
            0.0
        } else {
            src.len() as f64 / n_valid as f64
        }
    });
    let metrics = summarize(&errors_cm, ratio, &sim3, &align)?;
    Ok(PointEvaluation {
        metrics,
        sim3,
        align,
        errors_cm,
        mask,
    })
}

/// Summarises per-pixel errors (cm) into [`PointMetrics`].
fn summarize(
    errors_cm: &[f64],
    ratio: Option<f64>,
    sim3: &Sim3,
    align: &AlignInfo,
) -> Result<PointMetrics> {
    let recalls = recalls_strict(errors_cm, POINT_RECALL_MAX_CM);
    let [a1, a3, a5, a10] = AUC_THRESHOLDS;
    let m = sim3.to_matrix3x4();
    let mut gt_from_pred = [[0.0; 4]; 3];
    for (r, row) in gt_from_pred.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            *v = m[(r, c)];
        }
    }
    Ok(PointMetrics {
        num_points: errors_cm.len(),
        recall_pct: recalls.iter().map(|r| 100.0 * r).collect(),
        auc_1: 100.0 * auc_from_recalls(&recalls, a1)?,
        auc_3: 100.0 * auc_from_recalls(&recalls, a3)?,
        auc_5: 100.0 * auc_from_recalls(&recalls, a5)?,
        auc_10: 100.0 * auc_from_recalls(&recalls, a10)?,
        mean_cm: mean(errors_cm),
        median_cm: median(errors_cm),
        ratio,
        align: align.method,
        align_inliers: align.num_inliers,
        gt_from_pred,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3};
    use rand::SeedableRng;
    use rand_pcg::Pcg64;

    fn grid_points(n: usize) -> Vec<f32> {
        // A non-planar cloud of metric points.
        (0..n)
            .flat_map(|i| {
                let f = i as f32;
                [
                    (f * 0.37).sin() * 2.0,
                    (f * 0.11).cos() * 1.5,
                    3.0 + (f * 0.07).sin(),
                ]
            })
            .collect()
    }

    #[test]
    fn gt_against_itself_is_perfect() {
        let gt = grid_points(500);
        let mut mask = vec![true; 500];
        mask[7] = false;
        let mut rng = Pcg64::seed_from_u64(42);
        let ev = point_metrics(&gt, &gt, &mask, None, 0.03, &mut rng).unwrap();
        let m = &ev.metrics;
        assert_eq!(m.num_points, 499);
        assert_eq!([m.auc_1, m.auc_3, m.auc_5, m.auc_10], [100.0; 4]);
        assert!(m.recall_pct.iter().all(|&r| r == 100.0));
        assert!(m.mean_cm < 1e-9 && m.median_cm < 1e-9);
        assert_eq!(m.ratio, None);
        assert!(matches!(m.align, AlignMethod::Robust { .. }));
    }

    #[test]
    fn similarity_of_gt_is_undone() {
        // pred = S^-1(gt): any frame and scale must evaluate as perfect.
        let gt = grid_points(400);
        let s = Sim3 {
            scale: 0.3,
            rotation: *Rotation3::from_euler_angles(0.3, -1.0, 2.0).matrix(),
            translation: Vector3::new(5.0, -2.0, 1.0),
        };
        let pred: Vec<f32> = gt
            .chunks_exact(3)
            .flat_map(|c| {
                let q = s.apply(&Point3::new(c[0] as f64, c[1] as f64, c[2] as f64));
                [q.x as f32, q.y as f32, q.z as f32]
            })
            .collect();
        let mask = vec![true; 400];
        let mut rng = Pcg64::seed_from_u64(1);
        let ev = point_metrics(&pred, &gt, &mask, None, 0.03, &mut rng).unwrap();
        assert_eq!(ev.metrics.auc_1, 100.0);
        assert!(ev.metrics.mean_cm < 1e-3, "{}", ev.metrics.mean_cm);
        assert!((ev.sim3.scale - 1.0 / 0.3).abs() < 1e-4);
    }

    #[test]
    fn hand_computed_offsets() {
        // 100 exact points anchor the alignment; 8 points carry known offsets along x, all far
        // above the 3 cm threshold, so they are outliers and the fit is exact.
        let base = grid_points(108);
        let offsets_cm = [12.0, 20.0, 35.0, 50.0, 80.0, 120.0, 200.0, 400.0];
        let mut pred = base.clone();
        for (j, o) in offsets_cm.iter().enumerate() {
            pred[3 * (100 + j)] += (*o / 100.0) as f32;
        }
        let mask = vec![true; 108];
        let mut rng = Pcg64::seed_from_u64(3);
        let ev = point_metrics(&pred, &base, &mask, None, 0.03, &mut rng).unwrap();
        assert_eq!(ev.align.num_inliers, Some(100));
        for (j, o) in offsets_cm.iter().enumerate() {
            assert!(
                (ev.errors_cm[100 + j] - o).abs() < 1e-3,
                "{} vs {o}",
                ev.errors_cm[100 + j]
            );
        }
        // 100 of 108 below every k: recall = 100/108 for k = 1..10 (every offset is >= 12 cm).
        let r = 100.0 * 100.0 / 108.0;
        assert!(
            ev.metrics.recall_pct.iter().all(|x| (x - r).abs() < 1e-9),
            "{:?}",
            ev.metrics.recall_pct
        );
        assert!((ev.metrics.auc_5 - r).abs() < 1e-9);
        let want_mean = offsets_cm.iter().sum::<f64>() / 108.0;
        assert!((ev.metrics.mean_cm - want_mean).abs() < 1e-3);
        assert!(ev.metrics.median_cm < 1e-4);
    }

    #[test]
    fn subset_and_ratio() {
        let gt = grid_points(200);
        let mut gt_mask = vec![true; 200];
        gt_mask[0] = false;
        let subset: Vec<bool> = (0..200).map(|i| i % 2 == 0).collect();
        let mut rng = Pcg64::seed_from_u64(4);
        let ev = point_metrics(&gt, &gt, &gt_mask, Some(&subset), 0.03, &mut rng).unwrap();
        assert_eq!(ev.metrics.num_points, 99);
        assert!((ev.metrics.ratio.unwrap() - 99.0 / 199.0).abs() < 1e-12);
        assert!(!ev.mask[0] && !ev.mask[1] && ev.mask[2]);
    }

    #[test]
    fn invalid_inputs() {
        let gt = grid_points(10);
        let mut rng = Pcg64::seed_from_u64(5);
        assert!(point_metrics(&gt[..27], &gt, &[true; 10], None, 0.03, &mut rng).is_err());
        assert!(point_metrics(&gt, &gt, &[false; 10], None, 0.03, &mut rng).is_err());
        assert!(point_metrics(&gt, &gt, &[true; 10], Some(&[true; 9]), 0.03, &mut rng).is_err());
        let mut bad = gt.clone();
        bad[4] = f32::NAN;
        let err = point_metrics(&bad, &gt, &[true; 10], None, 0.03, &mut rng).unwrap_err();
        assert!(err.to_string().contains("pixel 1"), "{err}");
        // A NaN outside the mask is ignored.
        let mut mask = [true; 10];
        mask[1] = false;
        assert!(point_metrics(&bad, &gt, &mask, None, 0.03, &mut rng).is_ok());
    }
}
