//! Depth accuracy (`pipeline.md` §10.4, [project]): the depth of a prediction is the `z` of the
//! Sim(3)-aligned prediction (the §10.2 alignment) in each GT camera frame; `Rel` and `δ<τ` over
//! the valid GT pixels.

use nalgebra::Point3;

use crate::sim3::Sim3;
use crate::{Cameras, CoreError, Result};

/// `δ` thresholds (`pipeline.md` §10.4).
pub const DELTA_THRESHOLDS: [f64; 4] = [1.01, 1.03, 1.10, 1.25];
/// Denominator epsilon of the relative error (`pipeline.md` §10.4), metres.
pub const REL_EPS: f64 = 1e-6;

/// Depth accuracy summary.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DepthMetrics {
    /// Number of evaluated pixels (valid GT depth > 0 within the evaluation mask).
    pub num_pixels: usize,
    /// `mean(|d_gt - d_pred| / (d_gt + 1e-6))` (a fraction, not percent).
    pub abs_rel: f64,
    /// Percent of pixels with `max(d_gt/d_pred, d_pred/d_gt) < 1.01`.
    pub delta_1_01: f64,
    /// Same with 1.03 (percent).
    pub delta_1_03: f64,
    /// Same with 1.10 (percent).
    pub delta_1_10: f64,
    /// Same with 1.25 (percent).
    pub delta_1_25: f64,
}

