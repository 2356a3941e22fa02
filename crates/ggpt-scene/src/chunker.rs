//! Random overlapping-cube chunk sampler (`pipeline.md` §5), reproducing the official
//! `split_scenes_random` / `sample_a_chunk` (clip method "shrink") exactly given the same draws.
//!
//! All arrays are flat in pixel order; points are in the SfM frame (scene units): `ff_points` is
//! the **aligned** dense map `X_d`, `dlt_points` the DLT map `X_s` with mask `M_s`, `roi` the
//! optional region-of-interest mask `F` (restricts which dense points may enter a chunk).
//!
//! ```text
//! U <- M_s ; m_dlt <- min_dlt ; m_pix <- min_pixels ; fails <- 0
//! while count(U) > 0:
//!     r <- chunk_size * R ; j <- draw(count(U)) ; c <- X_s[j-th pixel of U]
//!     loop: Mk <- (X_d in box(c, r) and F) or (X_s in box(c, r) and U)
//!           if count(Mk) <= max_pixels: break ; r <- 0.9 r
//!     reject if n_dlt < m_dlt (m_dlt <- max(n_dlt/2, min_dlt/10)) or n_pix < m_pix (likewise)
//!     accept: stop if #chunks >= max_chunks_after_converge and Mk adds no DLT pixel;
//!             U <- U and not Mk ; push chunk
//!     stop after 10 consecutive rejections
//! ```
//!
//! Box tests are closed (`lo <= x <= hi`) and computed in `f32` with `lo = c - f32(r)`,
//! `hi = c + f32(r)` (the official torch arithmetic); `r` itself evolves in `f64`.

use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

use crate::error::{SceneError, check_len};

/// Shrink factor applied to `r` while a chunk holds more than `max_pixels` pixels (§5).
pub const SHRINK_FACTOR: f64 = 0.9;
/// Consecutive rejected attempts that end the sampling (§5).
pub const MAX_CONSECUTIVE_FAILURES: usize = 10;
/// Minimum counts are never lowered below `default / MIN_COUNT_FLOOR_DIVISOR` (§5).
pub const MIN_COUNT_FLOOR_DIVISOR: usize = 10;

/// Source of the one uniform draw per sampling attempt.
pub trait DrawSource {
    /// A uniform integer in `[0, n)`; `n ≥ 1`.
    fn draw(&mut self, n: usize) -> usize;
}

/// Default draw source: `rand_pcg::Pcg64` seeded from a `u64` (**[project]**; the official code
/// uses NumPy's `default_rng`, so chunk sets match the official ones only statistically).
#[derive(Debug, Clone)]
pub struct PcgDraws {
    rng: Pcg64,
}

impl PcgDraws {
    /// Generator seeded with `seed`.
    pub fn new(seed: u64) -> Self {
        PcgDraws {
            rng: Pcg64::seed_from_u64(seed),
        }
    }
    /// Generator for a scene: seeded with `seed_override` when given (`--seed`), else with
    /// [`scene_seed`]`(scene_name)`.
    pub fn for_scene(scene_name: &str, seed_override: Option<u64>) -> Self {
        Self::new(seed_override.unwrap_or_else(|| scene_seed(scene_name)))
    }
}

impl DrawSource for PcgDraws {
    fn draw(&mut self, n: usize) -> usize {
        if n <= 1 {
            0
        } else {
            self.rng.random_range(0..n)
        }
    }
}

/// Per-scene seed of the chunk sampler: CRC-32 (zlib / IEEE) of the scene name's UTF-8 bytes.
pub fn scene_seed(scene_name: &str) -> u64 {
    u64::from(crc32fast::hash(scene_name.as_bytes()))
}

/// Sampler parameters (official defaults, `pipeline.md` §5).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct ChunkParams {
    /// Cube half-size as a fraction of the scene radius `R` (0.2).
    pub chunk_size: f64,
    /// Maximum pixels per chunk; larger cubes shrink by 0.9 (400,000).
    pub max_pixels: usize,
    /// Initial minimum number of DLT pixels of an accepted chunk (100).
    pub min_dlt: usize,
    /// Initial minimum number of pixels of an accepted chunk (10,000).
    pub min_pixels: usize,
    /// After this many chunks, a chunk covering no new DLT pixel stops the sampling (100).
    pub max_chunks_after_converge: usize,
}

