//! Building training chunks from scenes (`pipeline.md` §11.1-§11.2).
//!
//! Per scene: the dense feed-forward points are Sim(3)-pre-aligned into the SfM frame (§3), the
//! GT points are Sim(3)-aligned into the SfM frame on `gt_msk ∧ M_s` and zeroed where invalid
//! (§11.1), the scene radius `R` is computed on the aligned points (§4), then independent
//! training chunks are drawn (§11.2: centre = uniform DLT pixel, `r = chunk_size R`, shrink
//! while over `max_pixels`, accept with enough DLT pixels and pixels, up to 10 draws) and
//! normalised into the chunk frame (§6), all with the `ggpt-scene` building blocks.
//!
//! Sources: synthetic scenes (`ggpt-synth` + the `ggpt-sfm` stage) and official per-sequence
//! directories (`gt.bin`, `ff_outputs.bin`, `sfm_dlt_outputs.bin`).

use ggpt_core::{Scene, SfmResult};
use ggpt_scene::chunker::{ChunkInputs, ChunkParams, PcgDraws, sample_training_chunk};
use ggpt_scene::prealign::{DEFAULT_ALIGN_MAX_ERROR, align_gt, prealign_ff};
use ggpt_scene::radius::{RadiusRule, scene_radius};
use ggpt_scene::record::{ChunkRecord, RecordSources};
use rand::SeedableRng;
use serde::{Deserialize, Serialize};

use crate::chunkset::TrainChunk;
use crate::error::{Result, TrainError};
use ggpt_core::chunk_input::ChunkInput;

/// Parameters of training-chunk extraction.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PrepareParams {
    /// Chunks drawn per scene.
    pub chunks_per_scene: usize,
    /// Sampler parameters (half-size fraction 0.2, pixel cap, minimum counts).
    pub chunking: ChunkParams,
    /// Scene radius rule.
    pub radius_rule: RadiusRule,
    /// RANSAC threshold of both Sim(3) alignments (SfM-frame units).
    pub align_max_error: f64,
    /// Seed of the RANSAC and chunk draws (combined with the scene name).
    pub seed: u64,
}

impl Default for PrepareParams {
    fn default() -> Self {
        Self {
            chunks_per_scene: 8,
            chunking: ChunkParams::default(),
            radius_rule: RadiusRule::AcrossViews,
            align_max_error: DEFAULT_ALIGN_MAX_ERROR,
            seed: 42,
        }
    }
}

/// Training chunks of one scene plus the scale of its GT alignment.
#[derive(Debug, Clone)]
pub struct PreparedScene {
    /// The chunks (scene index left at 0: the caller sets it).
    pub chunks: Vec<TrainChunk>,
    /// Metres per SfM unit (`1 / s` of the GT -> SfM similarity).
    pub metres_per_unit: f64,
    /// Scene radius `R` (SfM units).
    pub radius: f64,
}

