//! Validation: chunk-level point accuracy during training, and the whole-scene refinement of
//! held-out scenes through `ggpt_scene::refine_scene` with the official metrics
//! (`pipeline.md` §10.2: robust Sim(3) of the prediction onto GT, AUC@τ cm).

use burn::module::Module;
use burn::tensor::Device;
use ggpt_core::metrics::{auc_from_recalls, recalls_strict};
use ggpt_core::{Scene, SfmResult};
use ggpt_model::{Ggpt, GgptConfig};
use ggpt_scene::driver::{ChunkRefiner, RefineOptions, refine_scene};
use serde::{Deserialize, Serialize};

use crate::chunkset::{SceneEntry, TrainChunk};
use crate::error::{Result, TrainError};
use crate::loss::{HostTargets, loss};

/// Chunk-level validation result: AUC of the refined and of the input (aligned feed-forward)
/// points against the aligned GT, errors converted to cm with the scene's metres-per-unit
/// (no re-alignment: the chunk frame is the SfM frame).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChunkValidation {
    /// Chunks evaluated.
    pub chunks: usize,
    /// Validation loss (mean over forwards).
    pub loss: f64,
    /// AUC@5 cm of the input points (percent).
    pub input_auc5: f64,
    /// AUC@10 cm of the input points (percent).
    pub input_auc10: f64,
    /// AUC@5 cm of the refined points (percent).
    pub refined_auc5: f64,
    /// AUC@10 cm of the refined points (percent).
    pub refined_auc10: f64,
}

fn aucs(errors_cm: &[f64]) -> Result<(f64, f64)> {
    let rec = recalls_strict(errors_cm, 10);
    Ok((
        100.0 * auc_from_recalls(&rec, 5)?,
        100.0 * auc_from_recalls(&rec, 10)?,
    ))
}

/// Runs the network in evaluation mode (BatchNorm running statistics, no drop path) on
/// `chunks` in forwards of at most `max_tokens` tokens and measures the point accuracy.
pub fn validate_chunks(
    model: &Ggpt,
    cfg: &GgptConfig,
    chunks: &[TrainChunk],
    scenes: &[SceneEntry],
    device: &Device,
    max_tokens: usize,
) -> Result<ChunkValidation> {
    let model = model.valid().fork(device);
    let (mut e_in, mut e_out) = (Vec::new(), Vec::new());
    let (mut loss_sum, mut forwards) = (0.0, 0usize);
    let mut start = 0;
    while start < chunks.len() {
        let mut end = start + 1;
        let mut tokens = chunks[start].num_tokens();
        while end < chunks.len() && tokens + chunks[end].num_tokens() <= max_tokens {
            tokens += chunks[end].num_tokens();
            end += 1;
        }
        let group: Vec<&TrainChunk> = chunks[start..end].iter().collect();
        let batch = ggpt_model::infer::prepare_chunks(cfg, &group, device)?;
        let out = model.forward(&batch);
        let parts = loss(
            out.tokens_xyz.clone(),
            out.tokens_conf.clone(),
            &HostTargets::new(&group).upload(device),
        );
        loss_sum += ggpt_model::readback::read_tensor_f32(&parts.total, "val loss")?
            .first()
            .copied()
            .unwrap_or(f32::NAN) as f64;
        forwards += 1;
        for (c, o) in group.iter().zip(out.to_chunks(&batch)?) {
            let mpu = scenes
                .get(c.scene)
                .map(|s| s.metres_per_unit)
                .ok_or_else(|| {
                    TrainError::Invalid(format!("chunk of unknown scene {}", c.scene))
                })?;
            let to_cm = c.radius * mpu * 100.0;
            for i in 0..c.len() {
                if !c.gt_msk[i] {
                    continue;
                }
                let g = c.gt_pts[i];
                let d = |p: [f32; 3]| {
                    (((p[0] - g[0]) as f64).powi(2)
                        + ((p[1] - g[1]) as f64).powi(2)
                        + ((p[2] - g[2]) as f64).powi(2))
                    .sqrt()
                        * to_cm
                };
                e_in.push(d(c.ff_pts[i]));
                e_out.push(d(o.ff_pts_out[i]));
            }
        }
        start = end;
    }
    let (i5, i10) = aucs(&e_in)?;
    let (r5, r10) = aucs(&e_out)?;
    Ok(ChunkValidation {
        chunks: chunks.len(),
        loss: loss_sum / forwards.max(1) as f64,
        input_auc5: i5,
        input_auc10: i10,
        refined_auc5: r5,
        refined_auc10: r10,
    })
}

/// Seed of the RANSAC generator of the held-out evaluation (`pipeline.md` §10.2).
pub const HELD_OUT_EVAL_SEED: u64 = 42;

