//! The data classes: `FeedForward`, `Matches`, `SfmResult` and `Scene` (a scene folder read by
//! `read_scene`). Arrays are copied into Rust once, at construction; getters hand out new
//! numpy arrays (C order).

use std::collections::BTreeMap;

use ggpt_core::io::arrays::NamedArrays;
use ggpt_core::io::feedforward::{
    FeedForwardInput, FfFormat, FfReadOptions, VggtBranch, read_feed_forward,
};
use ggpt_core::{Dims, MatchSet, Scene, SfmResult};
use ggpt_sfm::convert::{PairLayout, RawKind, RawMatches};
use nalgebra::Matrix3;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use crate::arrays::{array, extrinsics, f32_values, intrinsics, json_value, to_npy};
use crate::errors::{core_error, invalid, sfm_error};

/// A feed-forward prediction (VGGT, Pi3, MapAnything, ...): points `[N, h, w, 3]` in the
/// model's world frame, confidence `[N, h, w]`, `cam_from_world` `[N, 3, 4]` (OpenCV axes),
/// K `[N, 3, 3]` in ff pixels (pixel centres at integers), optional images `[N, h, w, 3]`.
#[pyclass(module = "ggpt_rs._ggpt_rs", name = "FeedForward", frozen)]
#[derive(Clone)]
pub struct PyFeedForward {
    pub(crate) input: FeedForwardInput,
}

impl PyFeedForward {
    /// The images, or mid-grey when the prediction has none (only the ranking score of the BA
    /// tracks and the colours of the outputs use them).
    pub(crate) fn images_or_grey(&self) -> Vec<f32> {
        self.input
            .images
            .clone()
            .unwrap_or_else(|| vec![0.5; 3 * self.input.dims.pixels()])
    }
}

/// The arrays of a mapping (a dict, `numpy.load("x.npz")`, ...) as [`NamedArrays`]; `origin`
/// names them in errors. Entries that are not arrays (strings, lists of names) are skipped; numpy
/// arrays, torch tensors and objects with `__array__` are read.
fn named_arrays(arrays: &Bound<'_, PyAny>, origin: &str) -> PyResult<NamedArrays> {
    let mut map = BTreeMap::new();
    let keys = arrays
        .call_method0("keys")
        .map_err(|_| invalid(format!("{origin}: expected a dict (or mapping) of arrays")))?;
    for k in keys.try_iter()? {
        let k = k?;
        let key: String = k.extract()?;
        let v = arrays.get_item(&k)?;
        if v.hasattr("shape")? || v.hasattr("__array__")? || v.hasattr("detach")? {
            map.insert(key.clone(), to_npy(&v, &key)?);
        }
    }
    Ok(NamedArrays::new(origin, map))
}

/// MapAnything's per-view output dicts (each array `[1, ...]`) stacked over the views into one
/// mapping; a mapping is read as it is.
fn stacked_views(outputs: &Bound<'_, PyAny>, origin: &str) -> PyResult<NamedArrays> {
    let Ok(list) = outputs.cast::<PyList>() else {
        return named_arrays(outputs, origin);
    };
    let mut merged: BTreeMap<String, ggpt_core::io::npy::NpyArray> = BTreeMap::new();
    for (v, item) in list.iter().enumerate() {
        let one = named_arrays(&item, &format!("{origin}[{v}]"))?;
        for key in one.keys() {
            let Some(a) = one.array(key) else { continue };
            let mut a = a.clone();
            if a.shape.first() == Some(&1) {
                a.shape.remove(0);
            }
            match merged.get_mut(key) {
                None if v == 0 => {
                    a.shape.insert(0, 1);
                    merged.insert(key.to_string(), a);
                }
                None => {}
                Some(m) => {
                    if m.shape[1..] != a.shape[..] {
                        return Err(invalid(format!(
                            "{origin}[{v}].{key}: shape {:?} differs from view 0's {:?}",
                            a.shape,
                            &m.shape[1..]
                        )));
                    }
                    append(&mut m.data, a.data).map_err(|t| {
                        invalid(format!(
                            "{origin}[{v}].{key}: dtype {t} differs from view 0's"
                        ))
                    })?;
                    m.shape[0] += 1;
                }
            }
        }
    }
    Ok(NamedArrays::new(origin, merged))
}

