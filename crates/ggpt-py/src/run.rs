//! `run_sfm`, `refine` and their results. The GIL is released while the SfM and the network
//! run; progress reports and the stop checks (Ctrl-C, an exception raised by the progress
//! callback) take it back briefly between SfM steps, BA iterations and network forwards.

use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use ggpt_core::chunking::ChunkingSettings;
use ggpt_core::{Cancel, Progress, Scene};
use ggpt_infer::pipeline::{RefinedRun, RunOptions, save_run};
use ggpt_infer::rss::StageLog;
use ggpt_scene::driver::{DEFAULT_MAX_TOKENS_PER_FORWARD, DEFAULT_SEED, RefineOptions};
use ggpt_scene::export::{ColmapExportOptions, ExportOptions};
use ggpt_scene::fusion::FusionMode;
use ggpt_sfm::masks::Preset;
use ggpt_sfm::pipeline::{SfmConfig, run_sfm_with_progress};
use pyo3::prelude::*;

use crate::arrays::{array, extrinsics, intrinsics, json_value};
use crate::data::{PyFeedForward, PyMatches, PyScene, PySfmResult};
use crate::errors::{core_error, infer_error, invalid, sfm_error};
use crate::model::PyModel;

/// The stop request and progress callback of one call.
struct Control {
    cancel: Cancel,
    /// The first exception seen (Ctrl-C's `KeyboardInterrupt`, or one the callback raised).
    error: Arc<Mutex<Option<PyErr>>>,
    callback: Option<Py<PyAny>>,
}

impl Control {
    fn new(callback: Option<Py<PyAny>>) -> Self {
        let error: Arc<Mutex<Option<PyErr>>> = Arc::default();
        let seen = error.clone();
        // Python runs its signal handlers only when asked: ask at every stop check.
        let cancel = Cancel::new().with_poll(move || {
            Python::attach(|py| match py.check_signals() {
                Ok(()) => false,
                Err(e) => {
                    keep_first(&seen, e);
                    true
                }
            })
        });
        Control {
            cancel,
            error,
            callback,
        }
    }

    /// The progress callback for the library: `callback(stage, done, total, detail)`; an
    /// exception it raises stops the run at its next check and is re-raised by the call.
    fn progress(&self) -> impl FnMut(Progress) + Send + use<> {
        let callback = Python::attach(|py| self.callback.as_ref().map(|c| c.clone_ref(py)));
        let (error, cancel) = (self.error.clone(), self.cancel.clone());
        move |p: Progress| {
            let Some(cb) = &callback else { return };
            Python::attach(|py| {
                if let Err(e) = cb.call1(py, (p.stage, p.done, p.total, p.detail)) {
                    keep_first(&error, e);
                    cancel.cancel();
                }
            });
        }
    }

    /// The call's outcome: the exception seen first wins over the library's `Cancelled`.
    fn finish<T>(self, result: PyResult<T>) -> PyResult<T> {
        let seen = self.error.lock().ok().and_then(|mut e| e.take());
        match (seen, result) {
            (Some(e), _) => Err(e),
            (None, r) => r,
        }
    }
}

fn keep_first(slot: &Mutex<Option<PyErr>>, e: PyErr) {
    if let Ok(mut s) = slot.lock()
        && s.is_none()
    {
        *s = Some(e);
    }
}

