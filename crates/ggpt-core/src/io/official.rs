//! The official GGPT scene dicts `gt.bin`, `ff_outputs.bin`, `sfm_dlt_outputs.bin`
//! (`formats.md` §3): torch zip pickles read with the `pytorch-reader` crate, which gathers
//! strided / offset views into contiguous row-major data and reads Python bools.
//!
//! Values are kept exactly as stored (f32 after an up-cast of f16 / bf16, or a down-cast of f64,
//! matching the official `EvalDataset`'s `.float()`); [`read_official_dir`] maps them into a
//! [`Scene`] (extrinsics `[N,4,4]` → `[3,4]`, K f32 → f64, images from `images_ff` or `images`).
//! Unknown keys are ignored.

use std::collections::HashMap;
use std::path::Path;

use nalgebra::{Matrix3, Matrix3x4};
use pytorch_reader::{DType, PickleValue, PytorchReader, Tensor};

use crate::io::atomic::write_bytes_atomic;
use crate::io::st::{StWriter, check_finite_f32};
use crate::{Cameras, CoreError, Dims, FeedForward, GroundTruth, Result, Scene, SfmResult};

/// Tolerance on the last row `0 0 0 1` of a `[N, 4, 4]` extrinsic matrix.
const HOMOGENEOUS_ROW_TOL: f32 = 1e-4;

/// `gt.bin` (`formats.md` §3.1), values as stored.
#[derive(Debug, Clone, PartialEq)]
pub struct GtBin {
    /// ff resolution.
    pub dims: Dims,
    /// `[N, h, w, 3]` GT world points (metres), 0 where invalid.
    pub points: Vec<f32>,
    /// `[N, h, w]` valid GT depth.
    pub point_masks: Vec<bool>,
    /// `[N, 3, 3]` K at ff resolution (ff pixels, pixel-centre convention).
    pub intrinsics: Vec<f32>,
    /// `[N, 4, 4]` (or `[N, 3, 4]` as stored, padded to 4x4) GT `cam_from_world`, OpenCV.
    pub extrinsics: Vec<f32>,
    /// `[N, h, w, 3]` images in `[0, 1]`.
    pub images: Vec<f32>,
}

/// `ff_outputs.bin` (`formats.md` §3.2), values as stored.
#[derive(Debug, Clone, PartialEq)]
pub struct FfOutputsBin {
    /// ff resolution.
    pub dims: Dims,
    /// `[N, h, w, 3]` feed-forward input images in `[0, 1]`.
    pub images_ff: Vec<f32>,
    /// `[N, 3, 4]` feed-forward `cam_from_world`.
    pub extrinsics: Vec<f32>,
    /// `[N, 3, 3]` feed-forward K.
    pub intrinsics: Vec<f32>,
    /// `[N, h, w, 3]` dense points `X_d` (feed-forward frame).
    pub points: Vec<f32>,
    /// `[N, h, w]` raw confidence.
    pub points_conf: Vec<f32>,
}

/// `sfm_dlt_outputs.bin` (`formats.md` §3.3), values as stored.
#[derive(Debug, Clone, PartialEq)]
pub struct SfmDltOutputsBin {
    /// ff resolution.
    pub dims: Dims,
    /// `[N, 3, 3]` BA K.
    pub intrinsics: Vec<f32>,
    /// `[N, 3, 4]` BA `cam_from_world`.
    pub extrinsics: Vec<f32>,
    /// BA ran.
    pub camera_success: bool,
    /// `[N, h, w, 3]` DLT point map (SfM frame), 0 where no point.
    pub points: Vec<f32>,
    /// `[N, h, w]` `M_s`.
    pub point_masks: Vec<bool>,
    /// At least one DLT pixel.
    pub points_success: bool,
}

/// An opened official pickle: its tensors by dotted key and its pickle tree (for bools).
struct Pickle<'a> {
    path: &'a Path,
    tensors: HashMap<String, Tensor>,
    tree: Option<PickleValue>,
}

impl<'a> Pickle<'a> {
    fn open(path: &'a Path, need_tree: bool) -> Result<Self> {
        if !path.is_file() {
            return Err(CoreError::io(
                path,
                std::io::Error::new(std::io::ErrorKind::NotFound, "file not found"),
            ));
        }
        let bad = |e: pytorch_reader::PytorchError| {
            CoreError::format(
                path,
                "",
                format!("cannot read torch pickle (corrupt or truncated?): {e}"),
            )
        };
        let tensors = PytorchReader::new(path).map_err(bad)?.into_tensors();
        let tree = if need_tree {
            Some(PytorchReader::read_pickle_data(path, None).map_err(bad)?)
        } else {
            None
        };
        Ok(Self {
            path,
            tensors,
            tree,
        })
    }

