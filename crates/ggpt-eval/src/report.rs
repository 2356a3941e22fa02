//! One prediction of a scene against its ground truth: picks the prediction and cameras to
//! evaluate, runs the `pipeline.md` §10 metrics and assembles the JSON report (`ggpt-eval`).

use std::path::{Path, PathBuf};

use ggpt_core::io::npy::read_npy;
use ggpt_core::io::st::{Dtype, StFile, le_f32, le_f64};
use ggpt_core::metrics::{
    CameraMetrics, DepthMetrics, EVAL_ALIGN_MAX_ERROR, PointMetrics, camera_metrics, depth_metrics,
    point_metrics,
};
use ggpt_core::{Cameras, Dims, Scene, SfmResult};
use rand::SeedableRng;
use rand_pcg::Pcg64;

use crate::error::{EvalError, Result, invalid};

/// Which point map to evaluate.
#[derive(Debug, Clone, PartialEq)]
pub enum PredSource {
    /// The scene's feed-forward points (unaligned; "init" baseline).
    Ff,
    /// The scene's SfM (DLT) points, evaluated on `M_s ∧ V` with the ratio.
    Sfm,
    /// The GT points themselves (sanity check: 100 everywhere).
    Gt,
    /// A `.npy` file with `[N, h, w, 3]` (or `[N*h*w, 3]`) points.
    Npy(PathBuf),
    /// A `.safetensors` file and an optional tensor key.
    SafeTensors(PathBuf, Option<String>),
}

impl PredSource {
    /// Parses `ff|sfm|gt|FILE.npy|FILE.safetensors[:key]`.
    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "ff" => return Ok(PredSource::Ff),
            "sfm" => return Ok(PredSource::Sfm),
            "gt" => return Ok(PredSource::Gt),
            _ => {}
        }
        if s.ends_with(".npy") {
            return Ok(PredSource::Npy(PathBuf::from(s)));
        }
        if let Some(i) = s.find(".safetensors") {
            let (path, rest) = s.split_at(i + ".safetensors".len());
            let key = match rest.strip_prefix(':') {
                Some(k) if !k.is_empty() => Some(k.to_string()),
                Some(_) => invalid!("--pred {s}: empty tensor key after ':'"),
                None if rest.is_empty() => None,
                None => invalid!("--pred {s}: expected FILE.safetensors or FILE.safetensors:KEY"),
            };
            return Ok(PredSource::SafeTensors(PathBuf::from(path), key));
        }
        invalid!("--pred {s}: expected ff, sfm, gt, FILE.npy or FILE.safetensors[:KEY]")
    }

    /// Short label for tables and the report.
    pub fn label(&self) -> String {
        match self {
            PredSource::Ff => "ff".into(),
            PredSource::Sfm => "sfm".into(),
            PredSource::Gt => "gt".into(),
            PredSource::Npy(p) => p.display().to_string(),
            PredSource::SafeTensors(p, k) => match k {
                Some(k) => format!("{}:{k}", p.display()),
                None => p.display().to_string(),
            },
        }
    }
}

/// Which cameras to evaluate.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum CameraSource {
    /// `ff`/`sfm`/`gt` as `--pred` when it names one, else `ff` when present.
    Auto,
    /// Feed-forward cameras.
    Ff,
    /// Bundle-adjusted SfM cameras.
    Sfm,
    /// GT cameras (sanity check).
    Gt,
    /// No camera evaluation.
    None,
}

/// The JSON report of one evaluation.
#[derive(Debug, Clone, serde::Serialize)]
pub struct EvalReport {
    /// Crate version that produced the report.
    pub ggpt_eval_version: String,
    /// Scene name.
    pub scene: String,
    /// Feed-forward resolution.
    pub dims: Dims,
    /// Seed of the RANSAC generator.
    pub seed: u64,
    /// Evaluated prediction (`ff`, `sfm`, `gt` or a file).
    pub prediction: String,
    /// Point accuracy (`pipeline.md` §10.2).
    pub points: PointMetrics,
    /// Depth accuracy after the same alignment (`pipeline.md` §10.4); absent without GT depth.
    pub depth: Option<DepthMetrics>,
    /// Camera source evaluated (absent when none).
    pub camera_source: Option<String>,
    /// Camera accuracy (`pipeline.md` §10.3).
    pub cameras: Option<CameraMetrics>,
    /// Non-fatal problems (e.g. camera evaluation impossible).
    pub warnings: Vec<String>,
}

