//! Camera accuracy (`pipeline.md` §10.3): relative-pose errors over all view pairs `i < j`
//! (rotation angle, sign-agnostic translation direction), AUC@1/3/5/10 degrees with the official
//! histogram semantics, and the field-of-view error.

use nalgebra::{Matrix3, Matrix3x4, Vector3};

use super::{AUC_THRESHOLDS, camera_auc, mean};
use crate::{Cameras, CoreError, Result};

/// Normalisation epsilon of the translation directions (official `t / (||t|| + 1e-15)`).
pub const TRANSLATION_NORM_EPS: f64 = 1e-15;
/// Lower clamp of `1 - dot^2` in the official translation-angle formula.
pub const TRANSLATION_LOSS_EPS: f64 = 1e-15;
/// Error assigned to a NaN / infinite translation-direction error (degrees, official default).
pub const NON_FINITE_ERROR_DEG: f64 = 1e6;

/// Errors of one view pair `i < j` (degrees).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PairError {
    /// First view.
    pub i: usize,
    /// Second view (`j > i`).
    pub j: usize,
    /// Relative rotation error.
    pub rot_deg: f64,
    /// Sign-agnostic translation-direction error, in `[0, 90]` (or 1e6 when non-finite).
    pub trans_deg: f64,
    /// `max(rot_deg, trans_deg)`.
    pub max_deg: f64,
}

/// Camera accuracy summary. AUCs in percent, FoV errors in degrees.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CameraMetrics {
    /// Number of view pairs.
    pub num_pairs: usize,
    /// AUC@1° of the pair error (percent).
    pub auc_1: f64,
    /// AUC@3° (percent).
    pub auc_3: f64,
    /// AUC@5° (percent).
    pub auc_5: f64,
    /// AUC@10° (percent).
    pub auc_10: f64,
    /// Mean relative rotation error (degrees).
    pub rot_mean_deg: f64,
    /// Mean translation-direction error (degrees).
    pub trans_mean_deg: f64,
    /// Mean absolute horizontal FoV error (degrees).
    pub fovx_error_deg: f64,
    /// Mean absolute vertical FoV error (degrees).
    pub fovy_error_deg: f64,
    /// Mean of the two FoV errors (degrees).
    pub fov_error_deg: f64,
    /// Per-pair errors.
    pub pairs: Vec<PairError>,
}

fn rt(m: &Matrix3x4<f64>) -> (Matrix3<f64>, Vector3<f64>) {
    (
        m.fixed_view::<3, 3>(0, 0).into_owned(),
        m.column(3).into_owned(),
    )
}

/// Relative pose `cam_i_from_cam_j = cam_from_world_i (cam_from_world_j)^-1`, with the inverse
/// taken as `[R^T | -R^T t]` (rigid closed form).
fn relative(a: &Matrix3x4<f64>, b: &Matrix3x4<f64>) -> (Matrix3<f64>, Vector3<f64>) {
    let (ra, ta) = rt(a);
    let (rb, tb) = rt(b);
    let rbt = rb.transpose();
    (ra * rbt, ta - ra * rbt * tb)
}

/// Rotation angle between two rotations, `arccos(clamp((trace(R_gt^T R_pred) - 1) / 2))`, degrees.
pub fn rotation_error_deg(r_gt: &Matrix3<f64>, r_pred: &Matrix3<f64>) -> f64 {
    let c = (((r_gt.transpose() * r_pred).trace() - 1.0) / 2.0).clamp(-1.0, 1.0);
    c.acos().to_degrees()
}

/// Sign-agnostic angle between two translation directions with the official formula
/// `arccos(sqrt(1 - max(1 - dot^2, 1e-15)))` on `t / (||t|| + 1e-15)`, degrees; NaN/inf -> 1e6.
pub fn translation_error_deg(t_gt: &Vector3<f64>, t_pred: &Vector3<f64>) -> f64 {
    let a = t_gt / (t_gt.norm() + TRANSLATION_NORM_EPS);
    let b = t_pred / (t_pred.norm() + TRANSLATION_NORM_EPS);
    let dot = a.dot(&b);
    // `clamp_min` semantics: NaN stays NaN (f64::max would drop it).
    let raw = 1.0 - dot * dot;
    let loss = if raw.is_nan() {
        raw
    } else {
        raw.max(TRANSLATION_LOSS_EPS)
    };
    let e = (1.0 - loss).sqrt().acos().to_degrees();
    if e.is_finite() {
        e
    } else {
        NON_FINITE_ERROR_DEG
    }
}

