//! Before / after evaluation of a refined scene against its ground truth (`pipeline.md` §10):
//! the unaligned feed-forward points ("init"), the SfM (DLT) points on `M_s ∧ V`, and the refined
//! points, each Sim(3)-aligned to the GT with the §3.1 estimator; cameras of the feed-forward
//! prediction and of the SfM stage. The one evaluation of a refinement: `ggpt-infer`
//! (`evaluation.json`, the demo table) and `ggpt-train eval` (held-out scenes) both call
//! [`evaluate_refinement`].

use ggpt_core::metrics::points::PointEvaluation;
use ggpt_core::metrics::{
    CameraMetrics, EVAL_ALIGN_MAX_ERROR, PointMetrics, camera_metrics, point_metrics,
};
use ggpt_core::{Scene, SfmResult};
use rand::SeedableRng;
use rand_pcg::Pcg64;

use crate::error::{EvalError, Result};

/// The evaluation JSON (`evaluation.json`). Point AUCs in percent of GT-valid pixels within
/// τ cm; camera AUCs in percent of view pairs within τ degrees.
#[derive(Debug, Clone, serde::Serialize)]
pub struct SceneEvaluation {
    /// Scene name.
    pub scene: String,
    /// Seed of the RANSAC generator (one fresh generator per evaluated prediction).
    pub seed: u64,
    /// Feed-forward points before refinement ("init", unaligned input).
    pub ff: PointMetrics,
    /// SfM (DLT) points, on `M_s ∧ V` only (`ratio` = covered fraction); `None` without DLT point.
    pub sfm: Option<PointMetrics>,
    /// The same SfM points over **all** GT-valid pixels, an uncovered pixel counting as a miss
    /// (the paper's supplementary Table 5 convention); `None` without DLT point.
    pub sfm_all_pixels: Option<AllPixelMetrics>,
    /// Refined points ("pred").
    pub refined: PointMetrics,
    /// Refined points on the SfM-covered pixels only (`M_s ∧ V`, aligned there, as `sfm`): the
    /// like-for-like comparison with the SfM points; `None` without DLT point.
    pub refined_on_sfm: Option<PointMetrics>,
    /// Feed-forward cameras.
    pub cameras_ff: Option<CameraMetrics>,
    /// SfM (bundle-adjusted) cameras, i.e. the cameras of the refined output.
    pub cameras_sfm: Option<CameraMetrics>,
    /// Non-fatal problems.
    pub warnings: Vec<String>,
}

/// Point accuracy over all GT-valid pixels of a prediction that covers only some of them
/// (the SfM points): uncovered pixels count as misses, so every recall, and therefore every AUC,
/// is the covered-pixel value times the coverage (same alignment).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct AllPixelMetrics {
    /// GT-valid pixels (the denominator).
    pub num_points: usize,
    /// Covered pixels / GT-valid pixels.
    pub coverage: f64,
    /// Recall@k cm for k = 1..=10 (percent of all GT-valid pixels).
    pub recall_pct: Vec<f64>,
    /// AUC@1 cm (percent).
    pub auc_1: f64,
    /// AUC@3 cm (percent).
    pub auc_3: f64,
    /// AUC@5 cm (percent).
    pub auc_5: f64,
    /// AUC@10 cm (percent).
    pub auc_10: f64,
}

impl AllPixelMetrics {
    /// From the covered-pixel metrics of a subset evaluation (`covered.ratio` is its coverage);
    /// `None` when `covered` has no ratio (not a subset evaluation) or an empty denominator.
    pub fn from_covered(covered: &PointMetrics) -> Option<Self> {
        let coverage = covered.ratio?;
        if !(coverage > 0.0 && coverage <= 1.0) {
            return None;
        }
        Some(Self {
            num_points: (covered.num_points as f64 / coverage).round() as usize,
            coverage,
            recall_pct: covered.recall_pct.iter().map(|r| r * coverage).collect(),
            auc_1: covered.auc_1 * coverage,
            auc_3: covered.auc_3 * coverage,
            auc_5: covered.auc_5 * coverage,
            auc_10: covered.auc_10 * coverage,
        })
    }
}