impl Default for ChunkParams {
    fn default() -> Self {
        ChunkParams {
            chunk_size: 0.2,
            max_pixels: 400_000,
            min_dlt: 100,
            min_pixels: 10_000,
            max_chunks_after_converge: 100,
        }
    }
}

/// Borrowed per-pixel inputs of the sampler (flat, pixel order, SfM frame).
#[derive(Debug, Clone, Copy)]
pub struct ChunkInputs<'a> {
    /// Aligned dense points `X_d`, `[P, 3]`.
    pub ff_points: &'a [f32],
    /// DLT points `X_s`, `[P, 3]` (values where `dlt_mask` is false are ignored).
    pub dlt_points: &'a [f32],
    /// `M_s`, `[P]`.
    pub dlt_mask: &'a [bool],
    /// Region-of-interest mask `F`, `[P]` (all true when `None`).
    pub roi: Option<&'a [bool]>,
}

impl ChunkInputs<'_> {
    /// Number of pixels `P`; checks that all arrays agree and that indices fit in `u32`.
    pub fn pixels(&self) -> Result<usize, SceneError> {
        let p = self.dlt_mask.len();
        check_len("chunker: ff_points", self.ff_points.len(), 3 * p)?;
        check_len("chunker: dlt_points", self.dlt_points.len(), 3 * p)?;
        if let Some(f) = self.roi {
            check_len("chunker: region-of-interest mask", f.len(), p)?;
        }
        if u32::try_from(p).is_err() {
            return Err(SceneError::Invalid(format!(
                "chunker: {p} pixels exceed the u32 pixel-index range"
            )));
        }
        Ok(p)
    }
}

/// An accepted chunk: an axis-aligned cube (L∞ ball) of half-size `radius` around `center`.
#[derive(Debug, Clone, PartialEq)]
pub struct Chunk {
    /// Position in sampling order (0-based).
    pub index: usize,
    /// Pixels of the chunk (`Mk`), ascending pixel order.
    pub pixels: Vec<u32>,
    /// Centre `c` (SfM frame): the DLT point of an uncovered pixel.
    pub center: [f32; 3],
    /// Pixel whose DLT point is the centre.
    pub center_pixel: u32,
    /// Final (possibly shrunk) half-size `r` (scene units).
    pub radius: f64,
    /// Pixels of the chunk with a DLT point (`Mk ∧ M_s`).
    pub n_dlt: usize,
}

/// Book-keeping of one sampling attempt (mirrors the fixture's `chunks/attempt_*`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize)]
pub struct Attempt {
    /// `count(U)` before the draw.
    pub uncovered: usize,
    /// The drawn index into the uncovered DLT pixels (pixel order).
    pub draw: usize,
    /// Final half-size (bits of the f64), see [`Attempt::radius`].
    pub radius_bits: u64,
    /// Pixels in the attempt's mask.
    pub n_pixels: usize,
    /// Pixels of the mask with a DLT point.
    pub n_dlt: usize,
    /// Minimum DLT count in force at the attempt.
    pub min_dlt: usize,
    /// Minimum pixel count in force at the attempt.
    pub min_pixels: usize,
    /// Number of ×0.9 shrinks.
    pub shrinks: u32,
    /// The attempt became a chunk.
    pub accepted: bool,
}

impl Attempt {
    /// Final half-size of the attempt (scene units).
    pub fn radius(&self) -> f64 {
        f64::from_bits(self.radius_bits)
    }
}

/// Why the sampling loop ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum StopReason {
    /// Every DLT pixel is covered.
    AllCovered,
    /// `MAX_CONSECUTIVE_FAILURES` consecutive rejections.
    Failures,
    /// More than `max_chunks_after_converge` chunks and a chunk added no DLT pixel.
    Converged,
}

/// The incremental sampler: call [`ChunkSampler::next_chunk`] until it returns `None`.
#[derive(Debug)]
pub struct ChunkSampler<'a> {
    inputs: ChunkInputs<'a>,
    params: ChunkParams,
    scene_radius: f64,
    uncovered: Vec<bool>,
    n_uncovered: usize,
    m_dlt: usize,
    m_pix: usize,
    fails: usize,
    n_chunks: usize,
    stop: Option<StopReason>,
    attempts: Vec<Attempt>,
    scratch: Vec<u32>,
}