/// Loads `[N, h, w, 3]` predicted points for `source` (validated size and finiteness over all pixels).
pub fn load_prediction(scene: &Scene, source: &PredSource) -> Result<Vec<f32>> {
    let want = 3 * scene.dims.pixels();
    let pts = match source {
        PredSource::Ff => scene.ff.as_ref().map(|f| f.points.clone()).ok_or_else(|| {
            EvalError::Invalid(format!("scene {} has no feed-forward points", scene.name))
        })?,
        PredSource::Sfm => scene
            .sfm
            .as_ref()
            .map(|s| s.points.clone())
            .ok_or_else(|| EvalError::Invalid(format!("scene {} has no SfM result", scene.name)))?,
        PredSource::Gt => scene.gt.as_ref().map(|g| g.points.clone()).ok_or_else(|| {
            EvalError::Invalid(format!("scene {} has no ground truth", scene.name))
        })?,
        PredSource::Npy(path) => {
            let a = read_npy(path).map_err(|source| EvalError::Input {
                what: format!("reading prediction {}", path.display()),
                source,
            })?;
            check_shape(path, "", &a.shape, scene.dims)?;
            a.to_f32().ok_or_else(|| {
                EvalError::Invalid(format!(
                    "{}: dtype {} is not float32/float64",
                    path.display(),
                    a.data.descr()
                ))
            })?
        }
        PredSource::SafeTensors(path, key) => load_safetensors(path, key.as_deref(), scene.dims)?,
    };
    if pts.len() != want {
        invalid!(
            "prediction {}: {} values, expected {want} ({:?} x 3)",
            source.label(),
            pts.len(),
            scene.dims
        );
    }
    if let Some(i) = pts.iter().position(|v| !v.is_finite()) {
        invalid!(
            "prediction {}: non-finite value at flat index {i} (pixel {})",
            source.label(),
            i / 3
        );
    }
    Ok(pts)
}

fn check_shape(path: &Path, key: &str, shape: &[usize], d: Dims) -> Result<()> {
    let ok = shape == [d.n, d.h, d.w, 3] || shape == [d.pixels(), 3];
    if !ok {
        invalid!(
            "{}{}: shape {shape:?}, expected [{}, {}, {}, 3] or [{}, 3] for this scene",
            path.display(),
            if key.is_empty() {
                String::new()
            } else {
                format!(" [{key}]")
            },
            d.n,
            d.h,
            d.w,
            d.pixels()
        );
    }
    Ok(())
}

/// Keys tried in order when a safetensors prediction is given without a key.
const DEFAULT_ST_KEYS: [&str; 3] = ["points", "pred_points", "world_points"];

fn load_safetensors(path: &Path, key: Option<&str>, dims: Dims) -> Result<Vec<f32>> {
    let st = StFile::open(path).map_err(|source| EvalError::Input {
        what: format!("reading prediction {}", path.display()),
        source,
    })?;
    let key = match key {
        Some(k) => k.to_string(),
        None => {
            let keys = st.keys();
            if keys.len() == 1 {
                keys.into_iter().next().unwrap_or_default()
            } else if let Some(k) = DEFAULT_ST_KEYS.iter().find(|k| st.has(k)) {
                (*k).to_string()
            } else {
                invalid!(
                    "{}: several tensors {keys:?}; name one with FILE.safetensors:KEY",
                    path.display()
                );
            }
        }
    };
    let (dtype, shape, bytes) = st.tensor(&key)?;
    check_shape(path, &key, shape, dims)?;
    match dtype {
        Dtype::F32 => Ok(le_f32(bytes)),
        Dtype::F64 => Ok(le_f64(bytes).into_iter().map(|v| v as f32).collect()),
        d => invalid!("{} [{key}]: dtype {d:?} is not F32/F64", path.display()),
    }
}

