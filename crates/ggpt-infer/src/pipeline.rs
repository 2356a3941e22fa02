//! Whole-scene inference (`ggpt-infer run`): SfM when needed, pre-alignment, chunking, network,
//! fusion, export, evaluation and error maps, with wall time and peak memory per stage.
//!
//! Frames: refined outputs live in the SfM frame (scene units, `pipeline.md` §1); the
//! evaluation aligns every prediction to the GT frame (metres).

use std::path::{Path, PathBuf};
use std::time::Instant;

use ggpt_core::chunking::ChunkingSettings;
use ggpt_core::{Progress, Scene, SfmResult};
use ggpt_scene::ChunkRefiner;
use ggpt_scene::chunk_settings::ResolvedChunking;
use ggpt_scene::driver::{RefineOptions, RefinedScene, refine_scene_with_progress};
use ggpt_scene::export::{ExportOptions, ExportSummary};
use ggpt_sfm::ba::CameraModel;
use ggpt_sfm::masks::Preset;
use ggpt_sfm::pipeline::{SfmConfig, SfmSummary, run_sfm_with_progress};

use crate::refiner::{BurnRefiner, RefinerStats};
use crate::rss::{StageLog, StageTiming, mib, peak_rss_bytes, reset_peak_rss};
use crate::run_output::RunOutput;
use crate::{InferError, Result};
use ggpt_eval::error_maps::{DEFAULT_ERROR_MAP_MAX_CM, ErrorMapInputs, render_error_maps};
use ggpt_eval::refinement::{SceneEvaluation, evaluate_refinement};

/// A [`ChunkRefiner`] that reports what it did (the network stage of the timing table).
pub trait MeasuredRefiner: ChunkRefiner {
    /// Returns the statistics gathered since the last call and resets them.
    fn take_stats(&mut self) -> RefinerStats;
}

impl MeasuredRefiner for BurnRefiner {
    fn take_stats(&mut self) -> RefinerStats {
        BurnRefiner::take_stats(self)
    }
}

/// Options of [`run_scene`].
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// Alignment, chunking, batching, fusion (`pipeline.md` §3-§8). `refine.chunking` is the
    /// base of the chunk-sampler resolution ([`crate::engine::Refiner::refine`]), `refine.cancel`
    /// the stop request of the whole run.
    pub refine: RefineOptions,
    /// Explicit chunk-sampler settings (`--chunk-size`, ...): they win over the model's
    /// `inference.json`, which wins over `refine.chunking` (resolved by
    /// [`crate::engine::Refiner::refine`]; [`run_scene`] uses `refine.chunking` as given).
    pub chunking: ChunkingSettings,
    /// PLY / arrays / COLMAP export (`pipeline.md` §9).
    pub export: ExportOptions,
    /// SfM threshold preset when the SfM stage has to run (default `demo`, the user-facing one).
    pub sfm_preset: Preset,
    /// Evaluate against the ground truth when the scene has one.
    pub evaluate: bool,
    /// Write per-view error maps with the evaluation.
    pub error_maps: bool,
    /// Upper end of the error-map colour scale (cm).
    pub error_map_max_cm: f64,
}

impl Default for RunOptions {
    fn default() -> Self {
        RunOptions {
            refine: RefineOptions::default(),
            chunking: ChunkingSettings::default(),
            export: ExportOptions::default(),
            sfm_preset: Preset::Demo,
            evaluate: true,
            error_maps: true,
            error_map_max_cm: DEFAULT_ERROR_MAP_MAX_CM,
        }
    }
}

/// What [`run_scene`] produced.
#[derive(Debug, Clone)]
pub struct RunReport {
    /// Output folder.
    pub out_dir: PathBuf,
    /// Fused result (SfM frame).
    pub refined: RefinedScene,
    /// The SfM result used (moved out of `scene.sfm`, or computed).
    pub sfm: SfmResult,
    /// Summary of the SfM stage when it ran here.
    pub sfm_summary: Option<SfmSummary>,
    /// Export summary.
    pub export: ExportSummary,
    /// Evaluation (scenes with ground truth).
    pub evaluation: Option<SceneEvaluation>,
    /// Network statistics.
    pub network: RefinerStats,
    /// Wall time and peak memory per stage, in order.
    pub stages: Vec<StageTiming>,
}