/// Appends `b` to `a` when both have the same dtype (`Err`: `b`'s descriptor).
fn append(
    a: &mut ggpt_core::io::npy::NpyData,
    b: ggpt_core::io::npy::NpyData,
) -> Result<(), &'static str> {
    use ggpt_core::io::npy::NpyData as D;
    match (a, b) {
        (D::F32(x), D::F32(y)) => x.extend(y),
        (D::F64(x), D::F64(y)) => x.extend(y),
        (D::U8(x), D::U8(y)) => x.extend(y),
        (D::Bool(x), D::Bool(y)) => x.extend(y),
        (D::I32(x), D::I32(y)) => x.extend(y),
        (D::I64(x), D::I64(y)) => x.extend(y),
        (D::U16(x), D::U16(y)) => x.extend(y),
        (_, y) => return Err(y.descr()),
    }
    Ok(())
}

/// Reads `a` in `format` (see [`read_feed_forward`]).
fn read_as(
    a: NamedArrays,
    format: Option<FfFormat>,
    branch: VggtBranch,
    intrinsics: Option<Vec<Matrix3<f64>>>,
) -> PyResult<PyFeedForward> {
    let opts = FfReadOptions {
        format,
        branch,
        intrinsics,
    };
    Ok(PyFeedForward {
        input: read_feed_forward(a, &opts).map_err(core_error)?,
    })
}

/// `[N, 3, 3]` intrinsics from a numpy array.
fn intrinsics_arg(obj: &Bound<'_, PyAny>) -> PyResult<Vec<Matrix3<f64>>> {
    let a = to_npy(obj, "K")?;
    let v = a
        .to_f64()
        .ok_or_else(|| invalid("K: expected float32 or float64"))?;
    match a.shape.as_slice() {
        [_, 3, 3] => Ok(v.chunks_exact(9).map(Matrix3::from_row_slice).collect()),
        [3, 3] => Ok(vec![Matrix3::from_row_slice(&v)]),
        s => Err(invalid(format!("K: shape {s:?}, expected [N, 3, 3]"))),
    }
}

#[pymethods]
impl PyFeedForward {
    /// From arrays: see the class doc. float32 or float64; a leading batch of 1 is removed.
    #[new]
    #[pyo3(signature = (points, conf, cam_from_world, K, images = None))]
    #[allow(non_snake_case)]
    fn new(
        points: &Bound<'_, PyAny>,
        conf: &Bound<'_, PyAny>,
        cam_from_world: &Bound<'_, PyAny>,
        K: &Bound<'_, PyAny>,
        images: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        let mut map = BTreeMap::new();
        map.insert("points".to_string(), to_npy(points, "points")?);
        map.insert("conf".to_string(), to_npy(conf, "conf")?);
        map.insert(
            "cam_from_world".to_string(),
            to_npy(cam_from_world, "cam_from_world")?,
        );
        map.insert("K".to_string(), to_npy(K, "K")?);
        if let Some(i) = images {
            map.insert("images".to_string(), to_npy(i, "images")?);
        }
        let mut a = NamedArrays::new("FeedForward", map);
        a.squeeze_batch(&[
            ("points", 4),
            ("conf", 3),
            ("cam_from_world", 3),
            ("K", 3),
            ("images", 4),
        ])
        .map_err(core_error)?;
        let input = read_feed_forward(
            a,
            &FfReadOptions {
                format: Some(FfFormat::Ggpt),
                ..FfReadOptions::default()
            },
        )
        .map_err(core_error)?;
        Ok(PyFeedForward { input })
    }

    /// Reads a mapping of arrays (a dict, `numpy.load("x.npz")`) in one of the known layouts
    /// (`format`: `vggt`, `mapanything`, `pi3`, `ggpt`, or `None` to detect it from the keys);
    /// `branch` is VGGT's (`depth`, the official demo's default, or `points`); `K` gives Pi3's
    /// intrinsics. The same reader as `ggpt-infer run --ff FILE`.
    #[staticmethod]
    #[pyo3(signature = (arrays, format = None, branch = "depth", K = None, origin = "arrays"))]
    #[allow(non_snake_case)]
    fn from_arrays(
        arrays: &Bound<'_, PyAny>,
        format: Option<&str>,
        branch: &str,
        K: Option<&Bound<'_, PyAny>>,
        origin: &str,
    ) -> PyResult<Self> {
        read_as(
            named_arrays(arrays, origin)?,
            format
                .map(FfFormat::parse)
                .transpose()
                .map_err(core_error)?,
            VggtBranch::parse(branch).map_err(core_error)?,
            K.map(intrinsics_arg).transpose()?,
        )
    }

