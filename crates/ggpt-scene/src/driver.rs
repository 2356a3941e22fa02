//! Whole-scene refinement (`pipeline.md` §3-§8): pre-align, radius, chunk sampling, per-chunk
//! records, network forwards batched by a token budget, un-normalisation and streaming fusion.
//!
//! The network is behind the [`ChunkRefiner`] trait so this crate stays free of Burn; the model
//! crate (or a test mock) implements it. Chunks are processed in sampling order and results are
//! placed by chunk index, so the batching never changes the output (`pipeline.md` §7).
//!
//! Edge cases (`pipeline.md` §13): inconsistent sizes / view counts -> error; NaN / inf in the
//! inputs -> error naming the array and the first bad flat index; no DLT point -> error unless
//! `allow_unrefined` (then the unaligned feed-forward points with confidence 0); Sim(3) failure ->
//! identity with a warning; no accepted chunk -> aligned feed-forward points with their
//! feed-forward confidence and a warning.

use ggpt_core::sim3::AlignMethod;
use ggpt_core::{Cameras, Dims, Progress, Scene, SfmResult};
use nalgebra::Matrix3x4;
use rand::SeedableRng;

use crate::chunker::{ChunkInputs, ChunkParams, PcgDraws, StopReason, sample_chunks};
use crate::error::{SceneError, check_finite, check_len};
use crate::fusion::{FusionAccumulator, FusionMode};
use crate::prealign::{DEFAULT_ALIGN_MAX_ERROR, prealign_ff};
use crate::radius::{RadiusRule, SceneRadius, scene_radius};
use crate::record::{ChunkRecord, RecordSources, unnormalise};
use crate::roi::RegionOfInterest;

/// Default token budget of one network forward ([project]). Memory follows the tokens of the
/// *deep* levels: small chunks are sparse in their unit cube and pool little, so a batch of many
/// small chunks keeps most of its tokens down to enc3 / enc4 (released configuration, the
/// `infer` bench of `ggpt-infer`: 11.1 GB for 800k such tokens of a 4-view scene, 6-10.5 GB for
/// 400k), while one dense chunk pools well (2.8 GB for 400k tokens). Forward time is linear in the
/// batch, so smaller batches cost no throughput; a chunk larger than the budget runs alone.
pub const DEFAULT_MAX_TOKENS_PER_FORWARD: usize = 400_000;
/// Default seed of the RANSAC sampler (project-wide default seed).
pub const DEFAULT_SEED: u64 = 42;

/// The network, seen from the pipeline.
pub trait ChunkRefiner {
    /// Refines a batch of normalised chunk records; returns, per chunk and in the same order,
    /// the dense points `[K, 3]` in **chunk coordinates** and their confidence `[K]`.
    fn refine(&mut self, chunks: &[ChunkRecord]) -> Result<Vec<RefinedChunk>, SceneError>;
}

/// Network output of one chunk (chunk frame).
#[derive(Debug, Clone, PartialEq)]
pub struct RefinedChunk {
    /// Refined dense points, normalised chunk coordinates, one per chunk pixel.
    pub points: Vec<[f32; 3]>,
    /// Confidence (`1 + exp(h)` scale), one per chunk pixel.
    pub conf: Vec<f32>,
}