impl<'a> ChunkSampler<'a> {
    /// New sampler over `inputs` with scene radius `scene_radius` (scene units, §4).
    pub fn new(
        inputs: ChunkInputs<'a>,
        scene_radius: f64,
        params: ChunkParams,
    ) -> Result<Self, SceneError> {
        inputs.pixels()?;
        if !scene_radius.is_finite()
            || scene_radius < 0.0
            || !params.chunk_size.is_finite()
            || params.chunk_size <= 0.0
        {
            return Err(SceneError::Invalid(format!(
                "chunker: scene radius {scene_radius} and chunk_size {} must be finite, radius >= 0, chunk_size > 0",
                params.chunk_size
            )));
        }
        let uncovered = inputs.dlt_mask.to_vec();
        let n_uncovered = uncovered.iter().filter(|&&b| b).count();
        Ok(ChunkSampler {
            inputs,
            m_dlt: params.min_dlt,
            m_pix: params.min_pixels,
            params,
            scene_radius,
            uncovered,
            n_uncovered,
            fails: 0,
            n_chunks: 0,
            stop: if n_uncovered == 0 {
                Some(StopReason::AllCovered)
            } else {
                None
            },
            attempts: Vec::new(),
            scratch: Vec::new(),
        })
    }

    /// Every attempt so far, in order.
    pub fn attempts(&self) -> &[Attempt] {
        &self.attempts
    }
    /// Number of DLT pixels not covered by any chunk yet.
    pub fn uncovered_count(&self) -> usize {
        self.n_uncovered
    }
    /// The uncovered mask `U` (`[P]`).
    pub fn uncovered_mask(&self) -> &[bool] {
        &self.uncovered
    }
    /// Why the sampling ended (`None` while it is still running).
    pub fn stop_reason(&self) -> Option<StopReason> {
        self.stop
    }

    /// Runs attempts until one is accepted (returns it) or the loop ends (returns `None`).
    pub fn next_chunk(&mut self, draws: &mut dyn DrawSource) -> Result<Option<Chunk>, SceneError> {
        while self.stop.is_none() {
            if self.n_uncovered == 0 {
                self.stop = Some(StopReason::AllCovered);
                break;
            }
            let chunk = self.attempt(draws)?;
            if self.fails >= MAX_CONSECUTIVE_FAILURES && self.stop.is_none() {
                self.stop = Some(StopReason::Failures);
            }
            if chunk.is_some() {
                return Ok(chunk);
            }
        }
        Ok(None)
    }