/// Builds the scene of a call: a `Scene` (its parts replaced by the ones given), or a
/// feed-forward prediction with matches and/or an SfM result.
fn build_scene(
    scene: Option<&PyScene>,
    ff: Option<&PyFeedForward>,
    matches: Option<Vec<PyRef<'_, PyMatches>>>,
    sfm: Option<&PySfmResult>,
    name: Option<String>,
) -> PyResult<Scene> {
    let mut s = match (scene, ff) {
        (Some(sc), _) => sc.scene.clone(),
        (None, Some(f)) => Scene {
            name: "scene".into(),
            dims: f.input.dims,
            images: f.images_or_grey(),
            gt: None,
            ff: None,
            sfm: None,
            matches: Vec::new(),
        },
        (None, None) => return Err(invalid("give a feed-forward prediction (ff) or a scene")),
    };
    if let Some(f) = ff {
        if f.input.dims != s.dims && scene.is_some() {
            return Err(invalid(format!(
                "ff has N={} at {}x{}, the scene N={} at {}x{}",
                f.input.dims.n, f.input.dims.h, f.input.dims.w, s.dims.n, s.dims.h, s.dims.w
            )));
        }
        s.ff = Some(f.input.ff.clone());
        if let Some(img) = &f.input.images {
            s.images = img.clone();
        }
    }
    if let Some(m) = matches {
        s.matches = m
            .iter()
            .enumerate()
            .map(|(i, m)| m.to_match_set(s.dims, i))
            .collect::<PyResult<_>>()?;
    }
    if let Some(r) = sfm {
        if r.dims != s.dims {
            return Err(invalid(
                "the SfM result is for another resolution or view count",
            ));
        }
        s.sfm = Some(r.result.clone());
    }
    if let Some(n) = name {
        s.name = n;
    }
    s.validate().map_err(core_error)?;
    if s.ff.is_none() {
        return Err(invalid("the scene has no feed-forward prediction"));
    }
    if s.sfm.is_none() && s.matches.is_empty() {
        return Err(invalid(
            "neither matches nor an SfM result: give matches=[Matches(...)] (the SfM stage runs on them) or sfm=",
        ));
    }
    Ok(s)
}

/// Runs the SfM stage (`ggpt-sfm run`): matches -> bundle-adjusted cameras and DLT points.
#[pyfunction]
#[pyo3(signature = (ff, matches, *, preset = "demo", seed = 42, progress = None))]
pub fn run_sfm(
    py: Python<'_>,
    ff: PyRef<'_, PyFeedForward>,
    matches: Vec<PyRef<'_, PyMatches>>,
    preset: &str,
    seed: u64,
    progress: Option<Py<PyAny>>,
) -> PyResult<PySfmResult> {
    if matches.is_empty() {
        return Err(invalid("matches: give at least one Matches"));
    }
    let dims = ff.input.dims;
    let sets = matches
        .iter()
        .enumerate()
        .map(|(i, m)| m.to_match_set(dims, i))
        .collect::<PyResult<Vec<_>>>()?;
    let mut cfg = SfmConfig::preset(Preset::parse(preset).map_err(sfm_error)?);
    cfg.seed = seed;
    let control = Control::new(progress);
    cfg.cancel = control.cancel.clone();
    let mut report = control.progress();
    let images = ff.images_or_grey();
    let feed = ff.input.ff.clone();
    let out = py.detach(|| run_sfm_with_progress(&feed, &images, dims, &sets, &cfg, &mut report));
    let out = control.finish(out.map_err(sfm_error))?;
    Ok(PySfmResult {
        dims,
        summary: serde_json::to_value(&out.summary).ok(),
        result: out.result,
    })
}

/// The options of a refinement, as `ggpt-infer run` builds them from its flags.
#[allow(clippy::too_many_arguments)]
fn run_options(
    seed: Option<u64>,
    fusion: &str,
    chunking: ChunkingSettings,
    max_tokens_per_forward: Option<usize>,
    sfm_preset: &str,
    allow_unrefined: bool,
    cancel: Cancel,
) -> PyResult<RunOptions> {
    let fusion = match fusion {
        "mean" => FusionMode::Mean,
        "confidence" => FusionMode::ConfidenceWeighted,
        other => {
            return Err(invalid(format!(
                "fusion {other:?}: expected mean or confidence"
            )));
        }
    };
    chunking.validate(|f| f.to_string()).map_err(invalid)?;
    let max_tokens = max_tokens_per_forward.unwrap_or(DEFAULT_MAX_TOKENS_PER_FORWARD);
    if max_tokens == 0 {
        return Err(invalid("max_tokens_per_forward must be positive"));
    }
    let seed_value = seed.unwrap_or(DEFAULT_SEED);
    Ok(RunOptions {
        refine: RefineOptions {
            seed: seed_value,
            chunk_seed: seed,
            max_tokens_per_forward: max_tokens,
            fusion,
            allow_unrefined,
            cancel,
            ..RefineOptions::default()
        },
        chunking,
        export: ExportOptions {
            seed: seed_value,
            ..ExportOptions::default()
        },
        sfm_preset: Preset::parse(sfm_preset).map_err(sfm_error)?,
        ..RunOptions::default()
    })
}