/// Options of [`refine_scene`] (official defaults).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct RefineOptions {
    /// Chunk sampler parameters (`pipeline.md` §5).
    pub chunking: ChunkParams,
    /// Scene radius rule (`chunking.radius_rule`, `pipeline.md` §4).
    pub radius_rule: RadiusRule,
    /// RANSAC threshold of the pre-alignment (`align.max_error`, scene units).
    pub align_max_error: f64,
    /// Seed of the RANSAC sampler.
    pub seed: u64,
    /// Overrides the per-scene chunk seed `crc32(scene name)` (`--seed`).
    pub chunk_seed: Option<u64>,
    /// Token budget per forward; a chunk larger than the budget runs alone.
    pub max_tokens_per_forward: usize,
    /// Fusion rule (`pipeline.md` §8).
    pub fusion: FusionMode,
    /// With no DLT point, return the feed-forward points (conf 0) instead of failing.
    pub allow_unrefined: bool,
    /// Optional region of interest (evaluation option, `pipeline.md` §10.5, see [`crate::roi`]):
    /// restricts the dense points that may enter chunks (`F`) and the DLT points used after the
    /// alignment, and switches the radius to the pooled rule over `F`.
    #[serde(skip)]
    pub roi: Option<RegionOfInterest>,
    /// Stop request, checked before every network forward: a cancelled token ends the call
    /// with [`SceneError::Cancelled`] (default: never cancelled).
    #[serde(skip)]
    pub cancel: ggpt_core::Cancel,
}

impl Default for RefineOptions {
    fn default() -> Self {
        RefineOptions {
            chunking: ChunkParams::default(),
            radius_rule: RadiusRule::AcrossViews,
            align_max_error: DEFAULT_ALIGN_MAX_ERROR,
            seed: DEFAULT_SEED,
            chunk_seed: None,
            max_tokens_per_forward: DEFAULT_MAX_TOKENS_PER_FORWARD,
            fusion: FusionMode::Mean,
            allow_unrefined: false,
            roi: None,
            cancel: ggpt_core::Cancel::default(),
        }
    }
}

/// Summary of one processed chunk.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ChunkSummary {
    /// Index in sampling order.
    pub index: usize,
    /// Centre (SfM frame).
    pub center: [f32; 3],
    /// Half-size (scene units).
    pub radius: f64,
    /// Dense tokens (pixels).
    pub num_pixels: usize,
    /// DLT tokens.
    pub num_dlt: usize,
}

/// The pre-alignment that was applied.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct AlignSummary {
    /// `sfm_from_ff = [sR | t]` (f64).
    pub sfm_from_ff: [[f64; 4]; 3],
    /// The `f32` matrix applied.
    pub sfm_from_ff_f32: [[f32; 4]; 3],
    /// Branch of the retry schedule.
    pub method: AlignMethod,
    /// Correspondences used.
    pub num_pairs: usize,
    /// RANSAC inliers (robust branch only).
    pub num_inliers: Option<usize>,
}

/// Output of [`refine_scene`]; all per-pixel arrays flat in pixel order, SfM frame.
#[derive(Debug, Clone)]
pub struct RefinedScene {
    /// Resolution.
    pub dims: Dims,
    /// `[P, 3]` refined points (aligned `X_d` where uncovered).
    pub points: Vec<f32>,
    /// `[P]` refined confidence (0 where uncovered).
    pub conf: Vec<f32>,
    /// `[P]` covered by at least one chunk.
    pub covered: Vec<bool>,
    /// `[P]` number of covering chunks.
    pub count: Vec<u32>,
    /// `[P, 3]` aligned feed-forward points (SfM frame).
    pub aligned_ff: Vec<f32>,
    /// Pre-alignment (`None` on the unrefined path).
    pub alignment: Option<AlignSummary>,
    /// Scene radius (`None` on the unrefined path).
    pub radius: Option<SceneRadius>,
    /// Processed chunks in order.
    pub chunks: Vec<ChunkSummary>,
    /// Sampling attempts.
    pub attempts: usize,
    /// DLT pixels left uncovered by the sampler.
    pub uncovered_dlt: usize,
    /// DLT pixels used by the sampler (`M_s`, or `M_s ∧ F`).
    pub dlt_pixels: usize,
    /// Why the sampler stopped.
    pub stop: Option<StopReason>,
    /// Network forwards.
    pub forwards: usize,
    /// Tokens over all forwards.
    pub total_tokens: usize,
    /// Chunk seed used.
    pub chunk_seed: u64,
    /// True on the `allow_unrefined` path (no DLT point).
    pub unrefined: bool,
    /// True when no chunk was accepted (output = aligned feed-forward prediction).
    pub no_chunk_fallback: bool,
    /// Warnings raised (also logged).
    pub warnings: Vec<String>,
}