    /// VGGT's predictions (the dict `model(images)` returns after the demo's
    /// `pose_encoding_to_extri_intri`, or `numpy.load("predictions.npz")`): `extrinsic`
    /// `[S, 3, 4]` camera-from-world (OpenCV), `intrinsic` `[S, 3, 3]`, `depth` `[S, H, W, 1]` +
    /// `depth_conf`, `world_points` `[S, H, W, 3]` + `world_points_conf`, `images`
    /// `[S, 3, H, W]`; a leading batch of 1 is removed. `branch="depth"` (the official demo's
    /// default: depth unprojected with the predicted cameras) or `"points"` (the point head).
    #[staticmethod]
    #[pyo3(signature = (predictions, branch = "depth"))]
    fn from_vggt(predictions: &Bound<'_, PyAny>, branch: &str) -> PyResult<Self> {
        read_as(
            named_arrays(predictions, "VGGT predictions")?,
            Some(FfFormat::Vggt),
            VggtBranch::parse(branch).map_err(core_error)?,
            None,
        )
    }

    /// MapAnything's outputs: the list of per-view dicts `model.infer` returns (`pts3d`
    /// `[1, H, W, 3]`, `conf`, `intrinsics`, `camera_poses` camera-to-world `[1, 4, 4]`,
    /// `img_no_norm`), or one mapping of arrays stacked over the views.
    #[staticmethod]
    fn from_mapanything(outputs: &Bound<'_, PyAny>) -> PyResult<Self> {
        read_as(
            stacked_views(outputs, "MapAnything outputs")?,
            Some(FfFormat::MapAnything),
            VggtBranch::Depth,
            None,
        )
    }

    /// Pi3's outputs (`points` `[N, H, W, 3]` world frame, `conf` logits, `camera_poses`
    /// camera-to-world, optional `local_points`, `images`; leading batch of 1 removed). `K`:
    /// intrinsics `[N, 3, 3]` in ff pixels; `None` estimates one focal per view by least
    /// squares on the camera-frame points, principal point at `(w/2, h/2)`.
    #[staticmethod]
    #[pyo3(signature = (outputs, K = None))]
    #[allow(non_snake_case)]
    fn from_pi3(outputs: &Bound<'_, PyAny>, K: Option<&Bound<'_, PyAny>>) -> PyResult<Self> {
        read_as(
            named_arrays(outputs, "Pi3 outputs")?,
            Some(FfFormat::Pi3),
            VggtBranch::Depth,
            K.map(intrinsics_arg).transpose()?,
        )
    }

    /// `[N, h, w, 3]` float32 points (model frame).
    #[getter]
    fn points<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let d = self.input.dims;
        array(py, self.input.ff.points.clone(), &[d.n, d.h, d.w, 3])
    }

    /// `[N, h, w]` float32 confidence.
    #[getter]
    fn conf<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let d = self.input.dims;
        array(py, self.input.ff.conf.clone(), &[d.n, d.h, d.w])
    }

    /// `[N, 3, 4]` float64 `cam_from_world`.
    #[getter]
    fn cam_from_world<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        extrinsics(py, &self.input.ff.cameras.cam_from_world)
    }

    /// `[N, 3, 3]` float64 intrinsics (ff pixels, pixel-centre convention).
    #[getter]
    #[allow(non_snake_case)]
    fn K<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        intrinsics(py, &self.input.ff.cameras.intrinsics)
    }

    /// `[N, h, w, 3]` float32 images in `[0, 1]`, or `None`.
    #[getter]
    fn images<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyAny>>> {
        let d = self.input.dims;
        self.input
            .images
            .clone()
            .map(|v| array(py, v, &[d.n, d.h, d.w, 3]))
            .transpose()
    }

    /// Number of views.
    #[getter]
    fn num_views(&self) -> usize {
        self.input.dims.n
    }

    /// ff height (pixels).
    #[getter]
    fn height(&self) -> usize {
        self.input.dims.h
    }

    /// ff width (pixels).
    #[getter]
    fn width(&self) -> usize {
        self.input.dims.w
    }

    /// The layout it was read from (`vggt`, `mapanything`, `pi3`, `ggpt`).
    #[getter]
    fn format(&self) -> &'static str {
        self.input.format.name()
    }

    fn __repr__(&self) -> String {
        let d = self.input.dims;
        format!(
            "FeedForward(views={}, height={}, width={}, format={:?}, images={})",
            d.n,
            d.h,
            d.w,
            self.input.format.name(),
            self.input.images.is_some()
        )
    }
}