fn cameras_of(scene: &Scene, source: CameraSource) -> Option<(&'static str, &Cameras)> {
    match source {
        CameraSource::Ff => scene.ff.as_ref().map(|f| ("ff", &f.cameras)),
        CameraSource::Sfm => scene.sfm.as_ref().map(|s| ("sfm", &s.cameras)),
        CameraSource::Gt => scene.gt.as_ref().map(|g| ("gt", &g.cameras)),
        CameraSource::Auto | CameraSource::None => None,
    }
}

/// Resolves `auto` against the prediction.
pub fn resolve_cameras(pred: &PredSource, cams: CameraSource, scene: &Scene) -> CameraSource {
    match cams {
        CameraSource::Auto => match pred {
            PredSource::Sfm => CameraSource::Sfm,
            PredSource::Gt => CameraSource::Gt,
            _ if scene.ff.is_some() => CameraSource::Ff,
            _ => CameraSource::None,
        },
        c => c,
    }
}

/// Evaluates `pred` (and the cameras `cams`) of `scene` against its ground truth with the
/// RANSAC generator seeded by `seed`.
pub fn evaluate_scene(
    scene: &Scene,
    pred: &PredSource,
    cams: CameraSource,
    seed: u64,
) -> Result<EvalReport> {
    let gt = scene.gt.as_ref().ok_or_else(|| {
        EvalError::Invalid(format!(
            "scene {} has no ground truth to evaluate against",
            scene.name
        ))
    })?;
    let points = load_prediction(scene, pred)?;
    let subset = match pred {
        PredSource::Sfm => scene.sfm.as_ref().map(|s| s.mask.as_slice()),
        _ => None,
    };
    let mut rng = Pcg64::seed_from_u64(seed);
    let ev = point_metrics(
        &points,
        &gt.points,
        &gt.mask,
        subset,
        EVAL_ALIGN_MAX_ERROR,
        &mut rng,
    )
    .map_err(|source| EvalError::Metric {
        what: format!("point accuracy of {}", pred.label()),
        source,
    })?;
    let mut warnings = Vec::new();
    let depth = match depth_metrics(
        &points,
        &ev.sim3,
        &gt.cameras,
        &gt.points,
        gt.depth.as_deref(),
        &ev.mask,
    ) {
        Ok(d) => Some(d),
        Err(e) => {
            warnings.push(format!("depth metrics skipped: {e}"));
            None
        }
    };
    let cam_source = resolve_cameras(pred, cams, scene);
    let (camera_source, cameras) = if cam_source == CameraSource::None {
        (None, None)
    } else {
        match cameras_of(scene, cam_source) {
            None => {
                warnings.push(format!(
                    "camera evaluation skipped: scene has no {cam_source:?} cameras"
                ));
                (None, None)
            }
            Some((name, c)) => match camera_metrics(c, &gt.cameras) {
                Ok(m) => (Some(name.to_string()), Some(m)),
                Err(e) => {
                    warnings.push(format!("camera evaluation skipped: {e}"));
                    (None, None)
                }
            },
        }
    };
    for w in &warnings {
        tracing::warn!("{w}");
    }
    Ok(EvalReport {
        ggpt_eval_version: env!("CARGO_PKG_VERSION").to_string(),
        scene: scene.name.clone(),
        dims: scene.dims,
        seed,
        prediction: pred.label(),
        points: ev.metrics,
        depth,
        camera_source,
        cameras,
        warnings,
    })
}

/// File name of the `ggpt-sfm run` output looked up inside a directory given to [`load_sfm_outputs`].
pub const SFM_OUTPUT_FILE: &str = "sfm_dlt_outputs.safetensors";