    fn err(&self, key: &str, msg: impl Into<String>) -> CoreError {
        CoreError::format(self.path, key, msg)
    }

    fn get(&self, key: &str) -> Result<&Tensor> {
        self.tensors.get(key).ok_or_else(|| {
            let mut keys: Vec<&String> = self.tensors.keys().collect();
            keys.sort();
            self.err(key, format!("missing tensor (tensors present: {keys:?})"))
        })
    }

    fn bytes(&self, key: &str, t: &Tensor) -> Result<Vec<u8>> {
        let b = t
            .read()
            .map_err(|e| self.err(key, format!("cannot read tensor data: {e}")))?;
        if b.len() != t.byte_len() {
            return Err(self.err(
                key,
                format!(
                    "tensor data has {} bytes, expected {}",
                    b.len(),
                    t.byte_len()
                ),
            ));
        }
        Ok(b)
    }

    /// Float tensor `key` as f32 (f32 as is; f64 / f16 / bf16 converted), shape checked.
    fn f32(&self, key: &str, shape: &[usize]) -> Result<Vec<f32>> {
        let t = self.get(key)?;
        self.check_shape(key, t, shape)?;
        let b = self.bytes(key, t)?;
        let v = match t.dtype() {
            DType::F32 => b
                .chunks_exact(4)
                .map(|c| f32::from_ne_bytes([c[0], c[1], c[2], c[3]]))
                .collect(),
            DType::F64 => b
                .chunks_exact(8)
                .map(|c| {
                    f64::from_ne_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]) as f32
                })
                .collect(),
            DType::F16 => b
                .chunks_exact(2)
                .map(|c| half::f16::from_ne_bytes([c[0], c[1]]).to_f32())
                .collect(),
            DType::BF16 => b
                .chunks_exact(2)
                .map(|c| half::bf16::from_ne_bytes([c[0], c[1]]).to_f32())
                .collect(),
            other => {
                return Err(self.err(
                    key,
                    format!("wrong dtype {other:?}, expected a float tensor (f32)"),
                ));
            }
        };
        Ok(v)
    }

    /// Finite float tensor.
    fn f32_finite(&self, key: &str, shape: &[usize]) -> Result<Vec<f32>> {
        let v = self.f32(key, shape)?;
        check_finite_f32(self.path, key, &v)?;
        Ok(v)
    }

    /// Bool tensor `key` (bool, or u8 holding 0 / 1), shape checked.
    fn bool(&self, key: &str, shape: &[usize]) -> Result<Vec<bool>> {
        let t = self.get(key)?;
        self.check_shape(key, t, shape)?;
        if !matches!(t.dtype(), DType::Bool | DType::U8) {
            return Err(self.err(key, format!("wrong dtype {:?}, expected bool", t.dtype())));
        }
        let b = self.bytes(key, t)?;
        b.iter()
            .enumerate()
            .map(|(i, &x)| match x {
                0 => Ok(false),
                1 => Ok(true),
                _ => Err(self.err(key, format!("value {x} at flat index {i} is not a bool"))),
            })
            .collect()
    }

    fn check_shape(&self, key: &str, t: &Tensor, shape: &[usize]) -> Result<()> {
        if t.shape() != shape {
            return Err(self.err(
                key,
                format!("wrong shape {:?}, expected {shape:?}", t.shape()),
            ));
        }
        Ok(())
    }

    /// `[N, h, w]` from a `[N, h, w, 3]` tensor `key`.
    fn dims_of(&self, key: &str) -> Result<Dims> {
        let t = self.get(key)?;
        match t.shape() {
            [n, h, w, 3] if *n > 0 && *h > 0 && *w > 0 => Ok(Dims {
                n: *n,
                h: *h,
                w: *w,
            }),
            s => Err(self.err(
                key,
                format!("wrong shape {s:?}, expected [N, h, w, 3] with N, h, w > 0"),
            )),
        }
    }

    /// `[N, 3, 4]` extrinsics (a `[N, 4, 4]` input is accepted when its last row is `0 0 0 1`).
    fn extrinsics_3x4(&self, key: &str, n: usize) -> Result<Vec<f32>> {
        let t = self.get(key)?;
        match t.shape() {
            [_, 4, 4] => {
                let v = self.f32_finite(key, &[n, 4, 4])?;
                to_3x4(&v).map_err(|i| self.err(key, format!("view {i}: last row is not 0 0 0 1")))
            }
            _ => self.f32_finite(key, &[n, 3, 4]),
        }
    }

    /// Python bool `key` of the top-level dict (also accepts an int or a 0-d bool tensor).
    fn py_bool(&self, key: &str) -> Result<bool> {
        if let Some(PickleValue::Dict(d)) = &self.tree {
            match d.get(key) {
                Some(PickleValue::Bool(b)) => return Ok(*b),
                Some(PickleValue::Int(i)) => return Ok(*i != 0),
                _ => {}
            }
        }
        if self.tensors.contains_key(key) {
            let v = self.bool(key, &[])?;
            return v
                .first()
                .copied()
                .ok_or_else(|| self.err(key, "empty scalar"));
        }
        Err(self.err(key, "missing Python bool"))
    }
}