    /// One attempt: draw, crop (with shrinking), accept or reject.
    fn attempt(&mut self, draws: &mut dyn DrawSource) -> Result<Option<Chunk>, SceneError> {
        let n_unc = self.n_uncovered;
        let j = draws.draw(n_unc);
        if j >= n_unc {
            return Err(SceneError::Invalid(format!(
                "chunker: draw source returned {j} for a draw in [0, {n_unc})"
            )));
        }
        let centre_pixel = self
            .uncovered
            .iter()
            .enumerate()
            .filter(|(_, u)| **u)
            .nth(j)
            .map(|(p, _)| p)
            .ok_or_else(|| {
                SceneError::Invalid(format!("chunker: uncovered pixel #{j} not found"))
            })?;
        let c = point(self.inputs.dlt_points, centre_pixel);
        let mut r = self.params.chunk_size * self.scene_radius;
        let mut shrinks = 0u32;
        let mut mask = std::mem::take(&mut self.scratch);
        let mut degenerate = false;
        loop {
            let fits = self.crop(c, r, &mut mask);
            if fits {
                break;
            }
            // A box that no longer changes in f32 cannot shrink below max_pixels: more than
            // max_pixels points coincide with the centre. Reject instead of looping forever.
            if box_is_point(c, r as f32) {
                degenerate = true;
                break;
            }
            r *= SHRINK_FACTOR;
            shrinks += 1;
        }
        let n_pix = mask.len();
        let n_dlt = mask
            .iter()
            .filter(|&&p| {
                self.inputs
                    .dlt_mask
                    .get(p as usize)
                    .copied()
                    .unwrap_or(false)
            })
            .count();
        let mut attempt = Attempt {
            uncovered: n_unc,
            draw: j,
            radius_bits: r.to_bits(),
            n_pixels: n_pix,
            n_dlt,
            min_dlt: self.m_dlt,
            min_pixels: self.m_pix,
            shrinks,
            accepted: false,
        };
        let mut out = None;
        if degenerate {
            tracing::warn!(
                "chunker: more than {} points coincide with the chunk centre (pixel {centre_pixel}); attempt rejected",
                self.params.max_pixels
            );
            self.fails += 1;
        } else if n_dlt < self.m_dlt {
            self.m_dlt = (n_dlt / 2).max(self.params.min_dlt / MIN_COUNT_FLOOR_DIVISOR);
            self.fails += 1;
        } else if n_pix < self.m_pix {
            self.m_pix = (n_pix / 2).max(self.params.min_pixels / MIN_COUNT_FLOOR_DIVISOR);
            self.fails += 1;
        } else {
            self.fails = 0;
            let newly = mask
                .iter()
                .filter(|&&p| self.uncovered.get(p as usize).copied().unwrap_or(false))
                .count();
            if self.n_chunks >= self.params.max_chunks_after_converge && newly == 0 {
                self.stop = Some(StopReason::Converged);
            } else {
                for &p in &mask {
                    if let Some(u) = self.uncovered.get_mut(p as usize) {
                        *u = false;
                    }
                }
                self.n_uncovered -= newly;
                attempt.accepted = true;
                out = Some(Chunk {
                    index: self.n_chunks,
                    pixels: mask.clone(),
                    center: c,
                    center_pixel: centre_pixel as u32,
                    radius: r,
                    n_dlt,
                });
                self.n_chunks += 1;
            }
        }
        self.attempts.push(attempt);
        mask.clear();
        self.scratch = mask;
        Ok(out)
    }

    /// Fills `mask` with the pixels of the box `(c, r)`; returns false (mask incomplete) as soon
    /// as more than `max_pixels` pixels are found.
    fn crop(&self, c: [f32; 3], r: f64, mask: &mut Vec<u32>) -> bool {
        mask.clear();
        let (lo, hi) = box_bounds(c, r);
        let inp = &self.inputs;
        let roi = inp.roi;
        let ff = inp.ff_points.chunks_exact(3);
        let dlt = inp.dlt_points.chunks_exact(3);
        for (p, ((x, s), &u)) in ff.zip(dlt).zip(self.uncovered.iter()).enumerate() {
            let in_ff = in_box(x, lo, hi) && roi.is_none_or(|f| f.get(p).copied().unwrap_or(false));
            let inside = in_ff || (u && in_box(s, lo, hi));
            if inside {
                mask.push(p as u32);
                if mask.len() > self.params.max_pixels {
                    return false;
                }
            }
        }
        true
    }
}

/// `f32` box bounds `c ± f32(r)` (official torch arithmetic: f32 tensor minus Python float).
pub fn box_bounds(c: [f32; 3], r: f64) -> ([f32; 3], [f32; 3]) {
    let r32 = r as f32;
    (c.map(|v| v - r32), c.map(|v| v + r32))
}

/// Closed L∞ box test `lo <= x <= hi` on all three axes.
#[inline]
fn in_box(x: &[f32], lo: [f32; 3], hi: [f32; 3]) -> bool {
    x.len() == 3
        && lo[0] <= x[0]
        && x[0] <= hi[0]
        && lo[1] <= x[1]
        && x[1] <= hi[1]
        && lo[2] <= x[2]
        && x[2] <= hi[2]
}

fn box_is_point(c: [f32; 3], r32: f32) -> bool {
    c.iter().all(|&v| v - r32 == v && v + r32 == v)
}

fn point(points: &[f32], p: usize) -> [f32; 3] {
    match points.get(3 * p..3 * p + 3) {
        Some(s) => [s[0], s[1], s[2]],
        None => [0.0; 3],
    }
}

/// Result of a whole sampling run.
#[derive(Debug, Clone)]
pub struct ChunkSet {
    /// Accepted chunks in sampling order.
    pub chunks: Vec<Chunk>,
    /// Every attempt.
    pub attempts: Vec<Attempt>,
    /// DLT pixels left uncovered.
    pub uncovered: usize,
    /// Why the loop ended.
    pub stop: StopReason,
}

