//! The whole SfM stage (`sfm.md` §1–§10): ensembling, masks, BA track selection, bundle
//! adjustment, epipolar filter, DLT triangulation and scatter.
//!
//! Inputs: feed-forward points / cameras (feed-forward frame, ff pixels, pixel-centre
//! convention), the ff images and the dense matches of one or more matchers. Output: the SfM
//! result in the SfM frame (the frame BA leaves the cameras in) plus a summary.

use std::time::Instant;

use ggpt_core::Progress;
use ggpt_core::{Cameras, Dims, FeedForward, MatchSet, SfmResult};
use nalgebra::{Matrix3, Point3, Vector2};

use crate::ba::{BaObservation, BaOptions, BaProblem, CameraModel, LossFunction, bundle_adjust};
use crate::dlt::{DltOptions, DltOutput, triangulate_ba_tracks, triangulate_tracks};
use crate::ensemble::ensemble;
use crate::epipolar::epipolar_filter;
use crate::error::{Result, SfmError};
use crate::masks::{Preset, Thresholds, compute_masks};
use crate::matches::{Correspondences, INVALID_SCORE};
use crate::scatter::{ScatterOptions, ScatterResult, scatter};
use crate::tracks::{BaTracks, TrackSelection, build_ba_tracks, select_ba_tracks, shi_tomasi};

/// Cauchy loss scale of the BA (pixels, `sfm.md` §5 / §7.1).
pub const BA_CAUCHY_SCALE: f64 = 0.1;

/// Focal offset (pixels) of the older official BA initialisation (`sfm.md` §7.1: it added 0.5 to
/// the whole intrinsic matrix; only `fx`, `fy` matter once the principal point is fixed).
pub const LEGACY_FOCAL_OFFSET: f64 = 0.5;

/// Configuration of the SfM stage.
#[derive(Debug, Clone)]
pub struct SfmConfig {
    /// Preset the values came from (recorded in the summary).
    pub preset: Preset,
    /// Filtering thresholds (`sfm.md` §5).
    pub thresholds: Thresholds,
    /// BA camera model (`benchmark`: PINHOLE, `demo` / `many-views`: SIMPLE_PINHOLE).
    pub camera_model: CameraModel,
    /// One camera shared by all views (all presets: yes).
    pub shared_camera: bool,
    /// Refine the focal length(s) (all presets: yes).
    pub refine_focal: bool,
    /// BA robust loss (all presets: Cauchy, scale 0.1 px).
    pub ba_loss: LossFunction,
    /// Solver options (default [`BaOptions::official`]: the official pycolmap call, free gauge,
    /// 100 iterations, which reproduces Ceres' path and its converged cost on `sfm_small`;
    /// [`BaOptions::default`] is the faster project solver of `sfm.md` §7.2, see `docs/ba.md`).
    pub ba_options: BaOptions,
    /// Older official behaviour (the fork that produced `sfm_small`'s `ba/*`): add
    /// [`LEGACY_FOCAL_OFFSET`] px to the initial focal length(s) of the BA (default off: the newest
    /// official code shifts only the principal point, `sfm.md` §7.1).
    pub legacy_focal_offset: bool,
    /// Scatter options (clamp vs drop outside observations).
    pub scatter: ScatterOptions,
    /// [project] optional DLT cheirality test (default off).
    pub cheirality: bool,
    /// Seed of every random choice (default 42; the stage is deterministic).
    pub seed: u64,
    /// Stop request, checked before every step and every BA iteration (it replaces
    /// `ba_options.cancel`): a cancelled token ends the run with [`SfmError::Cancelled`].
    pub cancel: ggpt_core::Cancel,
}

impl SfmConfig {
    /// The configuration of a preset (`sfm.md` §5).
    pub fn preset(p: Preset) -> Self {
        SfmConfig {
            preset: p,
            thresholds: Thresholds::preset(p),
            camera_model: match p {
                Preset::Benchmark => CameraModel::Pinhole,
                Preset::Demo | Preset::ManyViews => CameraModel::SimplePinhole,
            },
            shared_camera: true,
            refine_focal: true,
            ba_loss: LossFunction::Cauchy {
                scale: BA_CAUCHY_SCALE,
            },
            ba_options: BaOptions::official(),
            legacy_focal_offset: false,
            scatter: ScatterOptions::default(),
            cheirality: false,
            seed: 42,
            cancel: ggpt_core::Cancel::default(),
        }
    }
}