/// Drops the last row of each `[4, 4]` matrix; `Err(view)` when it is not `0 0 0 1`.
fn to_3x4(v: &[f32]) -> std::result::Result<Vec<f32>, usize> {
    let mut out = Vec::with_capacity(v.len() / 4 * 3);
    for (i, m) in v.chunks_exact(16).enumerate() {
        let last = [m[12], m[13], m[14], m[15] - 1.0];
        if last.iter().any(|x| x.abs() > HOMOGENEOUS_ROW_TOL) {
            return Err(i);
        }
        out.extend_from_slice(&m[..12]);
    }
    Ok(out)
}

/// Reads `gt.bin`. Extrinsics are returned as stored (`[N, 4, 4]`; a `[N, 3, 4]` file is padded).
pub fn read_gt_bin(path: &Path) -> Result<GtBin> {
    let p = Pickle::open(path, false)?;
    let d = p.dims_of("points")?;
    let (n, h, w) = (d.n, d.h, d.w);
    let ext = p.get("extrinsics")?;
    let extrinsics = match ext.shape() {
        [_, 3, 4] => p
            .f32_finite("extrinsics", &[n, 3, 4])?
            .chunks_exact(12)
            .flat_map(|m| m.iter().copied().chain([0.0, 0.0, 0.0, 1.0]))
            .collect(),
        _ => {
            let v = p.f32_finite("extrinsics", &[n, 4, 4])?;
            to_3x4(&v)
                .map_err(|i| p.err("extrinsics", format!("view {i}: last row is not 0 0 0 1")))?;
            v
        }
    };
    Ok(GtBin {
        dims: d,
        points: p.f32_finite("points", &[n, h, w, 3])?,
        point_masks: p.bool("point_masks", &[n, h, w])?,
        intrinsics: p.f32_finite("intrinsics", &[n, 3, 3])?,
        extrinsics,
        images: p.f32_finite("images", &[n, h, w, 3])?,
    })
}

/// Reads `ff_outputs.bin` (`[N, 4, 4]` extrinsics are accepted and cut to `[N, 3, 4]`).
pub fn read_ff_outputs_bin(path: &Path) -> Result<FfOutputsBin> {
    let p = Pickle::open(path, false)?;
    let d = p.dims_of("points")?;
    let (n, h, w) = (d.n, d.h, d.w);
    Ok(FfOutputsBin {
        dims: d,
        images_ff: p.f32_finite("images_ff", &[n, h, w, 3])?,
        extrinsics: p.extrinsics_3x4("extrinsics", n)?,
        intrinsics: p.f32_finite("intrinsics", &[n, 3, 3])?,
        points: p.f32_finite("points", &[n, h, w, 3])?,
        points_conf: p.f32_finite("points_conf", &[n, h, w])?,
    })
}

/// Reads `sfm_dlt_outputs.bin` (the newest versions' extra keys are ignored).
pub fn read_sfm_dlt_outputs_bin(path: &Path) -> Result<SfmDltOutputsBin> {
    let p = Pickle::open(path, true)?;
    let d = p.dims_of("points")?;
    let (n, h, w) = (d.n, d.h, d.w);
    Ok(SfmDltOutputsBin {
        dims: d,
        intrinsics: p.f32_finite("intrinsics", &[n, 3, 3])?,
        extrinsics: p.extrinsics_3x4("extrinsics", n)?,
        camera_success: p.py_bool("camera_success")?,
        points: p.f32_finite("points", &[n, h, w, 3])?,
        point_masks: p.bool("point_masks", &[n, h, w])?,
        points_success: p.py_bool("points_success")?,
    })
}