/// Errors of the relative poses of all pairs `i < j` (`pipeline.md` §10.3). `pred` and `gt` are
/// `cam_from_world` per view (each in its own world frame and scale; only relative poses and
/// translation directions are compared). Fails when the view counts differ.
pub fn relative_pose_errors(
    pred: &[Matrix3x4<f64>],
    gt: &[Matrix3x4<f64>],
) -> Result<Vec<PairError>> {
    if pred.len() != gt.len() {
        return Err(CoreError::Invalid(format!(
            "camera metrics: {} predicted views vs {} GT views",
            pred.len(),
            gt.len()
        )));
    }
    let mut out = Vec::new();
    for (i, (pi, gi)) in pred.iter().zip(gt.iter()).enumerate() {
        for (j, (pj, gj)) in pred.iter().zip(gt.iter()).enumerate().skip(i + 1) {
            let (r_pred, t_pred) = relative(pi, pj);
            let (r_gt, t_gt) = relative(gi, gj);
            let rot = rotation_error_deg(&r_gt, &r_pred);
            let rot = if rot.is_finite() {
                rot
            } else {
                NON_FINITE_ERROR_DEG
            };
            let trans = translation_error_deg(&t_gt, &t_pred);
            out.push(PairError {
                i,
                j,
                rot_deg: rot,
                trans_deg: trans,
                max_deg: rot.max(trans),
            });
        }
    }
    Ok(out)
}

/// Horizontal and vertical field of view of `K` in degrees: `2 atan(W / (2 fx))` with
/// `W = 2 (cx + 0.5)` (pixel-centre principal point), same for `y`.
pub fn fov_deg(k: &Matrix3<f64>) -> (f64, f64) {
    let w = 2.0 * (k[(0, 2)] + 0.5);
    let h = 2.0 * (k[(1, 2)] + 0.5);
    (
        (w / (2.0 * k[(0, 0)])).atan().to_degrees() * 2.0,
        (h / (2.0 * k[(1, 1)])).atan().to_degrees() * 2.0,
    )
}

/// Mean absolute FoV differences `(fovx, fovy)` between predicted and GT intrinsics, degrees.
pub fn fov_errors(pred: &[Matrix3<f64>], gt: &[Matrix3<f64>]) -> Result<(f64, f64)> {
    if pred.len() != gt.len() || pred.is_empty() {
        return Err(CoreError::Invalid(format!(
            "FoV error: {} predicted vs {} GT intrinsics",
            pred.len(),
            gt.len()
        )));
    }
    let (ex, ey): (Vec<f64>, Vec<f64>) = pred
        .iter()
        .zip(gt.iter())
        .map(|(a, b)| {
            let (ax, ay) = fov_deg(a);
            let (bx, by) = fov_deg(b);
            ((ax - bx).abs(), (ay - by).abs())
        })
        .unzip();
    Ok((mean(&ex), mean(&ey)))
}