/// What a [`PyMatches`] holds.
#[derive(Clone)]
pub(crate) enum MatchData {
    /// A raw matcher output, converted to ff pixels when the scene's resolution is known.
    Raw {
        kind: RawKind,
        layout: PairLayout,
        primary: (Vec<usize>, Vec<f32>),
        score: (Vec<usize>, Vec<f32>),
        rank: Option<Vec<f32>>,
    },
    /// Already in ff pixels, `[t, s]` (a scene folder's `matches/*.safetensors`).
    Set(MatchSet),
}

/// Dense pairwise matches of one matcher.
#[pyclass(module = "ggpt_rs._ggpt_rs", name = "Matches", frozen)]
#[derive(Clone)]
pub struct PyMatches {
    pub(crate) name: String,
    pub(crate) data: MatchData,
}

impl PyMatches {
    /// The matches in ff pixels for a scene of `dims` (`MatchSet` layout `[t, s]`).
    pub(crate) fn to_match_set(&self, dims: Dims, index: usize) -> PyResult<MatchSet> {
        match &self.data {
            MatchData::Set(s) => Ok(s.clone()),
            MatchData::Raw {
                kind,
                layout,
                primary,
                score,
                rank,
            } => {
                let raw = RawMatches {
                    kind: *kind,
                    layout: *layout,
                    primary: &primary.1,
                    primary_shape: &primary.0,
                    score: &score.1,
                    score_shape: &score.0,
                };
                let what = format!("matches[{index}] ({})", self.name);
                let (pred_matches, pred_scores) = raw
                    .to_ff(dims.n, dims.h, dims.w, &what)
                    .map_err(sfm_error)?;
                if let Some(r) = rank
                    && r.len() != dims.n * dims.hw()
                {
                    return Err(invalid(format!(
                        "{what}: rank_scores has {} values, expected N*h*w = {}",
                        r.len(),
                        dims.n * dims.hw()
                    )));
                }
                Ok(MatchSet {
                    matcher: self.name.clone(),
                    pred_matches,
                    pred_scores,
                    pred_cycle_error: None,
                    rank_scores: rank.clone(),
                })
            }
        }
    }

    /// A scene folder's matches.
    pub(crate) fn from_set(set: MatchSet) -> Self {
        PyMatches {
            name: set.matcher.clone(),
            data: MatchData::Set(set),
        }
    }
}