impl RefinedScene {
    /// Counts and settings for `meta.json` (`pipeline.md` §9.4): views, resolution, DLT pixels,
    /// chunks, attempts, forwards, tokens, covered pixels, seeds, radius, alignment, warnings.
    pub fn summary_json(&self) -> serde_json::Value {
        let covered = self.covered.iter().filter(|&&c| c).count();
        serde_json::json!({
            "views": self.dims.n,
            "height": self.dims.h,
            "width": self.dims.w,
            "pixels": self.dims.pixels(),
            "dlt_pixels": self.dlt_pixels,
            "chunks": self.chunks.len(),
            "attempts": self.attempts,
            "uncovered_dlt_pixels": self.uncovered_dlt,
            "stop": self.stop,
            "forwards": self.forwards,
            "tokens": self.total_tokens,
            "dense_tokens": self.chunks.iter().map(|c| c.num_pixels).sum::<usize>(),
            "covered_pixels": covered,
            "chunk_seed": self.chunk_seed,
            "radius": self.radius,
            "alignment": self.alignment,
            "unrefined": self.unrefined,
            "no_chunk_fallback": self.no_chunk_fallback,
            "warnings": self.warnings,
        })
    }
}

/// Name of the refinement stage in progress reports (one unit per chunk).
pub const PROGRESS_STAGE: &str = "refine";

/// [`refine_scene_with_progress`] without progress reports.
pub fn refine_scene(
    scene: &Scene,
    sfm: &SfmResult,
    refiner: &mut dyn ChunkRefiner,
    opts: &RefineOptions,
) -> Result<RefinedScene, SceneError> {
    refine_scene_with_progress(scene, sfm, refiner, opts, &mut |_| {})
}

fn check_cameras(what: &str, c: &Cameras, n: usize) -> Result<(), SceneError> {
    if c.cam_from_world.len() != n || c.intrinsics.len() != n {
        return Err(SceneError::Invalid(format!(
            "mismatched view counts: {what} has {} extrinsics / {} intrinsics, the scene has {n} views",
            c.cam_from_world.len(),
            c.intrinsics.len()
        )));
    }
    if !c.is_finite() {
        return Err(SceneError::NonFinite {
            what: format!("{what} cameras"),
            index: 0,
            value: f64::NAN,
        });
    }
    Ok(())
}

fn rows<T: Copy + nalgebra::Scalar>(m: &Matrix3x4<T>) -> [[T; 4]; 3] {
    std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
}