/// Bundle-adjustment part of the summary.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct BaSummary {
    /// The BA ran and its cameras are used.
    pub success: bool,
    /// Cameras were given by the caller (no BA run).
    pub cameras_given: bool,
    /// BA points (selected tracks minus excluded ones).
    pub points: usize,
    /// BA observations.
    pub observations: usize,
    /// Selected tracks left out (non-finite / `|c| >= 3000` initial point).
    pub excluded_points: usize,
    /// Cost `½ Σ ρ(‖r‖²)` before / after (pixels²).
    pub initial_cost: f64,
    /// Cost after.
    pub final_cost: f64,
    /// LM iterations.
    pub iterations: usize,
    /// Solver message.
    pub message: String,
}

/// Summary of one run (written as `summary.json` by the binary).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SfmSummary {
    /// Preset name.
    pub preset: String,
    /// Thresholds used.
    pub thresholds: Thresholds,
    /// BA camera model (`PINHOLE` / `SIMPLE_PINHOLE`): the model of the cameras of the result.
    pub camera_model: CameraModel,
    /// Views, ff height and width.
    pub views: usize,
    /// ff height.
    pub height: usize,
    /// ff width.
    pub width: usize,
    /// Number of matchers ensembled.
    pub matchers: usize,
    /// Off-diagonal entries won by each matcher.
    pub ensemble_wins: Vec<usize>,
    /// Ranking score used for the BA track selection (`given` or `shi-tomasi`).
    pub ranking: String,
    /// Off-diagonal `M_BA` / `M_DLT` entries (before the epipolar filter).
    pub ba_mask_entries: usize,
    /// Off-diagonal `M_DLT` entries before the epipolar filter.
    pub dlt_mask_entries: usize,
    /// Views whose tracks have no valid off-diagonal match (fallback: no DLT point from them).
    pub views_without_matches: Vec<usize>,
    /// BA tracks selected.
    pub tracks_selected: usize,
    /// BA tracks covering each view after the selection.
    pub track_coverage: Vec<usize>,
    /// Bundle adjustment.
    pub ba: BaSummary,
    /// `M_DLT` entries removed by the epipolar filter.
    pub epipolar_removed: usize,
    /// DLT tracks: input (≥ 2 views), after `|w|`, after reprojection, after angle, kept.
    pub dlt_tracks: [usize; 5],
    /// Scatter: observations written, clamped, dropped.
    pub scatter_observations: usize,
    /// Observations clamped onto the border.
    pub scatter_clamped: usize,
    /// Observations dropped.
    pub scatter_dropped: usize,
    /// Pixels with a DLT point.
    pub points_kept: usize,
    /// Wall-clock seconds per stage, in order.
    pub timings: Vec<(String, f64)>,
}

/// Everything [`run_sfm`] produces.
#[derive(Debug, Clone)]
pub struct SfmOutput {
    /// Cameras, point map and flags (`sfm.md` §1).
    pub result: SfmResult,
    /// `[N, h, w]` DLT points per pixel (`dlt_count`, saturated at `u16::MAX`).
    pub dlt_count: Vec<u16>,
    /// `[N, h, w]` mean reprojection error of the contributing tracks (`dlt_reproj`, px).
    pub dlt_reproj: Vec<f32>,
    /// Ensembled correspondences (ff pixels).
    pub correspondences: Correspondences,
    /// `[N, N hw]` DLT visibility after the epipolar filter.
    pub dlt_visibility: Vec<bool>,
    /// Triangulated tracks.
    pub dlt: DltOutput,
    /// BA track selection record.
    pub selection: TrackSelection,
    /// BA input.
    pub ba_tracks: BaTracks,
    /// The BA tracks' points in the SfM frame, one per [`BaTracks::points`] entry: the points
    /// refined by the bundle adjustment when it ran and succeeded (`ba_points_refined`), otherwise
    /// (BA skipped with given cameras, BA failed, no track) the linear triangulation of each
    /// track's BA observations with the output cameras (NaN where it fails, `|w| <= 1e-10`).
    /// Exported as the COLMAP model's `points3D` (`output::colmap_model`).
    pub ba_points: Vec<Point3<f64>>,
    /// Whether [`SfmOutput::ba_points`] are the points refined by the bundle adjustment.
    pub ba_points_refined: bool,
    /// Summary.
    pub summary: SfmSummary,
}

/// Name of the SfM stage in progress reports.
pub const PROGRESS_STAGE: &str = "sfm";