/// Runs the sampler to the end (all chunks held in memory as pixel lists).
pub fn sample_chunks(
    inputs: ChunkInputs<'_>,
    scene_radius: f64,
    params: &ChunkParams,
    draws: &mut dyn DrawSource,
) -> Result<ChunkSet, SceneError> {
    let mut s = ChunkSampler::new(inputs, scene_radius, params.clone())?;
    let mut chunks = Vec::new();
    while let Some(c) = s.next_chunk(draws)? {
        chunks.push(c);
    }
    Ok(ChunkSet {
        chunks,
        uncovered: s.n_uncovered,
        stop: s.stop.unwrap_or(StopReason::AllCovered),
        attempts: s.attempts,
    })
}

/// One training chunk (`pipeline.md` §11.2, **[project]**): centre = a uniformly drawn DLT pixel
/// of the whole scene (no coverage bookkeeping: every DLT point may enter), `r = chunk_size R`,
/// shrink while over `max_pixels`, accept with ≥ `min_dlt` DLT pixels and ≥ `min_pixels` pixels;
/// up to [`MAX_CONSECUTIVE_FAILURES`] draws, `None` when all fail.
pub fn sample_training_chunk(
    inputs: ChunkInputs<'_>,
    scene_radius: f64,
    params: &ChunkParams,
    draws: &mut dyn DrawSource,
) -> Result<Option<Chunk>, SceneError> {
    for _ in 0..MAX_CONSECUTIVE_FAILURES {
        // A fresh sampler per draw keeps U = M_s and the minimums at their defaults.
        let mut s = ChunkSampler::new(
            inputs,
            scene_radius,
            ChunkParams {
                max_chunks_after_converge: usize::MAX,
                ..params.clone()
            },
        )?;
        if s.stop.is_some() {
            return Ok(None);
        }
        let c = s.attempt(draws)?;
        if c.is_some() {
            return Ok(c);
        }
    }
    Ok(None)
}

#[cfg(test)]
pub(crate) mod tests_support {
    use super::*;
    use crate::test_util::Fixture;

    /// Replays recorded draws; panics (test failure) when they run out.
    pub(crate) struct Replay(pub Vec<usize>, pub usize);
    impl DrawSource for Replay {
        fn draw(&mut self, n: usize) -> usize {
            let v = self.0[self.1];
            assert!(v < n, "recorded draw {v} out of [0, {n})");
            self.1 += 1;
            v
        }
    }

    /// `sfm_small` sampler parameters.
    pub(crate) fn fixture_params() -> ChunkParams {
        ChunkParams {
            max_pixels: 1200,
            min_dlt: 40,
            min_pixels: 300,
            ..ChunkParams::default()
        }
    }

    /// The fixture's chunks, replayed from the recorded draws.
    pub(crate) fn replay_fixture_chunks(
        steps: &Fixture,
        aligned: &[f32],
        dlt: &[f32],
        msk: &[bool],
    ) -> Vec<Chunk> {
        let radius = steps.f64("sim3/radius")[0];
        let draws: Vec<usize> = steps
            .i64("chunks/attempt_draw")
            .iter()
            .map(|&d| d as usize)
            .collect();
        let inputs = ChunkInputs {
            ff_points: aligned,
            dlt_points: dlt,
            dlt_mask: msk,
            roi: None,
        };
        sample_chunks(inputs, radius, &fixture_params(), &mut Replay(draws, 0))
            .unwrap()
            .chunks
    }
}

#[cfg(test)]
mod tests {
    use super::tests_support::Replay;
    use super::*;
    use crate::test_util::Fixture;

    #[test]
    fn crc32_seeds() {
        assert_eq!(scene_seed("demo"), 3594706848);
        assert_eq!(scene_seed("scannetpp-9bb22982672c69bf"), 4072360503);
        assert_eq!(
            scene_seed("synth_room_s0") as i64,
            Fixture::sfm_steps().i64("chunks/seed")[0]
        );
    }