/// Refines a scene with `model` (see `ggpt_rs.refine`).
#[pyfunction]
#[pyo3(signature = (model, ff = None, matches = None, *, scene = None, sfm = None, name = None, seed = None, fusion = "mean", chunk_size = None, max_chunk_pixels = None, min_chunk_dlt = None, min_chunk_pixels = None, max_tokens_per_forward = None, sfm_preset = "demo", allow_unrefined = false, progress = None))]
#[allow(clippy::too_many_arguments)]
pub fn refine(
    py: Python<'_>,
    model: PyRef<'_, PyModel>,
    ff: Option<PyRef<'_, PyFeedForward>>,
    matches: Option<Vec<PyRef<'_, PyMatches>>>,
    scene: Option<PyRef<'_, PyScene>>,
    sfm: Option<PyRef<'_, PySfmResult>>,
    name: Option<String>,
    seed: Option<u64>,
    fusion: &str,
    chunk_size: Option<f64>,
    max_chunk_pixels: Option<usize>,
    min_chunk_dlt: Option<usize>,
    min_chunk_pixels: Option<usize>,
    max_tokens_per_forward: Option<usize>,
    sfm_preset: &str,
    allow_unrefined: bool,
    progress: Option<Py<PyAny>>,
) -> PyResult<PyRefinedScene> {
    let mut scene = build_scene(
        scene.as_deref(),
        ff.as_deref(),
        matches,
        sfm.as_deref(),
        name,
    )?;
    let control = Control::new(progress);
    let opts = run_options(
        seed,
        fusion,
        ChunkingSettings {
            chunk_size,
            max_pixels: max_chunk_pixels,
            min_dlt: min_chunk_dlt,
            min_pixels: min_chunk_pixels,
        },
        max_tokens_per_forward,
        sfm_preset,
        allow_unrefined,
        control.cancel.clone(),
    )?;
    let mut report = control.progress();
    let model_ref: &PyModel = &model;
    let done = py.detach(|| {
        model_ref.with(|r| {
            let mut log = StageLog::new();
            let run = r.refine(&mut scene, &opts, &mut log, &mut report)?;
            let config = r.run_config("python", serde_json::json!(scene.name), &opts, &run);
            let meta = r.run_meta(&opts);
            Ok::<_, ggpt_infer::InferError>((run, config, meta, log))
        })
    })?;
    let (run, config, meta, log) = control.finish(done.map_err(infer_error))?;
    Ok(PyRefinedScene {
        inner: Arc::new(Refined {
            scene,
            run,
            opts,
            config,
            meta,
            log: Mutex::new(log),
        }),
    })
}

/// What a refinement keeps for its getters and `save`.
struct Refined {
    scene: Scene,
    run: RefinedRun,
    opts: RunOptions,
    config: serde_json::Value,
    meta: serde_json::Value,
    log: Mutex<StageLog>,
}

/// A refined scene (SfM frame): points, confidence, coverage, cameras; `save` writes the files
/// of `ggpt-infer run`.
#[pyclass(module = "ggpt_rs._ggpt_rs", name = "RefinedScene", frozen)]
pub struct PyRefinedScene {
    inner: Arc<Refined>,
}