/// Depth metrics of `pred` (`[N, h, w, 3]`, prediction frame) after applying `gt_from_pred`
/// (the point-accuracy alignment, prediction frame -> GT world frame, metres).
///
/// * `gt_cameras`: GT `cam_from_world` per view (GT world, metres); `n` views of `hw` pixels.
/// * `gt_depth`: `[N, h, w]` GT z-depth (metres); when `None` it is the `z` of `gt_points` in the
///   GT camera of its view.
/// * `mask`: `[N, h, w]` pixels to evaluate (typically the GT mask, or the point-evaluation mask);
///   pixels whose GT depth is not `> 0` are skipped.
///
/// A pixel whose predicted depth is `<= 0` (behind the GT camera) or non-finite fails every `δ`
/// test ([project]: the ratio would otherwise be negative and pass) and contributes its
/// `|d_gt - d_pred| / d_gt` to `Rel`. Fails on mismatched sizes or when no pixel is evaluated.
pub fn depth_metrics(
    pred: &[f32],
    gt_from_pred: &Sim3,
    gt_cameras: &Cameras,
    gt_points: &[f32],
    gt_depth: Option<&[f32]>,
    mask: &[bool],
) -> Result<DepthMetrics> {
    let n_px = mask.len();
    let n_views = gt_cameras.len();
    if n_views == 0 || !n_px.is_multiple_of(n_views) {
        return Err(CoreError::Invalid(format!(
            "depth metrics: {n_px} pixels for {n_views} GT cameras"
        )));
    }
    let hw = n_px / n_views;
    if pred.len() != 3 * n_px
        || gt_points.len() != 3 * n_px
        || gt_depth.is_some_and(|d| d.len() != n_px)
    {
        return Err(CoreError::Invalid(format!(
            "depth metrics: prediction {} values, GT points {}, GT depth {:?}, mask {n_px} pixels",
            pred.len(),
            gt_points.len(),
            gt_depth.map(|d| d.len())
        )));
    }
    let mut n = 0usize;
    let mut rel_sum = 0.0;
    let mut delta_hits = [0usize; 4];
    for (p, _) in mask.iter().enumerate().filter(|(_, m)| **m) {
        let view = p / hw;
        let r = gt_cameras.rotation(view);
        let t = gt_cameras.translation(view);
        let d_gt = match gt_depth {
            Some(d) => d.get(p).map_or(f64::NAN, |v| f64::from(*v)),
            None => {
                let g = gt_points.get(3 * p..3 * p + 3).unwrap_or(&[f32::NAN; 3]);
                (r * Point3::new(f64::from(g[0]), f64::from(g[1]), f64::from(g[2])).coords + t).z
            }
        };
        if !(d_gt.is_finite() && d_gt > 0.0) {
            continue;
        }
        let q = pred.get(3 * p..3 * p + 3).unwrap_or(&[f32::NAN; 3]);
        let x = gt_from_pred.apply(&Point3::new(
            f64::from(q[0]),
            f64::from(q[1]),
            f64::from(q[2]),
        ));
        let d_pred = (r * x.coords + t).z;
        n += 1;
        rel_sum += if d_pred.is_finite() {
            (d_gt - d_pred).abs() / (d_gt + REL_EPS)
        } else {
            f64::INFINITY
        };
        if d_pred.is_finite() && d_pred > 0.0 {
            let ratio = (d_gt / d_pred).max(d_pred / d_gt);
            for (hit, thr) in delta_hits.iter_mut().zip(DELTA_THRESHOLDS) {
                if ratio < thr {
                    *hit += 1;
                }
            }
        }
    }
    if n == 0 {
        return Err(CoreError::Invalid(
            "depth metrics: no pixel with valid GT depth in the mask".into(),
        ));
    }
    let pct = |h: usize| 100.0 * h as f64 / n as f64;
    Ok(DepthMetrics {
        num_pixels: n,
        abs_rel: rel_sum / n as f64,
        delta_1_01: pct(delta_hits[0]),
        delta_1_03: pct(delta_hits[1]),
        delta_1_10: pct(delta_hits[2]),
        delta_1_25: pct(delta_hits[3]),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix3, Matrix3x4, Vector3};

    /// One identity camera, 4 pixels with GT depths 1, 2, 4, 8 straight ahead.
    fn setup() -> (Cameras, Vec<f32>, Vec<f32>) {
        let cams = Cameras {
            cam_from_world: vec![Matrix3x4::identity()],
            intrinsics: vec![Matrix3::identity()],
        };
        let depth = vec![1.0f32, 2.0, 4.0, 8.0];
        let pts: Vec<f32> = depth.iter().flat_map(|d| [0.1 * d, -0.2 * d, *d]).collect();
        (cams, pts, depth)
    }

    #[test]
    fn gt_against_itself_is_perfect() {
        let (cams, pts, depth) = setup();
        let m = depth_metrics(
            &pts,
            &Sim3::identity(),
            &cams,
            &pts,
            Some(&depth),
            &[true; 4],
        )
        .unwrap();
        assert_eq!(m.num_pixels, 4);
        assert!(m.abs_rel < 1e-6);
        assert_eq!(
            [m.delta_1_01, m.delta_1_03, m.delta_1_10, m.delta_1_25],
            [100.0; 4]
        );
        // Depth derived from the GT points gives the same.
        let m2 = depth_metrics(&pts, &Sim3::identity(), &cams, &pts, None, &[true; 4]).unwrap();
        assert_eq!(m, m2);
    }

    #[test]
    fn hand_computed_ratios() {
        let (cams, gt, depth) = setup();
        // Predicted depths: 1.005, 2*1.02, 4*1.2, -1 (behind the camera).
        let pred_d = [1.005f32, 2.04, 4.8, -1.0];
        let pred: Vec<f32> = pred_d.iter().flat_map(|d| [0.0, 0.0, *d]).collect();
        let m = depth_metrics(
            &pred,
            &Sim3::identity(),
            &cams,
            &gt,
            Some(&depth),
            &[true; 4],
        )
        .unwrap();
        assert_eq!(m.delta_1_01, 25.0);
        assert_eq!(m.delta_1_03, 50.0);
        assert_eq!(m.delta_1_10, 50.0);
        assert_eq!(m.delta_1_25, 75.0);
        let want_rel =
            (0.005 / (1.0 + 1e-6) + 0.04 / (2.0 + 1e-6) + 0.8 / (4.0 + 1e-6) + 9.0 / (8.0 + 1e-6))
                / 4.0;
        assert!(
            (m.abs_rel - want_rel).abs() < 1e-6,
            "{} vs {want_rel}",
            m.abs_rel
        );
    }

    #[test]
    fn alignment_is_applied_and_invalid_skipped() {
        let (cams, gt, mut depth) = setup();
        // pred = gt / 2 shifted: the alignment x -> 2 x + (0,0,0) restores it.
        let pred: Vec<f32> = gt.iter().map(|v| v / 2.0).collect();
        let s = Sim3 {
            scale: 2.0,
            rotation: Matrix3::identity(),
            translation: Vector3::zeros(),
        };
        depth[3] = 0.0; // invalid GT depth is skipped
        let m = depth_metrics(
            &pred,
            &s,
            &cams,
            &gt,
            Some(&depth),
            &[true, true, false, true],
        )
        .unwrap();
        assert_eq!(m.num_pixels, 2);
        assert_eq!(m.delta_1_01, 100.0);
        assert!(depth_metrics(&pred, &s, &cams, &gt, Some(&depth), &[false; 4]).is_err());
        assert!(depth_metrics(&pred[..9], &s, &cams, &gt, Some(&depth), &[true; 4]).is_err());
    }
}