    #[test]
    fn fixture_replay_reproduces_every_attempt_and_chunk() {
        let steps = Fixture::sfm_steps();
        let aligned = steps.f32("sim3/ff_aligned");
        let dlt = steps.f32("scatter/points");
        let msk = steps.bool("scatter/point_masks");
        let radius = steps.f64("sim3/radius")[0];
        let params = ChunkParams {
            max_pixels: 1200,
            min_dlt: 40,
            min_pixels: 300,
            ..ChunkParams::default()
        };
        let draws: Vec<usize> = steps
            .i64("chunks/attempt_draw")
            .iter()
            .map(|&d| d as usize)
            .collect();
        let mut replay = Replay(draws.clone(), 0);
        let inputs = ChunkInputs {
            ff_points: &aligned,
            dlt_points: &dlt,
            dlt_mask: &msk,
            roi: None,
        };
        let set = sample_chunks(inputs, radius, &params, &mut replay).unwrap();
        assert_eq!(replay.1, draws.len(), "all recorded draws consumed");
        let a = &set.attempts;
        assert_eq!(a.len(), 52);
        let tosample = steps.i64("chunks/attempt_tosample_count");
        let att_r = steps.f64("chunks/attempt_radius");
        let npx = steps.i64("chunks/attempt_n_pixels");
        let ngeo = steps.i64("chunks/attempt_n_geo");
        let mgeo = steps.i64("chunks/attempt_min_geo_arg");
        let mff = steps.i64("chunks/attempt_min_ff_arg");
        let acc = steps.bool("chunks/attempt_accepted");
        for (i, at) in a.iter().enumerate() {
            assert_eq!(
                at.uncovered as i64, tosample[i],
                "attempt {i} tosample_count"
            );
            assert_eq!(at.radius(), att_r[i], "attempt {i} radius");
            assert_eq!(at.n_pixels as i64, npx[i], "attempt {i} n_pixels");
            assert_eq!(at.n_dlt as i64, ngeo[i], "attempt {i} n_geo");
            assert_eq!(at.min_dlt as i64, mgeo[i], "attempt {i} min_geo");
            assert_eq!(at.min_pixels as i64, mff[i], "attempt {i} min_ff");
            assert_eq!(at.accepted, acc[i], "attempt {i} accepted");
        }
        assert_eq!(a.iter().filter(|x| x.shrinks > 0).count(), 6);
        assert_eq!(set.chunks.len(), 30);
        assert_eq!(set.uncovered, 5);
        assert_eq!(set.stop, StopReason::Failures);
        let centres = steps.f32("chunks/center");
        let radii = steps.f64("chunks/radius");
        let masks = steps.bool("chunks/masks");
        let px = msk.len();
        for (k, ch) in set.chunks.iter().enumerate() {
            assert_eq!(ch.index, k);
            assert_eq!(
                ch.center,
                [centres[3 * k], centres[3 * k + 1], centres[3 * k + 2]],
                "chunk {k} centre"
            );
            assert_eq!(ch.radius, radii[k], "chunk {k} radius");
            let want: Vec<u32> = masks[k * px..(k + 1) * px]
                .iter()
                .enumerate()
                .filter(|(_, m)| **m)
                .map(|(p, _)| p as u32)
                .collect();
            assert_eq!(ch.pixels, want, "chunk {k} mask");
            assert!(ch.pixels.contains(&ch.center_pixel));
        }
    }

    /// Tiny synthetic scene: points on a line, DLT points on some pixels.
    fn line_scene(n: usize) -> (Vec<f32>, Vec<f32>, Vec<bool>) {
        let ff: Vec<f32> = (0..n).flat_map(|i| [i as f32, 0.0, 0.0]).collect();
        let mask: Vec<bool> = (0..n).map(|i| i % 2 == 0).collect();
        let dlt: Vec<f32> = (0..n)
            .flat_map(|i| {
                if i % 2 == 0 {
                    [i as f32, 0.0, 0.0]
                } else {
                    [0.0; 3]
                }
            })
            .collect();
        (ff, dlt, mask)
    }

