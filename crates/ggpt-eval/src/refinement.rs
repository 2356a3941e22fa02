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
    /// Refined points ("pred").
    pub refined: PointMetrics,
    /// Feed-forward cameras.
    pub cameras_ff: Option<CameraMetrics>,
    /// SfM (bundle-adjusted) cameras, i.e. the cameras of the refined output.
    pub cameras_sfm: Option<CameraMetrics>,
    /// Non-fatal problems.
    pub warnings: Vec<String>,
}

/// Full evaluation, with the per-pixel errors of the feed-forward and refined points (for the
/// error maps).
#[derive(Debug, Clone)]
pub struct EvaluationDetail {
    /// The summary written as JSON.
    pub summary: SceneEvaluation,
    /// Feed-forward points.
    pub ff: PointEvaluation,
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
    let sfm_metrics = match eval(&sfm.points, Some(&sfm.mask)) {
        Ok(e) => Some(e.metrics),
        Err(e) => {
            warnings.push(format!("SfM points not evaluated: {e}"));
            None
        }
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
        refined: refined_ev.metrics.clone(),
        cameras_ff,
        cameras_sfm,
        warnings,
    };
    Ok(EvaluationDetail {
        summary,
        ff: ff_ev,
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
    if let Some(m) = &ev.sfm {
        s.push_str(&row("SfM / DLT points", m));
    }
    s.push_str(&row("GGPT refined (after)", &ev.refined));
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
    s.push_str("SfM points are evaluated on the pixels that have one (ratio); camera AUC@τ in degrees (§10.3).\n");
    s
}