/// Reads an SfM result to evaluate in place of the scene's own (`ggpt-eval --sfm PATH`):
/// the `sfm_dlt_outputs.safetensors` written by `ggpt-sfm run` (keys `points` F32 `[N,h,w,3]` in
/// the SfM frame, `point_masks` BOOL `[N,h,w]`, `extrinsics` F32 `[N,3,4]` or `[N,4,4]`
/// `cam_from_world`, `intrinsics` F32 `[N,3,3]` in ff pixels, optional 0-d BOOL
/// `camera_success` / `points_success`), a directory holding that file (e.g. the `--out` of
/// `ggpt-sfm run`), or an official `sfm_dlt_outputs.bin`. The size must match `dims`.
pub fn load_sfm_outputs(path: &Path, dims: Dims) -> Result<SfmResult> {
    let file = if path.is_dir() {
        let st = path.join(SFM_OUTPUT_FILE);
        let bin = path.join("sfm_dlt_outputs.bin");
        if st.is_file() {
            st
        } else if bin.is_file() {
            bin
        } else {
            invalid!(
                "{}: directory holds neither {SFM_OUTPUT_FILE} nor sfm_dlt_outputs.bin",
                path.display()
            );
        }
    } else {
        path.to_path_buf()
    };
    let (n, h, w) = (dims.n, dims.h, dims.w);
    let res = if file.extension().is_some_and(|e| e == "bin") {
        let b = ggpt_core::io::official::read_sfm_dlt_outputs_bin(&file).map_err(|source| {
            EvalError::Input {
                what: format!("reading SfM outputs {}", file.display()),
                source,
            }
        })?;
        if b.dims != dims {
            invalid!(
                "{}: SfM outputs are {:?}, the scene is {dims:?}",
                file.display(),
                b.dims
            );
        }
        b.to_sfm_result()
    } else {
        let st = StFile::open(&file).map_err(|source| EvalError::Input {
            what: format!("reading SfM outputs {}", file.display()),
            source,
        })?;
        let points = st.f32_finite("points", &[n, h, w, 3])?;
        let mask = st.bool("point_masks", &[n, h, w])?;
        let rows = match st.shape("extrinsics")? {
            [m, r, 4] if *m == n && (*r == 3 || *r == 4) => *r,
            s => invalid!(
                "{} [extrinsics]: shape {s:?}, expected [{n}, 3, 4] or [{n}, 4, 4]",
                file.display()
            ),
        };
        let ext = camera_floats(&st, "extrinsics", &[n, rows, 4])?;
        let k = camera_floats(&st, "intrinsics", &[n, 3, 3])?;
        let cam_from_world = ext
            .chunks_exact(rows * 4)
            .map(|m| nalgebra::Matrix3x4::from_row_iterator(m.iter().take(12).copied()))
            .collect();
        let intrinsics = k
            .chunks_exact(9)
            .map(|m| nalgebra::Matrix3::from_row_iterator(m.iter().copied()))
            .collect();
        let flag = |key: &str, default: bool| -> Result<bool> {
            if st.has(key) {
                Ok(st.scalar_bool(key)?)
            } else {
                Ok(default)
            }
        };
        let points_success = flag("points_success", mask.iter().any(|&b| b))?;
        SfmResult {
            points,
            mask,
            cameras: Cameras {
                cam_from_world,
                intrinsics,
            },
            camera_success: flag("camera_success", true)?,
            points_success,
        }
    };
    tracing::info!(
        "SfM outputs read from {} (camera_success {}, {} pixels with a point)",
        file.display(),
        res.camera_success,
        res.mask.iter().filter(|&&b| b).count()
    );
    Ok(res)
}

/// A finite F32 or F64 camera tensor of exactly `shape`, as f64.
fn camera_floats(st: &StFile, key: &str, shape: &[usize]) -> Result<Vec<f64>> {
    let v = match st.dtype(key)? {
        Dtype::F64 => st.f64(key, shape)?,
        _ => st.f32(key, shape)?.into_iter().map(f64::from).collect(),
    };
    if let Some(i) = v.iter().position(|x| !x.is_finite()) {
        invalid!(
            "{} [{key}]: non-finite value at flat index {i}",
            st.path().display()
        );
    }
    Ok(v)
}