    #[test]
    fn closed_box_shrink_and_coverage() {
        let (ff, dlt, mask) = line_scene(20);
        // R such that r = chunk_size * R = 2: box [c-2, c+2] closed -> 5 pixels around an interior centre.
        let params = ChunkParams {
            chunk_size: 0.5,
            max_pixels: 5,
            min_dlt: 1,
            min_pixels: 1,
            max_chunks_after_converge: 100,
        };
        let inputs = ChunkInputs {
            ff_points: &ff,
            dlt_points: &dlt,
            dlt_mask: &mask,
            roi: None,
        };
        let mut s = ChunkSampler::new(inputs, 4.0, params.clone()).unwrap();
        // Uncovered DLT pixels: 0,2,...,18; draw #5 -> pixel 10.
        let c = s.next_chunk(&mut Replay(vec![5], 0)).unwrap().unwrap();
        assert_eq!(c.center, [10.0, 0.0, 0.0]);
        assert_eq!(c.pixels, vec![8, 9, 10, 11, 12]);
        assert_eq!(c.radius, 2.0);
        assert_eq!(c.n_dlt, 3);
        assert_eq!(s.uncovered_count(), 7);
        // max_pixels 4: one shrink to 1.8 -> pixels 9..=11.
        let params4 = ChunkParams {
            max_pixels: 4,
            ..params
        };
        let mut s4 = ChunkSampler::new(inputs, 4.0, params4).unwrap();
        let c4 = s4.next_chunk(&mut Replay(vec![5], 0)).unwrap().unwrap();
        assert_eq!(c4.pixels, vec![9, 10, 11]);
        assert_eq!(c4.radius, 2.0 * 0.9);
        assert_eq!(s4.attempts()[0].shrinks, 1);
    }

    #[test]
    fn rejection_lowers_minimums_and_ten_failures_stop() {
        let (ff, dlt, mask) = line_scene(20);
        // r = 0.5: each chunk holds one pixel (one DLT point); min_dlt 100 can never be met.
        let params = ChunkParams {
            chunk_size: 0.5,
            max_pixels: 100,
            min_dlt: 100,
            min_pixels: 1,
            max_chunks_after_converge: 100,
        };
        let inputs = ChunkInputs {
            ff_points: &ff,
            dlt_points: &dlt,
            dlt_mask: &mask,
            roi: None,
        };
        let mut s = ChunkSampler::new(inputs, 1.0, params).unwrap();
        let mut src = PcgDraws::new(1);
        // Attempt 1: n_dlt 1 < 100 -> m_dlt = max(0, 10) = 10; then 1 < 10 -> 10 again, ... 10 failures.
        assert!(s.next_chunk(&mut src).unwrap().is_none());
        assert_eq!(s.attempts().len(), MAX_CONSECUTIVE_FAILURES);
        assert_eq!(s.attempts()[0].min_dlt, 100);
        assert!(
            s.attempts()[1..]
                .iter()
                .all(|a| a.min_dlt == 10 && !a.accepted)
        );
        assert_eq!(s.stop_reason(), Some(StopReason::Failures));
        assert_eq!(s.uncovered_count(), 10);
        // Pixel-count rule: min_pixels 50 with 1-pixel chunks: m_pix -> max(0, 5) = 5.
        let params = ChunkParams {
            chunk_size: 0.5,
            max_pixels: 100,
            min_dlt: 1,
            min_pixels: 50,
            max_chunks_after_converge: 100,
        };
        let mut s = ChunkSampler::new(inputs, 1.0, params).unwrap();
        assert!(s.next_chunk(&mut src).unwrap().is_none());
        assert_eq!(s.attempts()[1].min_pixels, 5);
        assert_eq!(s.attempts()[1].min_dlt, 1);
    }