#[pymethods]
impl PyMatches {
    /// Matches of one matcher for all ordered view pairs.
    ///
    /// * `kind="roma"` (RoMa v1/v2 `warp` `[N, N, Hm, Wm, 2]` in normalised edge coordinates,
    ///   `certainty` `[N, N, Hm, Wm]`), `"ufm"` (flow `[N, N, 2, Ho, Wo]` in output pixels,
    ///   covisibility `[N, N, Ho, Wo]`), `"pixels"` (a warp in matcher pixels, `[N, N, Hm, Wm,
    ///   2]`) or `"ff_pixels"` (locations in ff pixels `[N, N, h, w, 2]` or `[N, N, h*w, 2]`,
    ///   scores `[N, N, h, w]`, as the official `pred_matches`);
    /// * `layout`: the order of the two view axes, `"source_target"` (the raw `match_dense`
    ///   output: `[s, t]` maps the pixels of view `s` into view `t`) or `"target_source"` (the
    ///   official `pred_matches`);
    /// * `rank_scores`: optional `[N, h*w]` ranking score of the BA tracks (e.g. SuperPoint).
    #[new]
    #[pyo3(signature = (matches, scores, *, kind = "roma", layout = "source_target", name = "matcher", rank_scores = None))]
    fn new(
        matches: &Bound<'_, PyAny>,
        scores: &Bound<'_, PyAny>,
        kind: &str,
        layout: &str,
        name: &str,
        rank_scores: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        let kind = match kind {
            "roma" => RawKind::RomaWarp,
            "ufm" => RawKind::UfmFlow,
            "pixels" => RawKind::PixelWarp,
            "ff_pixels" => RawKind::FfPixels,
            other => {
                return Err(invalid(format!(
                    "kind {other:?}: expected roma, ufm, pixels or ff_pixels"
                )));
            }
        };
        let layout = match layout {
            "source_target" => PairLayout::SourceTarget,
            "target_source" => PairLayout::TargetSource,
            other => {
                return Err(invalid(format!(
                    "layout {other:?}: expected source_target or target_source"
                )));
            }
        };
        let primary = f32_values(matches, "matches")?;
        let score = f32_values(scores, "scores")?;
        let rank = rank_scores
            .map(|r| f32_values(r, "rank_scores").map(|(_, v)| v))
            .transpose()?;
        for (what, v) in [("matches", &primary.1), ("scores", &score.1)] {
            if let Some(i) = v.iter().position(|x| !x.is_finite()) {
                return Err(core_error(ggpt_core::CoreError::NonFinite {
                    path: format!("Matches({name})").into(),
                    key: what.into(),
                    index: i,
                    value: f64::from(v[i]),
                }));
            }
        }
        Ok(PyMatches {
            name: name.to_string(),
            data: MatchData::Raw {
                kind,
                layout,
                primary,
                score,
                rank,
            },
        })
    }

    /// Matcher name.
    #[getter]
    fn name(&self) -> &str {
        &self.name
    }

    /// `roma`, `ufm`, `pixels` or `ff_pixels`.
    #[getter]
    fn kind(&self) -> &'static str {
        match &self.data {
            MatchData::Set(_) => "ff_pixels",
            MatchData::Raw { kind, .. } => match kind {
                RawKind::RomaWarp => "roma",
                RawKind::UfmFlow => "ufm",
                RawKind::PixelWarp => "pixels",
                RawKind::FfPixels => "ff_pixels",
            },
        }
    }

    /// `source_target` or `target_source`.
    #[getter]
    fn layout(&self) -> &'static str {
        match &self.data {
            MatchData::Set(_) => "target_source",
            MatchData::Raw { layout, .. } => match layout {
                PairLayout::SourceTarget => "source_target",
                PairLayout::TargetSource => "target_source",
            },
        }
    }

    fn __repr__(&self) -> String {
        format!(
            "Matches(name={:?}, kind={:?}, layout={:?})",
            self.name,
            self.kind(),
            self.layout()
        )
    }
}

/// The SfM stage's output (SfM frame): DLT points, cameras, flags and the run's summary.
#[pyclass(module = "ggpt_rs._ggpt_rs", name = "SfmResult", frozen)]
#[derive(Clone)]
pub struct PySfmResult {
    pub(crate) dims: Dims,
    pub(crate) result: SfmResult,
    pub(crate) summary: Option<serde_json::Value>,
}

#[pymethods]
impl PySfmResult {
    /// `[N, h, w, 3]` float32 DLT points (SfM frame), 0 where `mask` is false.
    #[getter]
    fn points<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let d = self.dims;
        array(py, self.result.points.clone(), &[d.n, d.h, d.w, 3])
    }

    /// `[N, h, w]` bool: the pixel has a DLT point.
    #[getter]
    fn mask<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let d = self.dims;
        array(py, self.result.mask.clone(), &[d.n, d.h, d.w])
    }

    /// `[N, 3, 4]` float64 bundle-adjusted `cam_from_world` (SfM frame).
    #[getter]
    fn cam_from_world<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        extrinsics(py, &self.result.cameras.cam_from_world)
    }

    /// `[N, 3, 3]` float64 intrinsics (principal point at the image centre).
    #[getter]
    #[allow(non_snake_case)]
    fn K<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        intrinsics(py, &self.result.cameras.intrinsics)
    }

    /// The BA succeeded (otherwise the cameras are the feed-forward ones).
    #[getter]
    fn camera_success(&self) -> bool {
        self.result.camera_success
    }

    /// At least one DLT point.
    #[getter]
    fn points_success(&self) -> bool {
        self.result.points_success
    }

    /// The SfM run's summary (what `ggpt-sfm run` writes as `summary.json`), or `None` when
    /// the result was read from a file.
    #[getter]
    fn summary<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyAny>>> {
        self.summary.as_ref().map(|s| json_value(py, s)).transpose()
    }

    fn __repr__(&self) -> String {
        format!(
            "SfmResult(dlt_pixels={}, camera_success={}, points_success={})",
            self.result.mask.iter().filter(|&&m| m).count(),
            self.result.camera_success,
            self.result.points_success
        )
    }
}