/// The steps of [`run_sfm_correspondences`], in order: one progress unit each.
const STEPS: [&str; 7] = [
    "ensemble",
    "masks",
    "track selection",
    "bundle adjustment",
    "epipolar filter",
    "triangulation",
    "scatter",
];

/// Step timings and progress reports of one SfM run.
struct Stages<'a> {
    progress: &'a mut dyn FnMut(Progress),
    cancel: &'a ggpt_core::Cancel,
    timings: Vec<(String, f64)>,
    done: u64,
    t: Instant,
}

impl<'a> Stages<'a> {
    fn new(progress: &'a mut dyn FnMut(Progress), cancel: &'a ggpt_core::Cancel) -> Self {
        Stages {
            progress,
            cancel,
            timings: Vec::new(),
            done: 0,
            t: Instant::now(),
        }
    }
    fn report(&mut self, detail: &'static str) {
        let p = Progress::new(PROGRESS_STAGE, self.done, STEPS.len() as u64);
        (self.progress)(p.with_detail(detail));
    }
    /// Reports the start of step `name`; [`SfmError::Cancelled`] when the stop was requested.
    fn start(&mut self, name: &'static str) -> Result<()> {
        if self.cancel.is_cancelled() {
            return Err(SfmError::Cancelled);
        }
        self.report(name);
        self.t = Instant::now();
        Ok(())
    }
    fn done(&mut self, name: &str) {
        self.timings
            .push((name.to_string(), self.t.elapsed().as_secs_f64()));
        tracing::debug!(
            stage = name,
            seconds = self.t.elapsed().as_secs_f64(),
            "stage done"
        );
        self.done += 1;
        if self.done == STEPS.len() as u64 {
            self.report("");
        }
    }
}

fn check_inputs(ff: &FeedForward, images: &[f32], dims: Dims) -> Result<()> {
    let px = dims.pixels();
    if dims.n < 2 {
        return Err(SfmError::Invalid(format!(
            "the SfM stage needs at least 2 views, got {}",
            dims.n
        )));
    }
    if images.len() != 3 * px {
        return Err(SfmError::Shape(format!(
            "images: {} values, expected N*h*w*3 = {} (N={} h={} w={})",
            images.len(),
            3 * px,
            dims.n,
            dims.h,
            dims.w
        )));
    }
    if ff.points.len() != 3 * px {
        return Err(SfmError::Shape(format!(
            "feed-forward points: {} values, expected {}",
            ff.points.len(),
            3 * px
        )));
    }
    let c = &ff.cameras;
    if c.cam_from_world.len() != dims.n || c.intrinsics.len() != dims.n {
        return Err(SfmError::Shape(format!(
            "feed-forward cameras: {} extrinsics / {} intrinsics for {} views",
            c.cam_from_world.len(),
            c.intrinsics.len(),
            dims.n
        )));
    }
    for v in 0..dims.n {
        if c.cam_from_world[v]
            .iter()
            .chain(c.intrinsics[v].iter())
            .any(|x| !x.is_finite())
        {
            return Err(SfmError::Invalid(format!(
                "feed-forward camera of view {v} has a non-finite entry"
            )));
        }
        let k = &c.intrinsics[v];
        if !(k[(0, 0)] > 0.0 && k[(1, 1)] > 0.0) {
            return Err(SfmError::Invalid(format!(
                "feed-forward intrinsics of view {v}: focal lengths must be positive, got fx={} fy={}",
                k[(0, 0)],
                k[(1, 1)]
            )));
        }
    }
    Ok(())
}

/// Runs the SfM stage on matches stored as [`MatchSet`]s (ff pixels, `formats.md` §5.2).
/// See [`run_sfm_correspondences`].
pub fn run_sfm(
    ff: &FeedForward,
    images: &[f32],
    dims: Dims,
    matches: &[MatchSet],
    cfg: &SfmConfig,
) -> Result<SfmOutput> {
    run_sfm_with_progress(
        ff,
        images,
        dims,
        matches,
        cfg,
        &mut ggpt_core::progress::ignore,
    )
}

/// [`run_sfm`] with progress reports (stage [`PROGRESS_STAGE`], one unit per step).
pub fn run_sfm_with_progress(
    ff: &FeedForward,
    images: &[f32],
    dims: Dims,
    matches: &[MatchSet],
    cfg: &SfmConfig,
    progress: &mut dyn FnMut(Progress),
) -> Result<SfmOutput> {
    let sets = matches
        .iter()
        .map(|m| Correspondences::from_match_set(m, dims))
        .collect::<Result<Vec<_>>>()?;
    let rank = matches.iter().find_map(|m| m.rank_scores.clone());
    run_sfm_correspondences_with_progress(ff, images, &sets, rank.as_deref(), cfg, None, progress)
}