    #[test]
    fn full_coverage_roi_and_converge_rule() {
        let (ff, dlt, mask) = line_scene(20);
        let params = ChunkParams {
            chunk_size: 0.5,
            max_pixels: 100,
            min_dlt: 1,
            min_pixels: 1,
            max_chunks_after_converge: 100,
        };
        let inputs = ChunkInputs {
            ff_points: &ff,
            dlt_points: &dlt,
            dlt_mask: &mask,
            roi: None,
        };
        let set = sample_chunks(inputs, 3.0, &params, &mut PcgDraws::new(7)).unwrap();
        assert_eq!(set.stop, StopReason::AllCovered);
        assert_eq!(set.uncovered, 0);
        for ch in &set.chunks {
            assert!(
                ch.pixels
                    .iter()
                    .all(|&p| (ff[3 * p as usize] - ch.center[0]).abs() <= ch.radius as f32)
            );
        }
        // ROI excludes odd pixels' dense points: odd pixels never enter (no DLT point either).
        let roi: Vec<bool> = (0..20).map(|i| i % 2 == 0).collect();
        let inputs_roi = ChunkInputs {
            roi: Some(&roi),
            ..inputs
        };
        let set = sample_chunks(inputs_roi, 3.0, &params, &mut PcgDraws::new(7)).unwrap();
        assert!(
            set.chunks
                .iter()
                .all(|c| c.pixels.iter().all(|p| p % 2 == 0))
        );
        // An uncovered DLT point enters even when its dense point is far away.
        let mut ff_far = ff.clone();
        ff_far[3 * 12] = 1000.0;
        let inputs_far = ChunkInputs {
            ff_points: &ff_far,
            ..inputs
        };
        let mut s = ChunkSampler::new(
            inputs_far,
            4.0,
            ChunkParams {
                chunk_size: 0.5,
                ..params.clone()
            },
        )
        .unwrap();
        let c = s.next_chunk(&mut Replay(vec![5], 0)).unwrap().unwrap();
        assert_eq!(c.pixels, vec![8, 9, 10, 11, 12]); // 12 enters through its DLT point
        // Uncovered now: 0, 2, 4, 6, 14, 16, 18; #4 -> centre 14, box [12, 16]: the covered DLT
        // point of pixel 12 no longer pulls its pixel in (its dense point is far away).
        let c = s.next_chunk(&mut Replay(vec![4], 0)).unwrap().unwrap();
        assert_eq!(c.center, [14.0, 0.0, 0.0]);
        assert_eq!(c.pixels, vec![13, 14, 15, 16]);
        // max_chunks_after_converge = 0: the first chunk is accepted only if it adds DLT pixels (it always does).
        let p0 = ChunkParams {
            max_chunks_after_converge: 0,
            ..params
        };
        let set = sample_chunks(inputs, 3.0, &p0, &mut PcgDraws::new(3)).unwrap();
        assert!(!set.chunks.is_empty());
    }

    #[test]
    fn degenerate_coincident_points_do_not_loop() {
        let ff = vec![0.0f32; 3 * 50];
        let dlt = vec![0.0f32; 3 * 50];
        let mask = vec![true; 50];
        let params = ChunkParams {
            chunk_size: 0.2,
            max_pixels: 10,
            min_dlt: 1,
            min_pixels: 1,
            max_chunks_after_converge: 100,
        };
        let inputs = ChunkInputs {
            ff_points: &ff,
            dlt_points: &dlt,
            dlt_mask: &mask,
            roi: None,
        };
        let set = sample_chunks(inputs, 1.0, &params, &mut PcgDraws::new(0)).unwrap();
        assert!(set.chunks.is_empty());
        assert_eq!(set.stop, StopReason::Failures);
    }

    #[test]
    fn pcg_draws_deterministic_and_in_range() {
        let mut a = PcgDraws::for_scene("demo", None);
        let mut b = PcgDraws::new(3594706848);
        let mut c = PcgDraws::for_scene("demo", Some(42));
        let va: Vec<usize> = (0..50).map(|_| a.draw(17)).collect();
        let vb: Vec<usize> = (0..50).map(|_| b.draw(17)).collect();
        let vc: Vec<usize> = (0..50).map(|_| c.draw(17)).collect();
        assert_eq!(va, vb);
        assert_ne!(va, vc);
        assert!(va.iter().all(|&v| v < 17));
    }

    #[test]
    fn training_chunk() {
        let (ff, dlt, mask) = line_scene(20);
        let params = ChunkParams {
            chunk_size: 0.5,
            max_pixels: 100,
            min_dlt: 2,
            min_pixels: 3,
            max_chunks_after_converge: 100,
        };
        let inputs = ChunkInputs {
            ff_points: &ff,
            dlt_points: &dlt,
            dlt_mask: &mask,
            roi: None,
        };
        let c = sample_training_chunk(inputs, 4.0, &params, &mut PcgDraws::new(5))
            .unwrap()
            .unwrap();
        assert!(c.n_dlt >= 2 && c.pixels.len() >= 3);
        let impossible = ChunkParams {
            min_dlt: 50,
            ..params
        };
        assert!(
            sample_training_chunk(inputs, 4.0, &impossible, &mut PcgDraws::new(5))
                .unwrap()
                .is_none()
        );
    }
}