/// Extracts training chunks from a scene with feed-forward prediction, GT and SfM result.
/// Frames: `scene.ff` in the feed-forward frame, `sfm` in the SfM frame, GT in metres; all
/// chunk arrays are normalised SfM-frame coordinates.
pub fn prepare_scene(
    scene: &Scene,
    sfm: &SfmResult,
    params: &PrepareParams,
) -> Result<PreparedScene> {
    let name = &scene.name;
    let ff = scene
        .ff
        .as_ref()
        .ok_or_else(|| TrainError::Invalid(format!("scene {name}: no feed-forward prediction")))?;
    let gt = scene
        .gt
        .as_ref()
        .ok_or_else(|| TrainError::Invalid(format!("scene {name}: no ground truth")))?;
    if !sfm.mask.iter().any(|&m| m) {
        return Err(TrainError::Invalid(format!(
            "scene {name}: the SfM result has no DLT point"
        )));
    }
    let seed = params.seed ^ ggpt_scene::chunker::scene_seed(name);
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let pre = prealign_ff(
        &ff.points,
        &sfm.points,
        &sfm.mask,
        params.align_max_error,
        &mut rng,
    )?;
    let gt_al = align_gt(
        &gt.points,
        &gt.mask,
        &sfm.points,
        &sfm.mask,
        params.align_max_error,
        &mut rng,
    )?;
    let s = gt_al.tgt_from_src.scale;
    if !(s.is_finite() && s > 0.0) {
        return Err(TrainError::Invalid(format!(
            "scene {name}: GT alignment scale {s} is not positive"
        )));
    }
    let radius = scene_radius(&pre.aligned, scene.dims, params.radius_rule, None)?.radius;
    let inputs = ChunkInputs {
        ff_points: &pre.aligned,
        dlt_points: &sfm.points,
        dlt_mask: &sfm.mask,
        roi: None,
    };
    let sources = RecordSources {
        ff_points: &pre.aligned,
        ff_conf: &ff.conf,
        dlt_points: &sfm.points,
        dlt_mask: &sfm.mask,
        images: &scene.images,
        gt: Some((&gt_al.aligned, &gt.mask)),
    };
    let mut draws = PcgDraws::new(seed.wrapping_add(1));
    let mut chunks = Vec::with_capacity(params.chunks_per_scene);
    for _ in 0..params.chunks_per_scene {
        let Some(chunk) = sample_training_chunk(inputs, radius, &params.chunking, &mut draws)?
        else {
            tracing::warn!(
                "scene {name}: no acceptable training chunk in 10 draws; skipping the rest of the scene"
            );
            break;
        };
        let rec = ChunkRecord::build(&chunk, &sources)?;
        chunks.push(from_record(rec, 0)?);
    }
    Ok(PreparedScene {
        chunks,
        metres_per_unit: 1.0 / s,
        radius,
    })
}

/// Converts a `ggpt-scene` record with GT into a [`TrainChunk`]; DLT-less rows of `geo_pts`
/// are zeroed.
pub fn from_record(rec: ChunkRecord, scene: usize) -> Result<TrainChunk> {
    let gt = rec
        .gt
        .ok_or_else(|| TrainError::Invalid(format!("chunk {}: record without GT", rec.index)))?;
    let input = rec.input;
    let geo_pts = input
        .geo_pts
        .iter()
        .zip(&input.geo_msk)
        .map(|(p, &m)| if m { *p } else { [0.0; 3] })
        .collect();
    Ok(TrainChunk {
        scene,
        center: rec.center,
        radius: rec.radius,
        pixels: rec.pixels,
        input: ChunkInput {
            ff_pts: input.ff_pts,
            ff_conf: input.ff_conf,
            geo_pts,
            geo_msk: input.geo_msk,
        },
        gt_pts: gt.pts,
        gt_msk: gt.msk,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene_source::{SynthSpec, synthetic_scene};

    #[test]
    fn synthetic_scene_gives_normalised_chunks_with_gt() {
        let spec = SynthSpec {
            kind: ggpt_synth::SceneKind::Room,
            views: 3,
            width: 84,
            height: 56,
            seed: 3,
            regime: ggpt_synth::Regime::Benchmark,
        };
        let (scene, sfm) = synthetic_scene(&spec).unwrap();
        let params = PrepareParams {
            chunks_per_scene: 3,
            chunking: ChunkParams {
                max_pixels: 3000,
                min_dlt: 20,
                min_pixels: 100,
                ..ChunkParams::default()
            },
            ..PrepareParams::default()
        };
        let prep = prepare_scene(&scene, &sfm, &params).unwrap();
        assert!(!prep.chunks.is_empty());
        assert!(prep.metres_per_unit > 0.0 && prep.radius > 0.0);
        for c in &prep.chunks {
            c.validate().unwrap();
            assert!(c.len() <= 3000);
            // the centre pixel's DLT point is at the origin
            assert!(
                c.geo_pts
                    .iter()
                    .zip(&c.geo_msk)
                    .any(|(p, &m)| m && p.iter().all(|v| v.abs() < 1e-6))
            );
            // GT and dense points live on the same scale: median |ff - gt| well below the cube size
            let mut d: Vec<f32> = c
                .ff_pts
                .iter()
                .zip(&c.gt_pts)
                .zip(&c.gt_msk)
                .filter(|(_, m)| **m)
                .map(|((a, b), _)| {
                    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
                })
                .collect();
            d.sort_by(f32::total_cmp);
            assert!(
                d[d.len() / 2] < 0.5,
                "median |ff - gt| = {}",
                d[d.len() / 2]
            );
        }
    }
}