/// Full evaluation, with the per-pixel errors of the feed-forward and refined points (for the
/// error maps).
#[derive(Debug, Clone)]
pub struct EvaluationDetail {
    /// The summary written as JSON.
    pub summary: SceneEvaluation,
    /// Feed-forward points.
    pub ff: PointEvaluation,
    /// SfM (DLT) points on the pixels they cover; `None` when they could not be evaluated.
    pub sfm: Option<PointEvaluation>,
    /// Refined points.
    pub refined: PointEvaluation,
}

/// Evaluates the feed-forward, SfM and refined (`[N, h, w, 3]`, SfM frame) points of `scene`
/// against its GT (metres, GT frame). Errors when the scene has no ground truth.
pub fn evaluate_refinement(
    scene: &Scene,
    sfm: &SfmResult,
    refined_points: &[f32],
    seed: u64,
) -> Result<EvaluationDetail> {
    let gt = scene
        .gt
        .as_ref()
        .ok_or_else(|| EvalError::Invalid(format!("scene {} has no ground truth", scene.name)))?;
    let ff = scene.ff.as_ref().ok_or_else(|| {
        EvalError::Invalid(format!(
            "scene {} has no feed-forward prediction",
            scene.name
        ))
    })?;
    let eval = |pred: &[f32], subset: Option<&[bool]>| {
        let mut rng = Pcg64::seed_from_u64(seed);
        point_metrics(
            pred,
            &gt.points,
            &gt.mask,
            subset,
            EVAL_ALIGN_MAX_ERROR,
            &mut rng,
        )
    };
    let mut warnings = Vec::new();
    let ff_ev = eval(&ff.points, None).map_err(|source| EvalError::Metric {
        what: format!("{}: feed-forward point accuracy", scene.name),
        source,
    })?;
    let refined_ev = eval(refined_points, None).map_err(|source| EvalError::Metric {
        what: format!("{}: refined point accuracy", scene.name),
        source,
    })?;
    let sfm_ev = match eval(&sfm.points, Some(&sfm.mask)) {
        Ok(e) => Some(e),
        Err(e) => {
            warnings.push(format!("SfM points not evaluated: {e}"));
            None
        }
    };
    let sfm_metrics = sfm_ev.as_ref().map(|e| e.metrics.clone());
    let sfm_all_pixels = sfm_metrics.as_ref().and_then(AllPixelMetrics::from_covered);
    let refined_on_sfm = match sfm_metrics {
        Some(_) => match eval(refined_points, Some(&sfm.mask)) {
            Ok(e) => Some(e.metrics),
            Err(e) => {
                warnings.push(format!(
                    "refined points on the SfM pixels not evaluated: {e}"
                ));
                None
            }
        },
        None => None,
    };
    let mut cams = |what: &str, c: &ggpt_core::Cameras| match camera_metrics(c, &gt.cameras) {
        Ok(m) => Some(m),
        Err(e) => {
            warnings.push(format!("{what} cameras not evaluated: {e}"));
            None
        }
    };
    let cameras_ff = cams("feed-forward", &ff.cameras);
    let cameras_sfm = cams("SfM", &sfm.cameras);
    for w in &warnings {
        tracing::warn!("{w}");
    }
    let summary = SceneEvaluation {
        scene: scene.name.clone(),
        seed,
        ff: ff_ev.metrics.clone(),
        sfm: sfm_metrics,
        sfm_all_pixels,
        refined: refined_ev.metrics.clone(),
        refined_on_sfm,
        cameras_ff,
        cameras_sfm,
        warnings,
    };
    Ok(EvaluationDetail {
        summary,
        ff: ff_ev,
        sfm: sfm_ev,
        refined: refined_ev,
    })
}