/// A scene read from a folder (`read_scene`): every layout `ggpt-infer run --scene` reads.
#[pyclass(module = "ggpt_rs._ggpt_rs", name = "Scene", frozen)]
pub struct PyScene {
    pub(crate) scene: Scene,
}

#[pymethods]
impl PyScene {
    /// Scene name (seeds the chunk sampler unless `seed` is given).
    #[getter]
    fn name(&self) -> &str {
        &self.scene.name
    }

    /// The feed-forward prediction (with the scene's images), or `None`.
    #[getter]
    fn ff(&self) -> Option<PyFeedForward> {
        self.scene.ff.as_ref().map(|ff| PyFeedForward {
            input: FeedForwardInput {
                format: FfFormat::Ggpt,
                dims: self.scene.dims,
                ff: ff.clone(),
                images: Some(self.scene.images.clone()),
            },
        })
    }

    /// The dense matches, one `Matches` per matcher (ff pixels).
    #[getter]
    fn matches<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        PyList::new(
            py,
            self.scene
                .matches
                .iter()
                .map(|m| PyMatches::from_set(m.clone())),
        )
    }

    /// The SfM result stored in the folder, or `None`.
    #[getter]
    fn sfm(&self) -> Option<PySfmResult> {
        self.scene.sfm.as_ref().map(|s| PySfmResult {
            dims: self.scene.dims,
            result: s.clone(),
            summary: None,
        })
    }

    /// Ground truth as a dict (`points [N, h, w, 3]`, `mask [N, h, w]`, `cam_from_world`,
    /// `K`), or `None`.
    #[getter]
    fn gt<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
        let Some(gt) = &self.scene.gt else {
            return Ok(None);
        };
        let d = self.scene.dims;
        let out = PyDict::new(py);
        out.set_item("points", array(py, gt.points.clone(), &[d.n, d.h, d.w, 3])?)?;
        out.set_item("mask", array(py, gt.mask.clone(), &[d.n, d.h, d.w])?)?;
        out.set_item(
            "cam_from_world",
            extrinsics(py, &gt.cameras.cam_from_world)?,
        )?;
        out.set_item("K", intrinsics(py, &gt.cameras.intrinsics)?)?;
        Ok(Some(out))
    }

    /// `[N, h, w, 3]` float32 images in `[0, 1]`.
    #[getter]
    fn images<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let d = self.scene.dims;
        array(py, self.scene.images.clone(), &[d.n, d.h, d.w, 3])
    }

    fn __repr__(&self) -> String {
        let d = self.scene.dims;
        format!(
            "Scene(name={:?}, views={}, height={}, width={}, matchers={}, sfm={}, gt={})",
            self.scene.name,
            d.n,
            d.h,
            d.w,
            self.scene.matches.len(),
            self.scene.sfm.is_some(),
            self.scene.gt.is_some()
        )
    }
}

/// Reads a scene folder (project scene directory, official `ff_outputs.bin` +
/// `sfm_dlt_outputs.bin` [+ `gt.bin`], or `images/` + `ff.npz` + `matches/` [+ `sfm.npz`]).
#[pyfunction]
pub fn read_scene(py: Python<'_>, path: std::path::PathBuf) -> PyResult<PyScene> {
    let scene = py
        .detach(|| ggpt_core::io::read_scene(&path))
        .map_err(core_error)?;
    Ok(PyScene { scene })
}