/// `[N, 3, 4]` f32 row-major → f64 matrices.
fn ext_f64(v: &[f32]) -> Vec<Matrix3x4<f64>> {
    v.chunks_exact(12)
        .map(|m| Matrix3x4::from_row_iterator(m.iter().map(|&x| f64::from(x))))
        .collect()
}

/// `[N, 3, 3]` f32 row-major → f64 matrices.
fn k_f64(v: &[f32]) -> Vec<Matrix3<f64>> {
    v.chunks_exact(9)
        .map(|m| Matrix3::from_row_iterator(m.iter().map(|&x| f64::from(x))))
        .collect()
}

impl GtBin {
    /// Scene ground truth (extrinsics cut to 3x4, K as f64; no depth in the official file).
    pub fn to_ground_truth(&self) -> GroundTruth {
        let ext = to_3x4(&self.extrinsics).unwrap_or_default();
        GroundTruth {
            points: self.points.clone(),
            mask: self.point_masks.clone(),
            depth: None,
            cameras: Cameras {
                cam_from_world: ext_f64(&ext),
                intrinsics: k_f64(&self.intrinsics),
            },
        }
    }
}

impl FfOutputsBin {
    /// Scene feed-forward prediction.
    pub fn to_feed_forward(&self) -> FeedForward {
        FeedForward {
            points: self.points.clone(),
            conf: self.points_conf.clone(),
            cameras: Cameras {
                cam_from_world: ext_f64(&self.extrinsics),
                intrinsics: k_f64(&self.intrinsics),
            },
        }
    }
}

impl SfmDltOutputsBin {
    /// Scene SfM result.
    pub fn to_sfm_result(&self) -> SfmResult {
        SfmResult {
            points: self.points.clone(),
            mask: self.point_masks.clone(),
            cameras: Cameras {
                cam_from_world: ext_f64(&self.extrinsics),
                intrinsics: k_f64(&self.intrinsics),
            },
            camera_success: self.camera_success,
            points_success: self.points_success,
        }
    }
}

/// Checks that `got` (from `file`, tensor `key`) equals the dims established so far.
fn same_dims(
    file: &Path,
    key: &str,
    got: Dims,
    want: &mut Option<(Dims, std::path::PathBuf)>,
) -> Result<()> {
    match want {
        Some((d, first)) if *d != got => Err(CoreError::format(
            file,
            key,
            format!(
                "N={} h={} w={} differ from N={} h={} w={} of {}",
                got.n,
                got.h,
                got.w,
                d.n,
                d.h,
                d.w,
                first.display()
            ),
        )),
        Some(_) => Ok(()),
        None => {
            *want = Some((got, file.to_path_buf()));
            Ok(())
        }
    }
}

/// Reads an official three-file directory (any subset holding `ff_outputs.bin` or `gt.bin`).
/// The scene name is the directory name (it seeds the chunk sampler, `pipeline.md` §5); images
/// come from `images_ff` (else the GT `images`). Not validated; `crate::io::read_scene` does that.
pub fn read_official_dir(dir: &Path) -> Result<Scene> {
    let (gt_p, ff_p, sfm_p) = (
        dir.join("gt.bin"),
        dir.join("ff_outputs.bin"),
        dir.join("sfm_dlt_outputs.bin"),
    );
    let gt = if gt_p.is_file() {
        Some(read_gt_bin(&gt_p)?)
    } else {
        None
    };
    let ff = if ff_p.is_file() {
        Some(read_ff_outputs_bin(&ff_p)?)
    } else {
        None
    };
    let sfm = if sfm_p.is_file() {
        Some(read_sfm_dlt_outputs_bin(&sfm_p)?)
    } else {
        None
    };
    let mut dims = None;
    if let Some(f) = &ff {
        same_dims(&ff_p, "points", f.dims, &mut dims)?;
    }
    if let Some(g) = &gt {
        same_dims(&gt_p, "points", g.dims, &mut dims)?;
    }
    if let Some(s) = &sfm {
        same_dims(&sfm_p, "points", s.dims, &mut dims)?;
    }
    let images = match (&ff, &gt) {
        (Some(f), _) => f.images_ff.clone(),
        (None, Some(g)) => g.images.clone(),
        (None, None) => {
            return Err(CoreError::format(
                dir,
                "",
                "official layout needs ff_outputs.bin or gt.bin",
            ));
        }
    };
    let dims = dims
        .map(|d| d.0)
        .ok_or_else(|| CoreError::format(dir, "", "no scene file found"))?;
    Ok(Scene {
        name: dir_name(dir),
        dims,
        images,
        gt: gt.as_ref().map(GtBin::to_ground_truth),
        ff: ff.as_ref().map(FfOutputsBin::to_feed_forward),
        sfm: sfm.as_ref().map(SfmDltOutputsBin::to_sfm_result),
        matches: Vec::new(),
    })
}