/// The before / after table printed by `ggpt-infer demo` and `run`.
pub fn format_refinement_table(ev: &SceneEvaluation) -> String {
    let mut s = format!(
        "{:<22} {:>8} {:>7} {:>7} {:>7} {:>7} {:>9} {:>7}\n",
        "points", "pixels", "AUC@1", "AUC@3", "AUC@5", "AUC@10", "median cm", "ratio"
    );
    let row = |name: &str, m: &PointMetrics| {
        let ratio = m
            .ratio
            .map_or("-".to_string(), |r| format!("{:.1}%", 100.0 * r));
        format!(
            "{:<22} {:>8} {:>7.2} {:>7.2} {:>7.2} {:>7.2} {:>9.3} {:>7}\n",
            name, m.num_points, m.auc_1, m.auc_3, m.auc_5, m.auc_10, m.median_cm, ratio
        )
    };
    s.push_str(&row("feed-forward (before)", &ev.ff));
    if let Some(m) = &ev.sfm_all_pixels {
        s.push_str(&format!(
            "{:<22} {:>8} {:>7.2} {:>7.2} {:>7.2} {:>7.2} {:>9} {:>7}\n",
            "SfM / DLT, all pixels",
            m.num_points,
            m.auc_1,
            m.auc_3,
            m.auc_5,
            m.auc_10,
            "-",
            format!("{:.1}%", 100.0 * m.coverage)
        ));
    }
    s.push_str(&row("GGPT refined (after)", &ev.refined));
    if let Some(m) = &ev.sfm {
        s.push_str("\non the SfM-covered pixels only (each aligned there):\n");
        s.push_str(&row("SfM / DLT points", m));
    }
    if let Some(m) = &ev.refined_on_sfm {
        s.push_str(&row("GGPT refined", m));
    }
    s.push_str(&format!(
        "\n{:<22} {:>8} {:>7} {:>7} {:>7} {:>7}\n",
        "cameras", "pairs", "AUC@1", "AUC@3", "AUC@5", "AUC@10"
    ));
    for (name, c) in [
        ("feed-forward", &ev.cameras_ff),
        ("SfM (refined output)", &ev.cameras_sfm),
    ] {
        if let Some(c) = c {
            s.push_str(&format!(
                "{:<22} {:>8} {:>7.2} {:>7.2} {:>7.2} {:>7.2}\n",
                name, c.num_pairs, c.auc_1, c.auc_3, c.auc_5, c.auc_10
            ));
        }
    }
    s.push_str("point AUC@τ: % of GT pixels within τ cm after robust Sim(3) alignment to the GT (pipeline.md §10.2);\n");
    s.push_str("\"all pixels\" counts a pixel without an SfM point as a miss (AUC = covered AUC x coverage);\n");
    s.push_str("ratio: evaluated / GT-valid pixels; camera AUC@τ in degrees (§10.3).\n");
    s
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use ggpt_core::sim3::AlignMethod;

    fn covered(ratio: Option<f64>) -> PointMetrics {
        PointMetrics {
            num_points: 300,
            recall_pct: (1..=10).map(|k| 10.0 * k as f64).collect(),
            auc_1: 20.0,
            auc_3: 40.0,
            auc_5: 60.0,
            auc_10: 80.0,
            mean_cm: 1.0,
            median_cm: 0.5,
            ratio,
            align: AlignMethod::PlainUmeyama,
            align_inliers: None,
            gt_from_pred: [
                [1.0, 0.0, 0.0, 0.0],
                [0.0, 1.0, 0.0, 0.0],
                [0.0, 0.0, 1.0, 0.0],
            ],
        }
    }

    /// Uncovered pixels are misses: recalls and AUCs scale with the coverage.
    #[test]
    fn all_pixel_metrics_count_uncovered_pixels_as_misses() {
        let m = AllPixelMetrics::from_covered(&covered(Some(0.25))).unwrap();
        assert_eq!(m.num_points, 1200);
        assert_eq!(m.coverage, 0.25);
        assert_eq!(
            (m.auc_1, m.auc_3, m.auc_5, m.auc_10),
            (5.0, 10.0, 15.0, 20.0)
        );
        assert_eq!(m.recall_pct[9], 25.0);
        assert!(AllPixelMetrics::from_covered(&covered(None)).is_none());
        assert!(AllPixelMetrics::from_covered(&covered(Some(0.0))).is_none());
    }
}