/// Runs the SfM stage.
///
/// * `ff`: feed-forward points `[N, h, w, 3]` (feed-forward frame) and cameras (`cam_from_world`,
///   K in ff pixels, pixel-centre convention; the BA keeps its principal point, e.g. VGGT's
///   `(w/2, h/2)`, and the output `K_sfm` has `((w-1)/2, (h-1)/2)`, `sfm.md` §7.1);
/// * `images`: `[N, h, w, 3]` RGB in `[0, 1]` (Shi–Tomasi ranking when `rank` is `None`);
/// * `sets`: correspondences of each matcher (config order, ties go to the first);
/// * `rank`: optional `[N hw]` ranking score (e.g. SuperPoint);
/// * `fixed_cameras`: skip the BA and use these cameras (SfM frame) instead (testing / replay).
///
/// Errors: shape mismatches, `N < 2`, non-finite or invalid feed-forward cameras, all-zero
/// scores. Fallbacks (documented in `docs/sfm.md`): a BA that fails or has no track keeps the
/// feed-forward cameras with `camera_success = false`; views without valid matches get no DLT
/// point of their own and are listed in the summary.
pub fn run_sfm_correspondences(
    ff: &FeedForward,
    images: &[f32],
    sets: &[Correspondences],
    rank: Option<&[f32]>,
    cfg: &SfmConfig,
    fixed_cameras: Option<&Cameras>,
) -> Result<SfmOutput> {
    let mut ignore = ggpt_core::progress::ignore;
    run_sfm_correspondences_with_progress(ff, images, sets, rank, cfg, fixed_cameras, &mut ignore)
}