/// Whole-scene result of one held-out scene: the summary of [`ggpt_eval::evaluate_refinement`]
/// (the same evaluation as `ggpt-infer`'s `evaluation.json`) and the chunk coverage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HeldOutScene {
    /// Scene name.
    pub name: String,
    /// AUC@5 cm of the feed-forward input ("init", unaligned; percent).
    pub ff_auc5: f64,
    /// AUC@10 cm of the feed-forward input.
    pub ff_auc10: f64,
    /// AUC@5 cm of the refined points ("pred").
    pub refined_auc5: f64,
    /// AUC@10 cm of the refined points.
    pub refined_auc10: f64,
    /// AUC@5 of the DLT points on `M_s ∧ V` (for reference); `None` when the scene has none
    /// to evaluate.
    pub sfm_auc5: Option<f64>,
    /// AUC@5 of the DLT points over all GT pixels, uncovered ones counted as misses (the
    /// paper's convention, [`ggpt_eval::AllPixelMetrics`]).
    #[serde(default)]
    pub sfm_all_auc5: Option<f64>,
    /// Fraction of GT pixels with a DLT point.
    #[serde(default)]
    pub sfm_coverage: Option<f64>,
    /// AUC@5 of the refined points on the DLT-covered pixels (aligned there, as `sfm_auc5`).
    #[serde(default)]
    pub refined_on_sfm_auc5: Option<f64>,
    /// Fraction of GT pixels covered by at least one chunk.
    pub covered: f64,
    /// Chunks.
    pub chunks: usize,
}

/// Means of [`HeldOutScene`]s over the evaluated scenes (`ggpt-train eval`'s summary).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HeldOutSummary {
    /// Scenes averaged.
    pub scenes: usize,
    /// Mean feed-forward AUC@5 cm.
    pub ff_auc5: f64,
    /// Mean feed-forward AUC@10 cm.
    pub ff_auc10: f64,
    /// Mean refined AUC@5 cm.
    pub refined_auc5: f64,
    /// Mean refined AUC@10 cm.
    pub refined_auc10: f64,
    /// Mean DLT AUC@5 over the scenes that have one (`None`: no scene has one).
    pub sfm_auc5: Option<f64>,
    /// Mean DLT AUC@5 over all GT pixels (uncovered = miss), over the scenes that have one.
    #[serde(default)]
    pub sfm_all_auc5: Option<f64>,
    /// Mean refined AUC@5 on the DLT-covered pixels, over the scenes that have one.
    #[serde(default)]
    pub refined_on_sfm_auc5: Option<f64>,
}