/// Camera accuracy of `pred` against `gt` (`pipeline.md` §10.3). Needs at least 2 views.
pub fn camera_metrics(pred: &Cameras, gt: &Cameras) -> Result<CameraMetrics> {
    if pred.len() < 2 {
        return Err(CoreError::Invalid(format!(
            "camera metrics need at least 2 views, got {}",
            pred.len()
        )));
    }
    let pairs = relative_pose_errors(&pred.cam_from_world, &gt.cam_from_world)?;
    let (fovx, fovy) = fov_errors(&pred.intrinsics, &gt.intrinsics)?;
    let e: Vec<f64> = pairs.iter().map(|p| p.max_deg).collect();
    let rot: Vec<f64> = pairs.iter().map(|p| p.rot_deg).collect();
    let trans: Vec<f64> = pairs.iter().map(|p| p.trans_deg).collect();
    let [a1, a3, a5, a10] = AUC_THRESHOLDS;
    Ok(CameraMetrics {
        num_pairs: pairs.len(),
        auc_1: 100.0 * camera_auc(&e, a1),
        auc_3: 100.0 * camera_auc(&e, a3),
        auc_5: 100.0 * camera_auc(&e, a5),
        auc_10: 100.0 * camera_auc(&e, a10),
        rot_mean_deg: mean(&rot),
        trans_mean_deg: mean(&trans),
        fovx_error_deg: fovx,
        fovy_error_deg: fovy,
        fov_error_deg: 0.5 * (fovx + fovy),
        pairs,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Unit};

    const SFM_SMALL: &str = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../../shared/fixtures/sfm_small"
    );

    fn pose(r: Matrix3<f64>, t: Vector3<f64>) -> Matrix3x4<f64> {
        let mut m = Matrix3x4::zeros();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
        m.set_column(3, &t);
        m
    }

    fn k(f: f64, w: usize, h: usize) -> Matrix3<f64> {
        Matrix3::new(
            f,
            0.0,
            (w as f64 - 1.0) / 2.0,
            0.0,
            f,
            (h as f64 - 1.0) / 2.0,
            0.0,
            0.0,
            1.0,
        )
    }

    fn rig(n: usize) -> Cameras {
        let cam_from_world = (0..n)
            .map(|i| {
                let a = i as f64 * 0.2;
                pose(
                    *Rotation3::from_euler_angles(0.05 * a, a, 0.0).matrix(),
                    Vector3::new(-(i as f64), 0.1 * i as f64, 0.3),
                )
            })
            .collect();
        Cameras {
            cam_from_world,
            intrinsics: vec![k(50.0, 56, 42); n],
        }
    }

    #[test]
    fn gt_against_itself_is_perfect() {
        let gt = rig(5);
        let m = camera_metrics(&gt, &gt).unwrap();
        assert_eq!(m.num_pairs, 10);
        assert_eq!([m.auc_1, m.auc_3, m.auc_5, m.auc_10], [100.0; 4]);
        assert!(m.pairs.iter().all(|p| p.max_deg < 1e-5), "{:?}", m.pairs);
        assert_eq!(m.fov_error_deg, 0.0);
    }

    #[test]
    fn invariant_to_similarity_of_the_world() {
        let gt = rig(4);
        // pred = gt in another world frame with another scale: cam_from_world' = [R R_w^T | s t - ...]
        let rw = *Rotation3::from_euler_angles(0.4, -0.2, 1.0).matrix();
        let tw = Vector3::new(3.0, -1.0, 2.0);
        let s = 2.5;
        // world' = s Rw world + tw  =>  X_cam = R world + t = R Rw^T (world' - tw)/s + t
        // scale camera coordinates by s: cam' = s X_cam = R Rw^T world' - R Rw^T tw + s t
        let pred = Cameras {
            cam_from_world: gt
                .cam_from_world
                .iter()
                .map(|m| {
                    let (r, t) = rt(m);
                    pose(r * rw.transpose(), -(r * rw.transpose() * tw) + s * t)
                })
                .collect(),
            intrinsics: gt.intrinsics.clone(),
        };
        let m = camera_metrics(&pred, &gt).unwrap();
        assert!(m.pairs.iter().all(|p| p.max_deg < 1e-5), "{:?}", m.pairs);
    }

    #[test]
    fn hand_computed_errors() {
        // Two views: GT relative pose = identity rotation, baseline along x.
        let gt = Cameras {
            cam_from_world: vec![
                pose(Matrix3::identity(), Vector3::zeros()),
                pose(Matrix3::identity(), Vector3::new(-1.0, 0.0, 0.0)),
            ],
            intrinsics: vec![k(50.0, 56, 42); 2],
        };
        // Prediction: view 1 rotated by 2° about y, translation direction tilted by 4.5° and flipped.
        let r = *Rotation3::from_axis_angle(&Unit::new_normalize(Vector3::y()), 2f64.to_radians())
            .matrix();
        let a = 4.5f64.to_radians();
        let t_want = -Vector3::new(a.cos(), a.sin(), 0.0) * 3.0; // opposite sign of the GT direction
        // cam_0_from_cam_1 = (R0 R1^T, t0 - R0 R1^T t1); view 0 identity => (R1^T, -R1^T t1).
        // R1 = r^T, t1 = -r^T t_want gives the relative pose (r, t_want).
        let pred = Cameras {
            cam_from_world: vec![
                pose(Matrix3::identity(), Vector3::zeros()),
                pose(r.transpose(), -(r.transpose() * t_want)),
            ],
            intrinsics: vec![k(50.0, 56, 42), k(60.0, 56, 42)],
        };
        let pairs = relative_pose_errors(&pred.cam_from_world, &gt.cam_from_world).unwrap();
        assert_eq!(pairs.len(), 1);
        let p = pairs[0];
        assert!((p.rot_deg - 2.0).abs() < 1e-6, "{p:?}");
        assert!((p.trans_deg - 4.5).abs() < 1e-6, "{p:?}");
        assert_eq!(p.max_deg, p.trans_deg);
        // FoV: 2 atan(56 / 100) vs 2 atan(56 / 120) on view 1 only.
        let (fx, fy) = fov_errors(&pred.intrinsics, &gt.intrinsics).unwrap();
        let want_x = (2.0 * (56.0f64 / 100.0).atan().to_degrees()
            - 2.0 * (56.0f64 / 120.0).atan().to_degrees())
            / 2.0;
        let want_y = (2.0 * (42.0f64 / 100.0).atan().to_degrees()
            - 2.0 * (42.0f64 / 120.0).atan().to_degrees())
            / 2.0;
        assert!((fx - want_x).abs() < 1e-9 && (fy - want_y).abs() < 1e-9);
        let m = camera_metrics(&pred, &gt).unwrap();
        assert_eq!(m.auc_1, 0.0);
        // e = 4.5: counted from k = 5 on: AUC@5 = 1/5, AUC@10 = 6/10.
        assert!(
            (m.auc_5 - 20.0).abs() < 1e-6 && (m.auc_10 - 60.0).abs() < 1e-6,
            "{m:?}"
        );
    }

    #[test]
    fn degenerate_cases() {
        // Zero translation: the official formula gives 90°, never NaN.
        assert!((translation_error_deg(&Vector3::zeros(), &Vector3::x()) - 90.0).abs() < 1e-9);
        assert_eq!(
            translation_error_deg(&Vector3::new(f64::NAN, 0.0, 0.0), &Vector3::x()),
            NON_FINITE_ERROR_DEG
        );
        // Identical directions give the clamp floor, not exactly 0.
        let e = translation_error_deg(&Vector3::x(), &(Vector3::x() * 5.0));
        assert!(e > 0.0 && e < 1e-5);
        assert!(camera_metrics(&rig(1), &rig(1)).is_err());
        assert!(relative_pose_errors(&rig(2).cam_from_world, &rig(3).cam_from_world).is_err());
    }

    fn read(path: &str) -> Vec<u8> {
        std::fs::read(path).unwrap_or_else(|e| panic!("fixture {path} missing or unreadable: {e}"))
    }

    fn floats(st: &safetensors::SafeTensors<'_>, key: &str) -> Vec<f64> {
        let t = st
            .tensor(key)
            .unwrap_or_else(|e| panic!("tensor {key}: {e}"));
        match t.dtype() {
            safetensors::Dtype::F32 => t
                .data()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64)
                .collect(),
            safetensors::Dtype::F64 => t
                .data()
                .chunks_exact(8)
                .map(|b| f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]))
                .collect(),
            d => panic!("{key}: unexpected dtype {d:?}"),
        }
    }

    fn cams(
        st: &safetensors::SafeTensors<'_>,
        ext_key: &str,
        k_key: &str,
        ext_rows: usize,
        shared_k: bool,
    ) -> Cameras {
        let e = floats(st, ext_key);
        let kk = floats(st, k_key);
        let n = e.len() / (ext_rows * 4);
        let cam_from_world = (0..n)
            .map(|i| Matrix3x4::from_row_slice(&e[i * ext_rows * 4..i * ext_rows * 4 + 12]))
            .collect();
        let intrinsics = (0..n)
            .map(|i| {
                if shared_k {
                    Matrix3::from_row_slice(&kk[..9])
                } else {
                    Matrix3::from_row_slice(&kk[9 * i..9 * i + 9])
                }
            })
            .collect();
        Cameras {
            cam_from_world,
            intrinsics,
        }
    }

    /// Official `evaluation.eval_cameras` numbers on `sfm_small` (fixture README, "BA" section),
    /// rounded to 0.1 (AUC %) / 0.01 (FoV degrees).
    #[test]
    fn sfm_small_matches_official_eval_cameras() {
        let inputs_b = read(&format!("{SFM_SMALL}/inputs.safetensors"));
        let steps_b = read(&format!("{SFM_SMALL}/steps.safetensors"));
        let inputs = safetensors::SafeTensors::deserialize(&inputs_b).unwrap();
        let steps = safetensors::SafeTensors::deserialize(&steps_b).unwrap();
        let gt = cams(&inputs, "gt/cam_from_world", "gt/K", 4, true);
        let ff = cams(&inputs, "ff/extrinsics", "ff/intrinsics", 3, false);
        let sfm = cams(&steps, "ba/out_extrinsics", "ba/out_intrinsics", 3, false);
        for (name, pred, want) in [
            ("ff", &ff, [0.0, 5.6, 10.0, 33.3, 2.57, 2.22, 2.39]),
            ("sfm", &sfm, [0.0, 16.7, 43.3, 63.3, 3.69, 3.42, 3.55]),
        ] {
            let m = camera_metrics(pred, &gt).unwrap();
            let got = [m.auc_1, m.auc_3, m.auc_5, m.auc_10];
            for (g, w) in got.iter().zip(want.iter()) {
                assert!(
                    (g - w).abs() <= 0.05 + 1e-9,
                    "{name}: AUC {got:?} vs official {want:?}"
                );
            }
            let fov = [m.fovx_error_deg, m.fovy_error_deg, m.fov_error_deg];
            for (g, w) in fov.iter().zip(want[4..].iter()) {
                assert!(
                    (g - w).abs() <= 0.005 + 1e-9,
                    "{name}: FoV {fov:?} vs official {:?}",
                    &want[4..]
                );
            }
        }
    }
}