/// The SfM result of `scene`, with the summary of the SfM stage when it ran here: the scene's
/// own result is moved out of `scene.sfm` (no copy; summary `None`), else the SfM stage
/// (`sfm.md`) runs on the scene's feed-forward outputs and matches. `progress` receives the SfM
/// stage's reports (`ggpt_sfm::pipeline::PROGRESS_STAGE`); `cancel` stops it between steps and
/// BA iterations.
pub fn ensure_sfm(
    scene: &mut Scene,
    preset: Preset,
    seed: u64,
    cancel: &ggpt_core::Cancel,
    progress: &mut dyn FnMut(Progress),
) -> Result<(SfmResult, Option<SfmSummary>)> {
    if let Some(sfm) = scene.sfm.take() {
        return Ok((sfm, None));
    }
    let ff = scene.ff.as_ref().ok_or_else(|| {
        InferError::Invalid(format!("scene {}: no feed-forward prediction", scene.name))
    })?;
    if scene.matches.is_empty() {
        return Err(InferError::Invalid(format!(
            "scene {}: neither an SfM result nor dense matches: cannot run the SfM stage (give a scene with sfm_dlt_outputs / sfm.npz, or with matches/)",
            scene.name
        )));
    }
    let mut cfg = SfmConfig::preset(preset);
    cfg.seed = seed;
    cfg.cancel = cancel.clone();
    let out = run_sfm_with_progress(
        ff,
        &scene.images,
        scene.dims,
        &scene.matches,
        &cfg,
        progress,
    )?;
    let dlt = out.result.mask.iter().filter(|&&m| m).count();
    tracing::info!(
        "SfM ({:?} preset): BA {} ({} tracks), {dlt} DLT pixels",
        preset,
        if out.result.camera_success {
            "succeeded"
        } else {
            "failed (feed-forward cameras kept)"
        },
        out.summary.tracks_selected
    );
    Ok((out.result, Some(out.summary)))
}

/// The refinement of one scene, before anything is written: what [`refine_run`] computed.
#[derive(Debug, Clone)]
pub struct RefinedRun {
    /// Fused result (SfM frame).
    pub refined: RefinedScene,
    /// The SfM result used (moved out of `scene.sfm`, or computed).
    pub sfm: SfmResult,
    /// Summary of the SfM stage when it ran here.
    pub sfm_summary: Option<SfmSummary>,
    /// Network statistics.
    pub network: RefinerStats,
    /// The chunk sampler's settings and where each came from, when they were resolved for a
    /// model ([`crate::engine::Refiner::refine`]; `None` from [`refine_run`], which uses
    /// `opts.refine.chunking` as given).
    pub chunking: Option<ResolvedChunking>,
}

/// SfM if needed ([`ensure_sfm`]: the scene's SfM result, or the computed one, moves into
/// [`RefinedRun::sfm`] and `scene.sfm` is left `None`), pre-alignment, chunking, network and
/// fusion; writes nothing. `log` receives the stages `sfm`, `prealign+chunking`, `network`,
/// `records+fusion`; `progress` the reports of the SfM stage (when it runs) and of the
/// refinement (stage `ggpt_scene::driver::PROGRESS_STAGE`, one unit per chunk). The stop
/// requests of `opts.refine.cancel` are honoured between SfM steps, BA iterations and forwards.
pub fn refine_run(
    scene: &mut Scene,
    refiner: &mut dyn MeasuredRefiner,
    opts: &RunOptions,
    log: &mut StageLog,
    progress: &mut dyn FnMut(Progress),
) -> Result<RefinedRun> {
    log.start("sfm");
    let (sfm, sfm_summary) = ensure_sfm(
        scene,
        opts.sfm_preset,
        opts.refine.seed,
        &opts.refine.cancel,
        progress,
    )?;
    log.finish();

    // Refinement: prealign + chunking | network | records + un-normalise + fusion.
    let _ = refiner.take_stats();
    reset_peak_rss();
    let t0 = Instant::now();
    let refined = refine_scene_with_progress(scene, &sfm, refiner, &opts.refine, progress)?;
    let total = t0.elapsed().as_secs_f64();
    let stats = refiner.take_stats();
    let peak_after = peak_rss_bytes().map(mib);
    match stats.first_call() {
        Some(first) => {
            let chunking = first.duration_since(t0).as_secs_f64();
            let network = stats.network_seconds();
            log.push(
                "prealign+chunking",
                chunking,
                stats.peak_rss_before_first_forward.map(mib).or(peak_after),
            );
            log.push("network", network, peak_after);
            log.push(
                "records+fusion",
                (total - chunking - network).max(0.0),
                peak_after,
            );
        }
        None => {
            log.push("prealign+chunking", total, peak_after);
            log.push("network", 0.0, None);
            log.push("records+fusion", 0.0, None);
        }
    }
    tracing::info!(
        "refined {} chunks in {} forwards ({} tokens); {} of {} pixels covered",
        refined.chunks.len(),
        refined.forwards,
        refined.total_tokens,
        refined.covered.iter().filter(|&&c| c).count(),
        refined.dims.pixels()
    );
    Ok(RefinedRun {
        refined,
        sfm,
        sfm_summary,
        network: stats,
        chunking: None,
    })
}