#[pymethods]
impl PyRefinedScene {
    /// `[N, h, w, 3]` float32 refined points (SfM frame; the aligned feed-forward point where no
    /// chunk reached the pixel).
    #[getter]
    fn points<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let d = self.inner.run.refined.dims;
        array(
            py,
            self.inner.run.refined.points.clone(),
            &[d.n, d.h, d.w, 3],
        )
    }

    /// `[N, h, w]` float32 refined confidence (0 where no chunk reached the pixel).
    #[getter]
    fn confidence<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let d = self.inner.run.refined.dims;
        array(py, self.inner.run.refined.conf.clone(), &[d.n, d.h, d.w])
    }

    /// `[N, h, w]` bool: at least one chunk reached the pixel.
    #[getter]
    fn covered<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let d = self.inner.run.refined.dims;
        array(py, self.inner.run.refined.covered.clone(), &[d.n, d.h, d.w])
    }

    /// `[N, h, w, 3]` float32 feed-forward points after the Sim(3) pre-alignment (SfM frame).
    #[getter]
    fn aligned_ff_points<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let d = self.inner.run.refined.dims;
        array(
            py,
            self.inner.run.refined.aligned_ff.clone(),
            &[d.n, d.h, d.w, 3],
        )
    }

    /// `[N, 3, 4]` float64 `cam_from_world` of the SfM stage (SfM frame).
    #[getter]
    fn cam_from_world<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        extrinsics(py, &self.inner.run.sfm.cameras.cam_from_world)
    }

    /// `[N, 3, 3]` float64 intrinsics of the SfM stage (ff pixels).
    #[getter]
    #[allow(non_snake_case)]
    fn K<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        intrinsics(py, &self.inner.run.sfm.cameras.intrinsics)
    }

    /// The SfM result used (computed here, or given).
    #[getter]
    fn sfm(&self) -> PySfmResult {
        PySfmResult {
            dims: self.inner.run.refined.dims,
            result: self.inner.run.sfm.clone(),
            summary: self
                .inner
                .run
                .sfm_summary
                .as_ref()
                .and_then(|s| serde_json::to_value(s).ok()),
        }
    }

    /// Counts and settings (chunks, tokens, coverage, alignment, network time, the chunk
    /// sampler's settings and their origin) as a dict.
    #[getter]
    fn stats<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let r = &self.inner.run;
        let stages = self
            .inner
            .log
            .lock()
            .map(|l| l.stages().to_vec())
            .unwrap_or_default();
        let v = serde_json::json!({
            "counts": r.refined.summary_json(),
            "network": r.network,
            "chunking": r.chunking,
            "stages": stages,
        });
        json_value(py, &v)
    }

    /// Writes the files of `ggpt-infer run --out DIR` (refined points as safetensors / npy /
    /// PLY, COLMAP `sparse/0`, `images/` and nerfstudio's `transforms.json`, `config.json`,
    /// `meta.json`; with ground truth also `evaluation.json` and error maps), each atomically;
    /// the options are `ggpt-infer run`'s export flags with the same defaults (`images`: the
    /// folder of original images, as `--images DIR`). Returns the folder.
    #[pyo3(signature = (out, *, conf_quantile = ggpt_scene::export::DEFAULT_CONF_QUANTILE, max_points = ggpt_scene::export::DEFAULT_MAX_POINTS, colmap = true, colmap_text = false, colmap_points = true, colmap_max_points = ggpt_scene::export::DEFAULT_COLMAP_MAX_POINTS, colmap_resolution = None, colmap_simple_pinhole = false, voxel_size = None, splat = true, images = None, error_maps = true, error_map_max_cm = ggpt_eval::error_maps::DEFAULT_ERROR_MAP_MAX_CM))]
    #[allow(clippy::too_many_arguments)]
    fn save(
        &self,
        py: Python<'_>,
        out: PathBuf,
        conf_quantile: f64,
        max_points: usize,
        colmap: bool,
        colmap_text: bool,
        colmap_points: bool,
        colmap_max_points: usize,
        colmap_resolution: Option<(usize, usize)>,
        colmap_simple_pinhole: bool,
        voxel_size: Option<f64>,
        splat: bool,
        images: Option<PathBuf>,
        error_maps: bool,
        error_map_max_cm: f64,
    ) -> PyResult<PathBuf> {
        if !(0.0..=1.0).contains(&conf_quantile) {
            return Err(invalid(format!(
                "conf_quantile {conf_quantile} must be in [0, 1]"
            )));
        }
        if matches!(colmap_resolution, Some((w, h)) if w == 0 || h == 0) {
            return Err(invalid(
                "colmap_resolution: (width, height) must be positive",
            ));
        }
        let inner = self.inner.clone();
        let mut opts = inner.opts.clone();
        opts.export.conf_quantile = conf_quantile;
        opts.export.max_points = max_points;
        opts.export.colmap = colmap.then(|| ColmapExportOptions {
            text: colmap_text,
            points: colmap_points,
            max_points: colmap_max_points,
            resolution: colmap_resolution.map(|(w, h)| (h, w)),
            simple_pinhole: colmap_simple_pinhole,
            ..ColmapExportOptions::default()
        });
        opts.export.voxel_size = voxel_size;
        opts.export.splat = splat;
        if let Some(dir) = &images {
            let o = ggpt_infer::inputs::original_images(dir, Some(inner.run.refined.dims.n))
                .map_err(infer_error)?;
            opts.export.image_sizes = Some(o.sizes);
            opts.export.image_files = Some(o.files);
        }
        opts.error_maps = error_maps;
        opts.error_map_max_cm = error_map_max_cm;
        let mut config = inner.config.clone();
        config["export"] = serde_json::to_value(&opts.export).unwrap_or_default();
        config["error_maps"] = error_maps.into();
        config["error_map_max_cm"] = error_map_max_cm.into();
        let report = py.detach(|| {
            let mut log = inner.log.lock().map(|l| l.clone()).unwrap_or_default();
            save_run(
                inner.run.clone(),
                &inner.scene,
                &opts,
                &out,
                &config,
                inner.meta.clone(),
                &mut log,
            )
        });
        Ok(report.map_err(infer_error)?.out_dir)
    }

    /// Accuracy against ground truth (`gt`: a `Scene` with ground truth; default: the refined
    /// scene's own) as a dict: feed-forward, SfM and refined AUC@1/3/5/10 cm after a robust
    /// Sim(3) to the GT frame, as `evaluation.json`.
    #[pyo3(signature = (gt = None))]
    fn evaluate<'py>(
        &self,
        py: Python<'py>,
        gt: Option<PyRef<'py, PyScene>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let mut scene = self.inner.scene.clone();
        if let Some(g) = &gt {
            if g.scene.dims != scene.dims {
                return Err(invalid(
                    "gt: the scene has another resolution or view count",
                ));
            }
            scene.gt = g.scene.gt.clone();
        }
        if scene.gt.is_none() {
            return Err(invalid(
                "no ground truth: pass gt=read_scene(...) of a scene with gt",
            ));
        }
        let run = &self.inner.run;
        let seed = self.inner.opts.refine.seed;
        let detail = py
            .detach(|| {
                ggpt_eval::refinement::evaluate_refinement(
                    &scene,
                    &run.sfm,
                    &run.refined.points,
                    seed,
                )
            })
            .map_err(|e| crate::errors::infer_error(e.into()))?;
        json_value(
            py,
            &serde_json::to_value(&detail.summary).unwrap_or_default(),
        )
    }

    fn __repr__(&self) -> String {
        let r = &self.inner.run.refined;
        format!(
            "RefinedScene(views={}, height={}, width={}, chunks={}, covered={:.1}%)",
            r.dims.n,
            r.dims.h,
            r.dims.w,
            r.chunks.len(),
            100.0 * r.covered.iter().filter(|&&c| c).count() as f64 / r.covered.len().max(1) as f64
        )
    }
}