/// Name of a directory (its last component; canonicalised first so `.` works).
pub fn dir_name(dir: &Path) -> String {
    let canon = dir.canonicalize().unwrap_or_else(|_| dir.to_path_buf());
    canon
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default()
}

fn cams_f32(c: &Cameras) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let e34: Vec<f32> = c
        .cam_from_world
        .iter()
        .flat_map(|m| m.transpose().iter().map(|&x| x as f32).collect::<Vec<_>>())
        .collect();
    let e44: Vec<f32> = e34
        .chunks_exact(12)
        .flat_map(|m| m.iter().copied().chain([0.0, 0.0, 0.0, 1.0]))
        .collect();
    let k: Vec<f32> = c
        .intrinsics
        .iter()
        .flat_map(|m| m.transpose().iter().map(|&x| x as f32).collect::<Vec<_>>())
        .collect();
    (e34, e44, k)
}

/// Writes the official quantities of `scene` as one safetensors file with the key names of
/// `../shared/fixtures/official_format/*/reference.safetensors`: `gt/{points, point_masks,
/// intrinsics, extrinsics [N,4,4], images}`, `ff_outputs/{images_ff, extrinsics [N,3,4],
/// intrinsics, points, points_conf}`, `sfm_dlt_outputs/{intrinsics, extrinsics, camera_success,
/// points, point_masks, points_success}` (f32, bools as BOOL, flags 0-d). Parts absent from the
/// scene are omitted. Atomic.
pub fn write_official_safetensors(path: &Path, scene: &Scene) -> Result<()> {
    scene.validate()?;
    let d = scene.dims;
    let (n, h, w) = (d.n, d.h, d.w);
    let mut st = StWriter::new();
    if let Some(gt) = &scene.gt {
        let (_, e44, k) = cams_f32(&gt.cameras);
        st.f32("gt/points", &[n, h, w, 3], &gt.points);
        st.bool("gt/point_masks", &[n, h, w], &gt.mask);
        st.f32("gt/intrinsics", &[n, 3, 3], &k);
        st.f32("gt/extrinsics", &[n, 4, 4], &e44);
        st.f32("gt/images", &[n, h, w, 3], &scene.images);
    }
    if let Some(ff) = &scene.ff {
        let (e34, _, k) = cams_f32(&ff.cameras);
        st.f32("ff_outputs/images_ff", &[n, h, w, 3], &scene.images);
        st.f32("ff_outputs/extrinsics", &[n, 3, 4], &e34);
        st.f32("ff_outputs/intrinsics", &[n, 3, 3], &k);
        st.f32("ff_outputs/points", &[n, h, w, 3], &ff.points);
        st.f32("ff_outputs/points_conf", &[n, h, w], &ff.conf);
    }
    if let Some(sfm) = &scene.sfm {
        let (e34, _, k) = cams_f32(&sfm.cameras);
        st.f32("sfm_dlt_outputs/intrinsics", &[n, 3, 3], &k);
        st.f32("sfm_dlt_outputs/extrinsics", &[n, 3, 4], &e34);
        st.bool("sfm_dlt_outputs/camera_success", &[], &[sfm.camera_success]);
        st.f32("sfm_dlt_outputs/points", &[n, h, w, 3], &sfm.points);
        st.bool("sfm_dlt_outputs/point_masks", &[n, h, w], &sfm.mask);
        st.bool("sfm_dlt_outputs/points_success", &[], &[sfm.points_success]);
    }
    let bytes = st.finish(path, None)?;
    write_bytes_atomic(path, &bytes)
}