/// Runs everything after the scene is loaded: [`refine_run`], then [`save_run`] into `out`
/// (created first, so that an unwritable folder fails before any work).
#[allow(clippy::too_many_arguments)]
pub fn run_scene(
    scene: &mut Scene,
    refiner: &mut dyn MeasuredRefiner,
    opts: &RunOptions,
    out: &Path,
    config: &serde_json::Value,
    meta: serde_json::Value,
    log: &mut StageLog,
    progress: &mut dyn FnMut(Progress),
) -> Result<RunReport> {
    let output = RunOutput::create(out)?;
    let run = refine_run(scene, refiner, opts, log, progress)?;
    save_into(output, run, scene, opts, config, meta, log)
}

/// Writes a [`RefinedRun`] of `scene` into `out`: export files, `refined.safetensors`,
/// `config.json` (`config`), and with ground truth (and `opts.evaluate`) the evaluation and error
/// maps; `meta` is extended with counts, stage timings (the `log`'s) and summaries and written as
/// `meta.json`, once, last. Every file goes through one [`RunOutput`] and is written atomically.
pub fn save_run(
    run: RefinedRun,
    scene: &Scene,
    opts: &RunOptions,
    out: &Path,
    config: &serde_json::Value,
    meta: serde_json::Value,
    log: &mut StageLog,
) -> Result<RunReport> {
    let output = RunOutput::create(out)?;
    save_into(output, run, scene, opts, config, meta, log)
}

/// [`save_run`] into an open output folder.
fn save_into(
    mut output: RunOutput,
    run: RefinedRun,
    scene: &Scene,
    opts: &RunOptions,
    config: &serde_json::Value,
    meta: serde_json::Value,
    log: &mut StageLog,
) -> Result<RunReport> {
    let RefinedRun {
        refined,
        sfm,
        sfm_summary,
        network: stats,
        chunking: _,
    } = run;
    let out = output.dir().to_path_buf();
    log.start("export");
    let mut export_opts = opts.export.clone();
    if let Some(c) = export_opts.colmap.as_mut() {
        let k = &sfm.cameras.intrinsics;
        c.shared_camera = k.windows(2).all(|w| w[0] == w[1]);
        // the BA's camera model, except for the original images of a splat-ready export: their
        // cameras are scaled per axis (PINHOLE, docs/images-to-splats.md)
        if let Some(s) = &sfm_summary
            && export_opts.image_sizes.is_none()
        {
            c.simple_pinhole |= s.camera_model == CameraModel::SimplePinhole;
        }
    }
    let summary = output.export(scene, &sfm, &refined, &export_opts)?;
    output.write_config(config)?;
    output.write_refined(&refined, &sfm)?;
    log.finish();

    let mut evaluation = None;
    if opts.evaluate && scene.gt.is_some() {
        log.start("evaluation");
        let detail = evaluate_refinement(scene, &sfm, &refined.points, opts.refine.seed)?;
        output.write_evaluation(&detail.summary)?;
        if opts.error_maps {
            let maps = render_error_maps(
                scene.dims,
                &scene.images,
                ErrorMapInputs {
                    ff: &detail.ff,
                    sfm: detail.sfm.as_ref(),
                    refined: &detail.refined,
                },
                opts.error_map_max_cm,
            )?;
            output.write_error_maps(&maps)?;
        }
        log.finish();
        evaluation = Some(detail.summary);
    }

    let stages = log.stages().to_vec();
    let mut meta = meta;
    if let serde_json::Value::Object(m) = &mut meta {
        let v = |x: serde_json::Result<serde_json::Value>| x.unwrap_or(serde_json::Value::Null);
        m.insert("scene".into(), scene.name.clone().into());
        m.insert("counts".into(), refined.summary_json());
        m.insert("network".into(), v(serde_json::to_value(&stats)));
        m.insert("stages".into(), v(serde_json::to_value(&stages)));
        m.insert("sfm_ran".into(), sfm_summary.is_some().into());
        m.insert("sfm".into(), v(serde_json::to_value(&sfm_summary)));
        m.insert("export".into(), v(serde_json::to_value(&summary)));
        m.insert("files".into(), v(serde_json::to_value(output.files())));
        if let Some(e) = &evaluation {
            let auc = |p: &ggpt_core::metrics::PointMetrics| serde_json::json!({"auc_1": p.auc_1, "auc_3": p.auc_3, "auc_5": p.auc_5, "auc_10": p.auc_10});
            m.insert("evaluation".into(), serde_json::json!({"ff": auc(&e.ff), "refined": auc(&e.refined), "sfm": e.sfm.as_ref().map(auc)}));
        }
    }
    output.finish(&meta)?;
    Ok(RunReport {
        out_dir: out,
        refined,
        sfm,
        sfm_summary,
        export: summary,
        evaluation,
        network: stats,
        stages,
    })
}
