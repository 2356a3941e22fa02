//! Evaluation of point maps and cameras against ground truth (`pipeline.md` §10,
//! `docs/evaluation.md`): the one owner of "how a scene is evaluated", used by the `ggpt-eval`
//! binary, by `ggpt-infer` (`evaluation.json`, the demo table) and by `ggpt-train eval`.
//!
//! * [`report`]: one prediction of a scene (`ff`, `sfm`, `gt` or a file) against its GT:
//!   point, depth and camera accuracy ([`report::evaluate_scene`], [`report::EvalReport`]);
//! * [`refinement`]: a refined scene before / after, i.e. the feed-forward input, the SfM
//!   points and the refined points, each Sim(3)-aligned to the GT with the same estimator and
//!   threshold ([`refinement::evaluate_refinement`], [`refinement::SceneEvaluation`]);
//! * [`error_maps`]: per-view error-map images of a refinement (input, feed-forward, SfM and
//!   refined errors on one colour scale), drawn on a [`figure::Canvas`] in the embedded font
//!   ([`figure::FONT_TTF`], shared with `ggpt-train plot`).
//!
//! Frames and units: predictions in their own frame (any scale), GT in metres; every metric
//! aligns the prediction to the GT first, and reports point errors in cm, camera errors in
//! degrees.

pub mod error;
pub mod error_maps;
pub mod figure;
pub mod refinement;
pub mod report;

pub use error::{EvalError, Result};
pub use refinement::{
    AllPixelMetrics, EvaluationDetail, SceneEvaluation, evaluate_refinement,
    format_refinement_table,
};
pub use report::{CameraSource, EvalReport, PredSource, evaluate_scene};