/// Human-readable table of one or more reports (one row per report).
pub fn format_table(reports: &[EvalReport]) -> String {
    let mut s = String::new();
    s.push_str(&format!(
        "{:<14} {:>8} {:>7} {:>7} {:>7} {:>7} {:>9} {:>9} {:>6} | {:>4} {:>6} {:>6} {:>6} {:>6} {:>6} | {:>7} {:>7} {:>7} {:>7}\n",
        "prediction",
        "points",
        "AUC@1",
        "AUC@3",
        "AUC@5",
        "AUC@10",
        "mean cm",
        "med cm",
        "ratio",
        "cams",
        "cAUC1",
        "cAUC3",
        "cAUC5",
        "cAUC10",
        "FoV°",
        "AbsRel",
        "δ<1.01",
        "δ<1.03",
        "δ<1.25"
    ));
    for r in reports {
        let p = &r.points;
        let ratio = p
            .ratio
            .map_or("-".to_string(), |v| format!("{:.1}%", 100.0 * v));
        let cams = match &r.cameras {
            Some(c) => format!(
                "{:>4} {:>6.1} {:>6.1} {:>6.1} {:>6.1} {:>6.2}",
                r.camera_source.as_deref().unwrap_or("?"),
                c.auc_1,
                c.auc_3,
                c.auc_5,
                c.auc_10,
                c.fov_error_deg
            ),
            None => format!(
                "{:>4} {:>6} {:>6} {:>6} {:>6} {:>6}",
                "-", "-", "-", "-", "-", "-"
            ),
        };
        let depth = match &r.depth {
            Some(d) => format!(
                "{:>7.4} {:>7.1} {:>7.1} {:>7.1}",
                d.abs_rel, d.delta_1_01, d.delta_1_03, d.delta_1_25
            ),
            None => format!("{:>7} {:>7} {:>7} {:>7}", "-", "-", "-", "-"),
        };
        let label = if r.prediction.chars().count() > 14 {
            let tail: String = r
                .prediction
                .chars()
                .rev()
                .take(13)
                .collect::<Vec<_>>()
                .into_iter()
                .rev()
                .collect();
            format!("…{tail}")
        } else {
            r.prediction.clone()
        };
        s.push_str(&format!(
            "{:<14} {:>8} {:>7.2} {:>7.2} {:>7.2} {:>7.2} {:>9.3} {:>9.3} {:>6} | {cams} | {depth}\n",
            label, p.num_points, p.auc_1, p.auc_3, p.auc_5, p.auc_10, p.mean_cm, p.median_cm, ratio
        ));
    }
    s.push_str("point AUC@τ: % of GT pixels within τ cm after robust Sim(3) alignment (pipeline.md §10.2);\n");
    s.push_str("camera AUC@τ: relative-pose error max(rot, trans dir) over view pairs, degrees (§10.3); depth (AbsRel fraction, δ<τ %) in the GT cameras (§10.4).\n");
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_prediction_sources() {
        assert_eq!(PredSource::parse("ff").unwrap(), PredSource::Ff);
        assert_eq!(PredSource::parse("sfm").unwrap(), PredSource::Sfm);
        assert_eq!(PredSource::parse("gt").unwrap(), PredSource::Gt);
        assert_eq!(
            PredSource::parse("a/b.npy").unwrap(),
            PredSource::Npy("a/b.npy".into())
        );
        assert_eq!(
            PredSource::parse("x.safetensors").unwrap(),
            PredSource::SafeTensors("x.safetensors".into(), None)
        );
        assert_eq!(
            PredSource::parse("out/x.safetensors:pts").unwrap(),
            PredSource::SafeTensors("out/x.safetensors".into(), Some("pts".into()))
        );
        assert!(PredSource::parse("x.safetensors:").is_err());
        assert!(PredSource::parse("points.txt").is_err());
    }
}