/// Refines `scene` (feed-forward prediction `scene.ff`, images) with the SfM result `sfm`
/// (`pipeline.md` §3-§8). Outputs live in the SfM frame. `progress` is called after every forward.
pub fn refine_scene_with_progress(
    scene: &Scene,
    sfm: &SfmResult,
    refiner: &mut dyn ChunkRefiner,
    opts: &RefineOptions,
    progress: &mut dyn FnMut(Progress),
) -> Result<RefinedScene, SceneError> {
    let dims = scene.dims;
    let px = dims.pixels();
    let ff = scene
        .ff
        .as_ref()
        .ok_or_else(|| SceneError::Invalid("the scene has no feed-forward prediction".into()))?;
    // Sizes and view counts.
    check_len("ff.points", ff.points.len(), 3 * px)?;
    check_len("ff.conf", ff.conf.len(), px)?;
    check_len("images", scene.images.len(), 3 * px)?;
    check_len("sfm.points", sfm.points.len(), 3 * px)?;
    check_len("sfm.mask", sfm.mask.len(), px)?;
    check_cameras("feed-forward", &ff.cameras, dims.n)?;
    check_cameras("SfM", &sfm.cameras, dims.n)?;
    if let Some(RegionOfInterest::Mask(f)) = &opts.roi {
        check_len("region-of-interest mask", f.len(), px)?;
    }
    // Never propagate NaN into the network.
    check_finite("ff.points", &ff.points)?;
    check_finite("ff.conf", &ff.conf)?;
    check_finite("sfm.points", &sfm.points)?;
    check_finite("images", &scene.images)?;
    let chunk_seed = opts
        .chunk_seed
        .unwrap_or_else(|| crate::chunker::scene_seed(&scene.name));
    let mut warnings = Vec::new();
    let mut warn = |w: String| {
        tracing::warn!("{w}");
        warnings.push(w);
    };

    let n_dlt_all = sfm.mask.iter().filter(|&&m| m).count();
    if n_dlt_all == 0 || !sfm.points_success {
        if !opts.allow_unrefined {
            return Err(SceneError::NoDltPoint);
        }
        warn("SfM produced no DLT point: exporting the unrefined feed-forward points with confidence 0".into());
        return Ok(RefinedScene {
            dims,
            points: ff.points.clone(),
            conf: vec![0.0; px],
            covered: vec![false; px],
            count: vec![0; px],
            aligned_ff: ff.points.clone(),
            alignment: None,
            radius: None,
            chunks: Vec::new(),
            attempts: 0,
            uncovered_dlt: 0,
            dlt_pixels: 0,
            stop: None,
            forwards: 0,
            total_tokens: 0,
            chunk_seed,
            unrefined: true,
            no_chunk_fallback: false,
            warnings,
        });
    }

    // §3 pre-alignment (on the full M_s).
    let mut rng = rand_pcg::Pcg64::seed_from_u64(opts.seed);
    let pre = prealign_ff(
        &ff.points,
        &sfm.points,
        &sfm.mask,
        opts.align_max_error,
        &mut rng,
    )?;
    if pre.is_identity_fallback() {
        warn("Sim(3) pre-alignment failed completely: using the identity".into());
    }
    let alignment = AlignSummary {
        sfm_from_ff: rows(&pre.tgt_from_src.to_matrix3x4()),
        sfm_from_ff_f32: rows(&pre.matrix_f32),
        method: pre.info.method,
        num_pairs: pre.num_pairs,
        num_inliers: pre.info.num_inliers,
    };
    let aligned = pre.aligned;
    check_finite("aligned feed-forward points", &aligned)?;

    // Region of interest restricts the dense points (F) and the DLT points used from here on.
    let (roi_dense, dlt_mask) = match &opts.roi {
        Some(r) => {
            let m = r.masks(&aligned, &sfm.points, &sfm.mask)?;
            (Some(m.dense), m.dlt_mask)
        }
        None => (None, sfm.mask.clone()),
    };
    let roi = roi_dense.as_deref();

    // §4 radius, §5 chunks.
    let radius = scene_radius(&aligned, dims, opts.radius_rule, roi)?;
    if radius.rule != opts.radius_rule {
        tracing::info!(
            "scene radius: {:?} rule used instead of {:?} (mask or N = 1)",
            radius.rule,
            opts.radius_rule
        );
    }
    let inputs = ChunkInputs {
        ff_points: &aligned,
        dlt_points: &sfm.points,
        dlt_mask: &dlt_mask,
        roi,
    };
    let mut draws = PcgDraws::new(chunk_seed);
    let set = sample_chunks(inputs, radius.radius, &opts.chunking, &mut draws)?;
    tracing::info!(
        "chunking: {} chunks from {} attempts (R = {:.6}, stop {:?}, {} DLT pixels uncovered)",
        set.chunks.len(),
        set.attempts.len(),
        radius.radius,
        set.stop,
        set.uncovered
    );

    // §6-§8: records, forwards by token budget, un-normalise, fuse.
    let src = RecordSources {
        ff_points: &aligned,
        ff_conf: &ff.conf,
        dlt_points: &sfm.points,
        dlt_mask: &dlt_mask,
        images: &scene.images,
        gt: None,
    };
    let mut acc = FusionAccumulator::new(px, opts.fusion);
    let mut summaries = Vec::with_capacity(set.chunks.len());
    let (mut forwards, mut total_tokens) = (0usize, 0usize);
    let total = set.chunks.len();
    let mut next = 0usize;
    // A record built but left for the next forward (it did not fit the token budget).
    let mut pending: Option<ChunkRecord> = None;
    while next < total {
        let mut batch: Vec<ChunkRecord> = Vec::new();
        let mut tokens = 0usize;
        loop {
            let rec = match pending.take() {
                Some(r) => r,
                None => match set.chunks.get(next) {
                    Some(chunk) => ChunkRecord::build(chunk, &src)?,
                    None => break,
                },
            };
            let t = rec.num_tokens();
            if !batch.is_empty() && tokens + t > opts.max_tokens_per_forward {
                pending = Some(rec);
                break;
            }
            tokens += t;
            batch.push(rec);
            next += 1;
        }
        if opts.cancel.is_cancelled() {
            return Err(SceneError::Cancelled);
        }
        let out = refiner.refine(&batch)?;
        if out.len() != batch.len() {
            return Err(SceneError::Refiner(format!(
                "{} results for a batch of {} chunks",
                out.len(),
                batch.len()
            )));
        }
        for (rec, res) in batch.iter().zip(&out) {
            let k = rec.len();
            if res.points.len() != k || res.conf.len() != k {
                return Err(SceneError::Refiner(format!(
                    "chunk {}: {} points / {} confidences for {k} pixels",
                    rec.index,
                    res.points.len(),
                    res.conf.len()
                )));
            }
            let world: Vec<[f32; 3]> = res
                .points
                .iter()
                .map(|&x| unnormalise(x, rec.center, rec.radius))
                .collect();
            acc.add_chunk(&rec.pixels, &world, &res.conf)
                .map_err(|e| SceneError::Refiner(format!("chunk {}: {e}", rec.index)))?;
            summaries.push(ChunkSummary {
                index: rec.index,
                center: rec.center,
                radius: rec.radius,
                num_pixels: k,
                num_dlt: rec.num_tokens() - k,
            });
        }
        forwards += 1;
        total_tokens += tokens;
        progress(Progress::new(PROGRESS_STAGE, next as u64, total as u64));
    }
    let fused = acc.finish(&aligned, &ff.conf)?;
    if fused.no_chunk_fallback {
        warn("no chunk was accepted: output = aligned feed-forward points with their feed-forward confidence".into());
    }
    Ok(RefinedScene {
        dims,
        points: fused.points,
        conf: fused.conf,
        covered: fused.covered,
        count: fused.count,
        aligned_ff: aligned,
        alignment: Some(alignment),
        radius: Some(radius),
        chunks: summaries,
        attempts: set.attempts.len(),
        uncovered_dlt: set.uncovered,
        dlt_pixels: dlt_mask.iter().filter(|&&m| m).count(),
        stop: Some(set.stop),
        forwards,
        total_tokens,
        chunk_seed,
        unrefined: false,
        no_chunk_fallback: fused.no_chunk_fallback,
        warnings,
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::test_util::Fixture;
    use ggpt_core::FeedForward;
    use nalgebra::{Matrix3, Matrix3x4};

    fn cams(ext: &[f32], intr: &[f32], n: usize) -> Cameras {
        Cameras {
            cam_from_world: (0..n)
                .map(|i| Matrix3x4::from_row_slice(&ext[12 * i..12 * i + 12]).map(f64::from))
                .collect(),
            intrinsics: (0..n)
                .map(|i| Matrix3::from_row_slice(&intr[9 * i..9 * i + 9]).map(f64::from))
                .collect(),
        }
    }

    /// The `sfm_small` scene with the official SfM output.
    pub(crate) fn fixture_scene() -> (Scene, SfmResult) {
        let inputs = Fixture::sfm_inputs();
        let steps = Fixture::sfm_steps();
        let dims = Dims { n: 4, h: 42, w: 56 };
        let ff = FeedForward {
            points: inputs.f32("ff/points"),
            conf: inputs.f32("ff/points_conf"),
            cameras: cams(
                &inputs.f32("ff/extrinsics"),
                &inputs.f32("ff/intrinsics"),
                4,
            ),
        };
        let scene = Scene {
            name: "synth_room_s0".into(),
            dims,
            images: inputs.f32("ff/images_ff"),
            gt: None,
            ff: Some(ff),
            sfm: None,
            matches: Vec::new(),
        };
        let sfm = SfmResult {
            points: steps.f32("scatter/points"),
            mask: steps.bool("scatter/point_masks"),
            cameras: cams(
                &steps.f32("ba/out_extrinsics"),
                &steps.f32("ba/out_intrinsics"),
                4,
            ),
            camera_success: true,
            points_success: true,
        };
        (scene, sfm)
    }

    pub(crate) fn fixture_opts() -> RefineOptions {
        RefineOptions {
            chunking: crate::chunker::tests_support::fixture_params(),
            ..RefineOptions::default()
        }
    }

    /// Identity network plus a known per-chunk offset (chunk coordinates) on x.
    pub(crate) struct MockRefiner {
        pub offset_per_chunk: f32,
        pub calls: Vec<usize>,
        pub seen: Vec<(usize, [f32; 3], f64)>,
    }
    impl ChunkRefiner for MockRefiner {
        fn refine(&mut self, chunks: &[ChunkRecord]) -> Result<Vec<RefinedChunk>, SceneError> {
            self.calls.push(chunks.len());
            Ok(chunks
                .iter()
                .map(|c| {
                    self.seen.push((c.index, c.center, c.radius));
                    let d = self.offset_per_chunk * (c.index as f32 + 1.0);
                    RefinedChunk {
                        points: c.ff_pts.iter().map(|x| [x[0] + d, x[1], x[2]]).collect(),
                        conf: vec![2.0; c.len()],
                    }
                })
                .collect())
        }
    }

    #[test]
    fn identity_refiner_fuses_back_to_aligned_points() {
        let (scene, sfm) = fixture_scene();
        let mut m = MockRefiner {
            offset_per_chunk: 0.0,
            calls: vec![],
            seen: vec![],
        };
        let out = refine_scene(&scene, &sfm, &mut m, &fixture_opts()).unwrap();
        assert!(!out.chunks.is_empty());
        assert_eq!(out.chunk_seed, 843347836);
        let mut covered = 0;
        for p in 0..scene.dims.pixels() {
            let a = &out.aligned_ff[3 * p..3 * p + 3];
            let x = &out.points[3 * p..3 * p + 3];
            if out.covered[p] {
                covered += 1;
                assert_eq!(out.conf[p], 2.0);
                for i in 0..3 {
                    assert!(
                        (a[i] - x[i]).abs() <= 1e-5 * (1.0 + a[i].abs()),
                        "pixel {p}: {x:?} vs {a:?}"
                    );
                }
            } else {
                assert_eq!(out.conf[p], 0.0);
                assert_eq!(a, x, "uncovered pixel {p} must keep the aligned point");
            }
        }
        assert!(covered > 0 && covered < scene.dims.pixels());
        // Every DLT pixel the sampler covered is covered.
        assert_eq!(
            out.dlt_pixels - out.uncovered_dlt,
            sfm.mask
                .iter()
                .zip(&out.covered)
                .filter(|(m, c)| **m && **c)
                .count()
        );
    }

    #[test]
    fn offsets_are_unnormalised_and_averaged() {
        let (scene, sfm) = fixture_scene();
        let off = 0.01f32;
        let mut m = MockRefiner {
            offset_per_chunk: off,
            calls: vec![],
            seen: vec![],
        };
        let out = refine_scene(&scene, &sfm, &mut m, &fixture_opts()).unwrap();
        // Expected x shift of pixel p = mean over covering chunks k of off (k+1) r_k.
        let mut shift = vec![0.0f64; scene.dims.pixels()];
        let mut cnt = vec![0u32; scene.dims.pixels()];
        let aligned = out.aligned_ff.clone();
        // Re-run the sampler independently with the same seed to know every chunk's pixels.
        let mut sampler_chunks = Vec::new();
        {
            let inputs = ChunkInputs {
                ff_points: &aligned,
                dlt_points: &sfm.points,
                dlt_mask: &sfm.mask,
                roi: None,
            };
            let set = sample_chunks(
                inputs,
                out.radius.unwrap().radius,
                &fixture_opts().chunking,
                &mut PcgDraws::new(out.chunk_seed),
            )
            .unwrap();
            sampler_chunks.extend(set.chunks);
        }
        assert_eq!(sampler_chunks.len(), out.chunks.len());
        for ch in &sampler_chunks {
            for &p in &ch.pixels {
                shift[p as usize] += f64::from(off) * (ch.index as f64 + 1.0) * ch.radius;
                cnt[p as usize] += 1;
            }
        }
        assert_eq!(cnt, out.count);
        for p in 0..scene.dims.pixels() {
            if cnt[p] > 0 {
                let want = f64::from(aligned[3 * p]) + shift[p] / f64::from(cnt[p]);
                assert!(
                    (f64::from(out.points[3 * p]) - want).abs() < 1e-5,
                    "pixel {p}"
                );
                assert!((out.points[3 * p + 1] - aligned[3 * p + 1]).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn batching_does_not_change_results() {
        let (scene, sfm) = fixture_scene();
        let mut one = MockRefiner {
            offset_per_chunk: 0.02,
            calls: vec![],
            seen: vec![],
        };
        let mut opts = fixture_opts();
        opts.max_tokens_per_forward = 1;
        let a = refine_scene(&scene, &sfm, &mut one, &opts).unwrap();
        assert!(one.calls.iter().all(|&c| c == 1));
        let mut many = MockRefiner {
            offset_per_chunk: 0.02,
            calls: vec![],
            seen: vec![],
        };
        opts.max_tokens_per_forward = 5000;
        let mut reports = Vec::new();
        let b =
            refine_scene_with_progress(&scene, &sfm, &mut many, &opts, &mut |p| reports.push(p))
                .unwrap();
        assert!(many.calls.len() < one.calls.len());
        assert!(many.calls.iter().any(|&c| c > 1));
        assert_eq!(a.points, b.points);
        assert_eq!(a.conf, b.conf);
        assert_eq!(one.seen, many.seen);
        assert_eq!(b.forwards, many.calls.len());
        let j = b.summary_json();
        assert_eq!(j["chunks"], b.chunks.len());
        assert_eq!(j["forwards"], many.calls.len());
        assert_eq!(j["chunk_seed"], 843347836u64);
        assert_eq!(j["alignment"]["method"]["method"], "robust");
        assert_eq!(reports.last().map(|p| p.done), Some(b.chunks.len() as u64));
        assert!(reports.iter().all(|p| p.stage == PROGRESS_STAGE));
        assert!(reports.windows(2).all(|w| w[0].done < w[1].done));
    }

    #[test]
    fn errors_and_edge_cases() {
        let (scene, sfm) = fixture_scene();
        let opts = fixture_opts();
        let mut m = MockRefiner {
            offset_per_chunk: 0.0,
            calls: vec![],
            seen: vec![],
        };
        // NaN in X_d names the first bad index.
        let mut bad = scene.clone();
        if let Some(ff) = bad.ff.as_mut() {
            ff.points[100] = f32::NAN;
            ff.points[200] = f32::INFINITY;
        }
        match refine_scene(&bad, &sfm, &mut m, &opts) {
            Err(SceneError::NonFinite { what, index, .. }) => {
                assert_eq!((what.as_str(), index), ("ff.points", 100))
            }
            other => panic!("expected NonFinite, got {other:?}"),
        }
        // Mismatched view counts.
        let mut sfm3 = sfm.clone();
        sfm3.cameras.cam_from_world.pop();
        assert!(
            matches!(refine_scene(&scene, &sfm3, &mut m, &opts), Err(SceneError::Invalid(s)) if s.contains("view counts"))
        );
        // Wrong array size.
        let mut short = sfm.clone();
        short.mask.pop();
        assert!(refine_scene(&scene, &short, &mut m, &opts).is_err());
        // No DLT point: error, or the unaligned ff points with conf 0.
        let mut empty = sfm.clone();
        empty.mask.fill(false);
        empty.points_success = false;
        assert!(matches!(
            refine_scene(&scene, &empty, &mut m, &opts),
            Err(SceneError::NoDltPoint)
        ));
        let allow = RefineOptions {
            allow_unrefined: true,
            ..opts.clone()
        };
        let u = refine_scene(&scene, &empty, &mut m, &allow).unwrap();
        assert!(u.unrefined);
        assert_eq!(u.points, scene.ff.as_ref().unwrap().points);
        assert!(u.conf.iter().all(|&c| c == 0.0));
        // No accepted chunk (impossible minimums): aligned ff with ff confidence.
        let strict = RefineOptions {
            chunking: ChunkParams {
                min_dlt: 1_000_000,
                ..opts.chunking.clone()
            },
            ..opts.clone()
        };
        let n = refine_scene(&scene, &sfm, &mut m, &strict).unwrap();
        assert!(n.no_chunk_fallback && n.chunks.is_empty());
        assert_eq!(n.points, n.aligned_ff);
        assert_eq!(n.conf, scene.ff.as_ref().unwrap().conf);
        assert!(!n.warnings.is_empty());
        // A refiner returning the wrong number of points is an error naming the chunk.
        struct Broken;
        impl ChunkRefiner for Broken {
            fn refine(&mut self, chunks: &[ChunkRecord]) -> Result<Vec<RefinedChunk>, SceneError> {
                Ok(chunks
                    .iter()
                    .map(|_| RefinedChunk {
                        points: vec![],
                        conf: vec![],
                    })
                    .collect())
            }
        }
        assert!(
            matches!(refine_scene(&scene, &sfm, &mut Broken, &opts), Err(SceneError::Refiner(s)) if s.contains("chunk 0"))
        );
    }

    #[test]
    fn region_of_interest_restricts_chunks() {
        let (scene, sfm) = fixture_scene();
        // Keep only views 0 and 1.
        let hw = scene.dims.hw();
        let roi: Vec<bool> = (0..scene.dims.pixels()).map(|p| p < 2 * hw).collect();
        let opts = RefineOptions {
            roi: Some(RegionOfInterest::Mask(roi.clone())),
            ..fixture_opts()
        };
        let mut m = MockRefiner {
            offset_per_chunk: 0.0,
            calls: vec![],
            seen: vec![],
        };
        let out = refine_scene(&scene, &sfm, &mut m, &opts).unwrap();
        assert_eq!(out.radius.unwrap().rule, RadiusRule::Pooled);
        assert!(out.covered.iter().zip(&roi).all(|(c, r)| !*c || *r));
        assert!(out.covered.iter().any(|&c| c));
        // A box around part of the scene: covered dense pixels lie in the box or entered
        // through an in-box DLT point.
        let (lo, hi) = ([-0.2f32, -0.5, 0.0], [0.3f32, 0.5, 3.0]);
        let opts = RefineOptions {
            roi: Some(RegionOfInterest::Box { min: lo, max: hi }),
            ..fixture_opts()
        };
        let out = refine_scene(&scene, &sfm, &mut m, &opts).unwrap();
        let inb = |x: &[f32]| (0..3).all(|a| lo[a] <= x[a] && x[a] <= hi[a]);
        let mut n = 0;
        for p in 0..scene.dims.pixels() {
            if out.covered[p] {
                n += 1;
                assert!(
                    inb(&out.aligned_ff[3 * p..3 * p + 3])
                        || (sfm.mask[p] && inb(&sfm.points[3 * p..3 * p + 3])),
                    "pixel {p}"
                );
            }
        }
        assert!(n > 0 && n < scene.dims.pixels());
    }
}