/// [`run_sfm_correspondences`] with progress reports (stage [`PROGRESS_STAGE`], one unit per
/// step; the detail names the step in progress).
pub fn run_sfm_correspondences_with_progress(
    ff: &FeedForward,
    images: &[f32],
    sets: &[Correspondences],
    rank: Option<&[f32]>,
    cfg: &SfmConfig,
    fixed_cameras: Option<&Cameras>,
    progress: &mut dyn FnMut(Progress),
) -> Result<SfmOutput> {
    let first = sets
        .first()
        .ok_or_else(|| SfmError::Invalid("no matches given".into()))?;
    let dims = first.dims;
    check_inputs(ff, images, dims)?;
    cfg.thresholds.validate()?;
    let n = dims.n;
    let hw = dims.hw();
    let nt = n * hw;
    let mut st = Stages::new(progress, &cfg.cancel);

    st.start("ensemble")?;
    let (corr, sel_idx) = ensemble(sets)?;
    let mut wins = vec![0usize; sets.len()];
    for t in 0..n {
        for s in 0..n {
            if s != t {
                let b = corr.idx(t, s, 0);
                for &m in &sel_idx[b..b + hw] {
                    if let Some(w) = wins.get_mut(m as usize) {
                        *w += 1;
                    }
                }
            }
        }
    }
    let any_valid = (0..n).any(|t| {
        (0..n).any(|s| {
            s != t
                && corr.scores[corr.idx(t, s, 0)..corr.idx(t, s, 0) + hw]
                    .iter()
                    .any(|&v| v >= INVALID_SCORE)
        })
    });
    if !any_valid {
        return Err(SfmError::Invalid("all matcher scores are zero (or invalid: non-finite or below 1e-5): there is no correspondence to use".into()));
    }
    let views_without_matches: Vec<usize> = corr
        .valid_matches_per_view()
        .iter()
        .enumerate()
        .filter(|(_, c)| **c == 0)
        .map(|(v, _)| v)
        .collect();
    if !views_without_matches.is_empty() {
        tracing::warn!(
            ?views_without_matches,
            "views without any valid match: they get no DLT point of their own"
        );
    }
    st.done("ensemble");

    st.start("masks")?;
    let (m_ba, mut m_dlt) = compute_masks(&corr, &cfg.thresholds)?;
    let off_diag = |m: &[bool]| m.iter().filter(|&&b| b).count() - nt;
    let ba_mask_entries = off_diag(&m_ba);
    let dlt_mask_entries = off_diag(&m_dlt);
    st.done("masks");

    st.start("track selection")?;
    let (rank_owned, ranking) = match rank {
        Some(r) => {
            if r.len() != nt {
                return Err(SfmError::Shape(format!(
                    "ranking score: {} values, expected N*h*w = {nt}",
                    r.len()
                )));
            }
            (r.to_vec(), "given")
        }
        None => (shi_tomasi(images, n, dims.h, dims.w)?, "shi-tomasi"),
    };
    let selection = select_ba_tracks(&m_ba, n, hw, &rank_owned, cfg.thresholds.mintrack_per_view)?;
    let ba_tracks = build_ba_tracks(&selection.track_ids(), &m_ba, &corr, &ff.points)?;
    st.done("track selection");

    st.start("bundle adjustment")?;
    let (cameras, ba, refined_points) = match fixed_cameras {
        Some(c) => {
            if c.cam_from_world.len() != n || c.intrinsics.len() != n {
                return Err(SfmError::Shape(format!(
                    "given cameras: {} / {} for {n} views",
                    c.cam_from_world.len(),
                    c.intrinsics.len()
                )));
            }
            if !c.is_finite() {
                return Err(SfmError::Invalid(
                    "given cameras have a non-finite entry".into(),
                ));
            }
            let ba = BaSummary {
                success: true,
                cameras_given: true,
                points: ba_tracks.points.len(),
                observations: ba_tracks.observations.len(),
                excluded_points: ba_tracks.excluded,
                initial_cost: f64::NAN,
                final_cost: f64::NAN,
                iterations: 0,
                message: "cameras given, BA skipped".into(),
            };
            (c.clone(), ba, None)
        }
        None => run_ba(ff, dims, &ba_tracks, cfg)?,
    };
    let ba_points_refined = refined_points.is_some();
    let ba_points = match refined_points {
        Some(p) => p,
        None => triangulate_ba_tracks(&ba_tracks, &cameras)?,
    };
    st.done("bundle adjustment");

    st.start("epipolar filter")?;
    let epipolar_removed = epipolar_filter(
        &corr,
        &mut m_dlt,
        &cameras,
        cfg.thresholds.max_epipolar_error,
    )?;
    st.done("epipolar filter");

    st.start("triangulation")?;
    let opts = DltOptions {
        max_reproj_error: cfg.thresholds.max_reproj_error,
        min_tri_angle_deg: cfg.thresholds.min_tri_angle_deg,
        cheirality: cfg.cheirality,
    };
    let dlt = triangulate_tracks(&corr, &m_dlt, &cameras, &opts)?;
    st.done("triangulation");

    st.start("scatter")?;
    let sc: ScatterResult = scatter(&corr, &m_dlt, &dlt, &cfg.scatter)?;
    st.done("scatter");

    let points_kept = sc.mask.iter().filter(|&&b| b).count();
    let summary = SfmSummary {
        preset: cfg.preset.name().into(),
        thresholds: cfg.thresholds,
        camera_model: cfg.camera_model,
        views: n,
        height: dims.h,
        width: dims.w,
        matchers: sets.len(),
        ensemble_wins: wins,
        ranking: ranking.into(),
        ba_mask_entries,
        dlt_mask_entries,
        views_without_matches,
        tracks_selected: selection.selected_order.len(),
        track_coverage: selection.coverage_final.clone(),
        ba: ba.clone(),
        epipolar_removed,
        dlt_tracks: dlt.counts(),
        scatter_observations: sc.observations,
        scatter_clamped: sc.clamped,
        scatter_dropped: sc.dropped,
        points_kept,
        timings: st.timings.clone(),
    };
    let result = SfmResult {
        points: sc.points,
        mask: sc.mask,
        cameras,
        camera_success: ba.success,
        points_success: points_kept > 0,
    };
    Ok(SfmOutput {
        result,
        dlt_count: sc
            .count
            .iter()
            .map(|&c| c.min(u16::MAX as u32) as u16)
            .collect(),
        dlt_reproj: sc.reproj,
        correspondences: corr,
        dlt_visibility: m_dlt,
        dlt,
        selection,
        ba_tracks,
        ba_points,
        ba_points_refined,
        summary,
    })
}