impl HeldOutSummary {
    /// The means over `results`; `None` when there is no result.
    pub fn of(results: &[HeldOutScene]) -> Option<Self> {
        if results.is_empty() {
            return None;
        }
        let n = results.len() as f64;
        let mean = |f: fn(&HeldOutScene) -> f64| results.iter().map(f).sum::<f64>() / n;
        let mean_of = |f: fn(&HeldOutScene) -> Option<f64>| {
            let v: Vec<f64> = results.iter().filter_map(f).collect();
            (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
        };
        Some(HeldOutSummary {
            scenes: results.len(),
            ff_auc5: mean(|r| r.ff_auc5),
            ff_auc10: mean(|r| r.ff_auc10),
            refined_auc5: mean(|r| r.refined_auc5),
            refined_auc10: mean(|r| r.refined_auc10),
            sfm_auc5: mean_of(|r| r.sfm_auc5),
            sfm_all_auc5: mean_of(|r| r.sfm_all_auc5),
            refined_on_sfm_auc5: mean_of(|r| r.refined_on_sfm_auc5),
        })
    }

    /// One line: `mean over N held-out scenes: AUC@5 a -> b (+d), AUC@10 ...`, then the DLT
    /// points over all pixels and the like-for-like comparison on the DLT pixels when known.
    pub fn describe(&self) -> String {
        let mut s = format!(
            "mean over {} held-out scenes: AUC@5 {:.1} -> {:.1} ({:+.1}), AUC@10 {:.1} -> {:.1} ({:+.1})",
            self.scenes,
            self.ff_auc5,
            self.refined_auc5,
            self.refined_auc5 - self.ff_auc5,
            self.ff_auc10,
            self.refined_auc10,
            self.refined_auc10 - self.ff_auc10
        );
        if let Some(all) = self.sfm_all_auc5 {
            s.push_str(&format!("; DLT AUC@5 over all pixels {all:.1}"));
        }
        if let (Some(dlt), Some(refined)) = (self.sfm_auc5, self.refined_on_sfm_auc5) {
            s.push_str(&format!(
                "; on the DLT pixels: DLT {dlt:.1}, refined {refined:.1}"
            ));
        }
        s
    }
}

impl HeldOutScene {
    /// One table row: name, feed-forward and refined AUC@5/10, DLT AUC@5, coverage, chunks.
    pub fn describe(&self) -> String {
        format!(
            "{:<28} ff AUC@5 {:5.1} AUC@10 {:5.1} | refined AUC@5 {:5.1} AUC@10 {:5.1} | DLT AUC@5 {} (all pixels {}, coverage {}) | refined on DLT pixels {} | covered {:.2} | {} chunks",
            self.name,
            self.ff_auc5,
            self.ff_auc10,
            self.refined_auc5,
            self.refined_auc10,
            opt(self.sfm_auc5),
            opt(self.sfm_all_auc5),
            self.sfm_coverage
                .map_or("-".to_string(), |c| format!("{:.1}%", 100.0 * c)),
            opt(self.refined_on_sfm_auc5),
            self.covered,
            self.chunks
        )
    }
}

/// `{v:5.1}`, or `    -` for `None`.
fn opt(v: Option<f64>) -> String {
    v.map_or("    -".to_string(), |v| format!("{v:5.1}"))
}

/// Refines a held-out scene with `refiner` (`pipeline.md` §3-§8) and evaluates the input and
/// the refined points against GT with [`ggpt_eval::evaluate_refinement`] (seed
/// [`HELD_OUT_EVAL_SEED`]).
pub fn evaluate_scene(
    scene: &Scene,
    sfm: &SfmResult,
    refiner: &mut dyn ChunkRefiner,
    opts: &RefineOptions,
) -> Result<HeldOutScene> {
    let gt = scene
        .gt
        .as_ref()
        .ok_or_else(|| TrainError::Invalid(format!("scene {}: no GT", scene.name)))?;
    let refined = refine_scene(scene, sfm, refiner, opts)?;
    let ev =
        ggpt_eval::evaluate_refinement(scene, sfm, &refined.points, HELD_OUT_EVAL_SEED)?.summary;
    let n_gt = gt.mask.iter().filter(|&&m| m).count().max(1);
    let cov = gt
        .mask
        .iter()
        .zip(&refined.covered)
        .filter(|(g, c)| **g && **c)
        .count();
    Ok(HeldOutScene {
        name: scene.name.clone(),
        ff_auc5: ev.ff.auc_5,
        ff_auc10: ev.ff.auc_10,
        refined_auc5: ev.refined.auc_5,
        refined_auc10: ev.refined.auc_10,
        sfm_auc5: ev.sfm.map(|m| m.auc_5),
        sfm_all_auc5: ev.sfm_all_pixels.as_ref().map(|m| m.auc_5),
        sfm_coverage: ev.sfm_all_pixels.as_ref().map(|m| m.coverage),
        refined_on_sfm_auc5: ev.refined_on_sfm.map(|m| m.auc_5),
        covered: cov as f64 / n_gt as f64,
        chunks: refined.chunks.len(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn held_out_summary_means() {
        let r = |name: &str, a: f64, sfm: Option<f64>| HeldOutScene {
            name: name.into(),
            ff_auc5: a,
            ff_auc10: a + 10.0,
            refined_auc5: a + 20.0,
            refined_auc10: a + 30.0,
            sfm_auc5: sfm,
            sfm_all_auc5: sfm.map(|v| v / 2.0),
            sfm_coverage: sfm.map(|_| 0.5),
            refined_on_sfm_auc5: sfm.map(|v| v + 1.0),
            covered: 1.0,
            chunks: 3,
        };
        assert_eq!(HeldOutSummary::of(&[]), None);
        let s = HeldOutSummary::of(&[r("a", 10.0, Some(50.0)), r("b", 20.0, None)]).unwrap();
        assert_eq!((s.scenes, s.ff_auc5, s.refined_auc10), (2, 15.0, 45.0));
        assert_eq!(s.sfm_auc5, Some(50.0));
        assert!(
            s.describe().contains("AUC@5 15.0 -> 35.0 (+20.0)"),
            "{}",
            s.describe()
        );
        assert_eq!(
            (s.sfm_all_auc5, s.refined_on_sfm_auc5),
            (Some(25.0), Some(51.0))
        );
        assert!(
            s.describe().contains(
                "DLT AUC@5 over all pixels 25.0; on the DLT pixels: DLT 50.0, refined 51.0"
            ),
            "{}",
            s.describe()
        );
        assert!(r("a", 1.0, None).describe().contains("DLT AUC@5     -"));
        assert!(
            r("a", 1.0, Some(40.0)).describe().contains(
                "DLT AUC@5  40.0 (all pixels  20.0, coverage 50.0%) | refined on DLT pixels  41.0"
            ),
            "{}",
            r("a", 1.0, Some(40.0)).describe()
        );
    }
}