/// Builds the [`BaProblem`] of the selected tracks (`sfm.md` §7.1): initial cameras and
/// intrinsics = feed-forward (feed-forward frame; focal + [`LEGACY_FOCAL_OFFSET`] with
/// [`SfmConfig::legacy_focal_offset`]), observations in ff pixels (pixel-centre convention),
/// principal point fixed at the feed-forward one (`sfm.md` §7.1: the official code hands
/// `K_ff + 0.5` to COLMAP in f32, so the principal point takes the same f32 round trip as the
/// observations).
pub fn ba_problem(ff: &FeedForward, dims: Dims, tracks: &BaTracks, cfg: &SfmConfig) -> BaProblem {
    let focal_offset = if cfg.legacy_focal_offset {
        LEGACY_FOCAL_OFFSET
    } else {
        0.0
    };
    BaProblem {
        cam_from_world: ff.cameras.cam_from_world.clone(),
        intrinsics: ff
            .cameras
            .intrinsics
            .iter()
            .map(|k| {
                let mut k = *k;
                k[(0, 0)] += focal_offset;
                k[(1, 1)] += focal_offset;
                k[(0, 2)] = colmap_round_trip(k[(0, 2)]);
                k[(1, 2)] = colmap_round_trip(k[(1, 2)]);
                k
            })
            .collect(),
        points: tracks.points.clone(),
        observations: tracks
            .observations
            .iter()
            .map(|o| BaObservation {
                view: o.view,
                point: o.point,
                xy: Vector2::new(colmap_round_trip(o.xy[0]), colmap_round_trip(o.xy[1])),
            })
            .collect(),
        model: cfg.camera_model,
        shared_camera: cfg.shared_camera,
        refine_focal: cfg.refine_focal,
        loss: cfg.ba_loss,
        image_size: (dims.h, dims.w),
    }
}

/// An f32 ff-pixel coordinate as the official BA sees it (`sfm.md` §7.1 problem layout): shifted
/// into COLMAP's corner convention in f32 (`f32(x + 0.5)`), widened to f64 and shifted back (exact
/// in f64). Keeps our BA problem bit-identical to the official one, so both follow the same LM path.
fn colmap_round_trip(x: f64) -> f64 {
    f64::from(x as f32 + 0.5) - 0.5
}

/// Initial cameras with the principal point moved to the image centre (the BA failure fallback).
fn initial_cameras(ff: &FeedForward, dims: Dims) -> Cameras {
    let (cx, cy) = ggpt_core::camera::centred_principal_point(dims.h, dims.w);
    let intrinsics = ff
        .cameras
        .intrinsics
        .iter()
        .map(|k| Matrix3::new(k[(0, 0)], 0.0, cx, 0.0, k[(1, 1)], cy, 0.0, 0.0, 1.0))
        .collect();
    Cameras {
        cam_from_world: ff.cameras.cam_from_world.clone(),
        intrinsics,
    }
}

/// Output cameras, BA summary and, when the BA succeeded, its refined points (one per
/// [`BaTracks::points`] entry, SfM frame).
type BaRun = (Cameras, BaSummary, Option<Vec<Point3<f64>>>);

/// Runs the BA (see [`BaRun`]).
fn run_ba(ff: &FeedForward, dims: Dims, tracks: &BaTracks, cfg: &SfmConfig) -> Result<BaRun> {
    let mut summary = BaSummary {
        success: false,
        cameras_given: false,
        points: tracks.points.len(),
        observations: tracks.observations.len(),
        excluded_points: tracks.excluded,
        initial_cost: 0.0,
        final_cost: 0.0,
        iterations: 0,
        message: String::new(),
    };
    if tracks.points.is_empty() {
        summary.message = "no BA track selected: keeping the feed-forward cameras".into();
        tracing::warn!("{}", summary.message);
        return Ok((initial_cameras(ff, dims), summary, None));
    }
    let problem = ba_problem(ff, dims, tracks, cfg);
    let options = BaOptions {
        cancel: cfg.cancel.clone(),
        ..cfg.ba_options.clone()
    };
    let report = bundle_adjust(&problem, &options)?;
    summary.initial_cost = report.initial_cost;
    summary.final_cost = report.final_cost;
    summary.iterations = report.iterations;
    summary.message = report.message.clone();
    let cams = Cameras {
        cam_from_world: report.cam_from_world,
        intrinsics: report.intrinsics,
    };
    if report.success && cams.is_finite() {
        summary.success = true;
        Ok((cams, summary, Some(report.points)))
    } else {
        tracing::warn!(message = %summary.message, "bundle adjustment failed: keeping the feed-forward cameras");
        Ok((initial_cameras(ff, dims), summary, None))
    }
}
