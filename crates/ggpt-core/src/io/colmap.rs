//! COLMAP sparse models (`formats.md` §6.2): `cameras`, `images`, `points3D` in binary (default)
//! or text, read and written.
//!
//! [`ColmapModel`] holds values **exactly as in the files**, i.e. in COLMAP's conventions: pixel
//! coordinates use the corner convention (top-left pixel centre at `(0.5, 0.5)`), poses are
//! `cam_from_world` as a Hamilton quaternion `(qw, qx, qy, qz)` + translation, ids from 1.
//! Conversion to and from the pipeline's pixel-centre convention happens only in
//! [`ColmapModel::from_cameras`], [`ColmapCamera::to_pinhole`], [`pixel_to_colmap`] and
//! [`colmap_to_pixel`] (`x_colmap = x + 0.5`).
//!
//! The writer emits `SIMPLE_PINHOLE` / `PINHOLE` only. The reader accepts the seven models of
//! §6.2, tolerates `rigs.*` / `frames.*` (ignored), prefers binary when both kinds exist, and is
//! lenient with text (comments, blank lines, a missing last points line); conversion to a
//! pinhole K rejects non-zero distortion and fisheye models.

use std::io::Write;
use std::path::{Path, PathBuf};

use nalgebra::{Matrix3, Matrix3x4, Rotation3, UnitQuaternion, Vector3};

use crate::io::atomic::write_atomic;
use crate::{Cameras, CoreError, Result};

/// Point3D id meaning "no 3D point" in `images.bin`.
pub const INVALID_POINT3D_ID: u64 = u64::MAX;

/// COLMAP camera models accepted (`formats.md` §6.2).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ColmapCameraModel {
    /// id 0: `f, cx, cy`
    SimplePinhole,
    /// id 1: `fx, fy, cx, cy`
    Pinhole,
    /// id 2: `f, cx, cy, k`
    SimpleRadial,
    /// id 3: `f, cx, cy, k1, k2`
    Radial,
    /// id 4: `fx, fy, cx, cy, k1, k2, p1, p2`
    Opencv,
    /// id 5: `fx, fy, cx, cy, k1, k2, k3, k4`
    OpencvFisheye,
    /// id 6: `fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6`
    FullOpencv,
}

const MODELS: [(ColmapCameraModel, i32, &str, usize); 7] = [
    (ColmapCameraModel::SimplePinhole, 0, "SIMPLE_PINHOLE", 3),
    (ColmapCameraModel::Pinhole, 1, "PINHOLE", 4),
    (ColmapCameraModel::SimpleRadial, 2, "SIMPLE_RADIAL", 4),
    (ColmapCameraModel::Radial, 3, "RADIAL", 5),
    (ColmapCameraModel::Opencv, 4, "OPENCV", 8),
    (ColmapCameraModel::OpencvFisheye, 5, "OPENCV_FISHEYE", 8),
    (ColmapCameraModel::FullOpencv, 6, "FULL_OPENCV", 12),
];

impl ColmapCameraModel {
    fn row(self) -> (ColmapCameraModel, i32, &'static str, usize) {
        MODELS
            .iter()
            .copied()
            .find(|r| r.0 == self)
            .unwrap_or(MODELS[0])
    }
    /// COLMAP model id.
    pub fn id(self) -> i32 {
        self.row().1
    }
    /// COLMAP model name.
    pub fn name(self) -> &'static str {
        self.row().2
    }
    /// Number of parameters.
    pub fn num_params(self) -> usize {
        self.row().3
    }
    fn from_id(id: i32) -> Option<Self> {
        MODELS.iter().find(|r| r.1 == id).map(|r| r.0)
    }
    fn from_name(name: &str) -> Option<Self> {
        MODELS.iter().find(|r| r.2 == name).map(|r| r.0)
    }
}

/// One camera (parameters in COLMAP corner convention).
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapCamera {
    /// Camera id (≥ 1).
    pub id: u32,
    /// Model.
    pub model: ColmapCameraModel,
    /// Image width in pixels.
    pub width: u64,
    /// Image height in pixels.
    pub height: u64,
    /// Parameters in model order (principal point in corner convention).
    pub params: Vec<f64>,
}

/// One 2D observation of an image (corner convention).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ColmapPoint2D {
    /// `(x, y)` in COLMAP pixels (corner convention).
    pub xy: [f64; 2],
    /// Observed 3D point, if any.
    pub point3d_id: Option<u64>,
}

/// One registered image.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapImage {
    /// Image id (≥ 1).
    pub id: u32,
    /// `cam_from_world` rotation, Hamilton `(qw, qx, qy, qz)`.
    pub qvec: [f64; 4],
    /// `cam_from_world` translation.
    pub tvec: [f64; 3],
    /// Camera id.
    pub camera_id: u32,
    /// Image file name.
    pub name: String,
    /// Observations.
    pub points2d: Vec<ColmapPoint2D>,
}

/// One 3D point with its track.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapPoint3D {
    /// Point id (≥ 1).
    pub id: u64,
    /// World coordinates.
    pub xyz: [f64; 3],
    /// Colour.
    pub rgb: [u8; 3],
    /// Mean reprojection error (pixels).
    pub error: f64,
    /// Track: `(image_id, point2D_idx)`.
    pub track: Vec<(u32, u32)>,
}

/// A COLMAP sparse model, values as stored in the files (COLMAP conventions).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ColmapModel {
    /// Cameras.
    pub cameras: Vec<ColmapCamera>,
    /// Images.
    pub images: Vec<ColmapImage>,
    /// 3D points.
    pub points3d: Vec<ColmapPoint3D>,
}

/// Pipeline pixel (pixel-centre convention) → COLMAP pixel (corner convention): `+ 0.5`.
pub fn pixel_to_colmap(xy: [f64; 2]) -> [f64; 2] {
    [xy[0] + 0.5, xy[1] + 0.5]
}

/// COLMAP pixel (corner convention) → pipeline pixel (pixel-centre convention): `- 0.5`.
pub fn colmap_to_pixel(xy: [f64; 2]) -> [f64; 2] {
    [xy[0] - 0.5, xy[1] - 0.5]
}

/// Hamilton `(w, x, y, z)` of the rotation closest to `r` (re-orthonormalised), with `w >= 0`.
pub fn rotation_to_qvec(r: &Matrix3<f64>) -> [f64; 4] {
    let rot = Rotation3::from_matrix(r);
    let q = UnitQuaternion::from_rotation_matrix(&rot);
    let s = if q.w < 0.0 { -1.0 } else { 1.0 };
    [s * q.w, s * q.i, s * q.j, s * q.k]
}

/// Rotation matrix of a Hamilton `(w, x, y, z)` quaternion (normalised first).
pub fn qvec_to_rotation(q: [f64; 4]) -> Matrix3<f64> {
    let uq = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[0], q[1], q[2], q[3]));
    uq.to_rotation_matrix().into_inner()
}

impl ColmapCamera {
    /// Pinhole K in the pipeline's **pixel-centre** convention (`cx = cx_colmap - 0.5`).
    /// Distortion models are accepted only when every distortion coefficient is exactly 0;
    /// `OPENCV_FISHEYE` is rejected (an equidistant projection is not a pinhole).
    pub fn to_pinhole(&self) -> std::result::Result<Matrix3<f64>, String> {
        let p = &self.params;
        if p.len() != self.model.num_params() {
            return Err(format!(
                "camera {}: {} parameters, {} expects {}",
                self.id,
                p.len(),
                self.model.name(),
                self.model.num_params()
            ));
        }
        let (fx, fy, cx, cy, dist): (f64, f64, f64, f64, &[f64]) = match self.model {
            ColmapCameraModel::SimplePinhole => (p[0], p[0], p[1], p[2], &[]),
            ColmapCameraModel::Pinhole => (p[0], p[1], p[2], p[3], &[]),
            ColmapCameraModel::SimpleRadial | ColmapCameraModel::Radial => {
                (p[0], p[0], p[1], p[2], &p[3..])
            }
            ColmapCameraModel::Opencv | ColmapCameraModel::FullOpencv => {
                (p[0], p[1], p[2], p[3], &p[4..])
            }
            ColmapCameraModel::OpencvFisheye => {
                return Err(format!(
                    "camera {}: OPENCV_FISHEYE (equidistant projection) cannot be represented as a pinhole camera",
                    self.id
                ));
            }
        };
        if let Some(d) = dist.iter().find(|d| **d != 0.0) {
            return Err(format!(
                "camera {}: {} with non-zero distortion ({d}) is not supported; undistort the images first",
                self.id,
                self.model.name()
            ));
        }
        Ok(Matrix3::new(
            fx,
            0.0,
            cx - 0.5,
            0.0,
            fy,
            cy - 0.5,
            0.0,
            0.0,
            1.0,
        ))
    }
}

/// The `SIMPLE_PINHOLE` focal of a pinhole `K`: `(fx + fy) / 2` (`sfm.md` §7.1, the official
/// rule when the BA initialises a SIMPLE_PINHOLE camera).
pub fn simple_pinhole_focal(k: &Matrix3<f64>) -> f64 {
    0.5 * (k[(0, 0)] + k[(1, 1)])
}

impl ColmapModel {
    /// Builds cameras and images from pipeline cameras (pixel-centre convention, `h x w`
    /// images): one `PINHOLE` (or `SIMPLE_PINHOLE` when `simple`, with the official focal rule
    /// `f = (fx + fy) / 2` of `sfm.md` §7.1) camera per view, or one shared camera (view 0's K)
    /// when `shared`; images named `names[i]`, ids `1..N`. No 3D points. The one writer of COLMAP
    /// cameras and images in the workspace (`ggpt-sfm` and `ggpt-scene` exports use it).
    pub fn from_cameras(
        cams: &Cameras,
        h: usize,
        w: usize,
        names: &[String],
        simple: bool,
        shared: bool,
    ) -> Result<Self> {
        Self::from_cameras_sized(cams, &vec![(h, w); cams.len()], names, simple, shared)
    }

    /// [`ColmapModel::from_cameras`] with each view's image size `sizes[i] = (h, w)`; a shared
    /// camera needs one size for all views.
    pub fn from_cameras_sized(
        cams: &Cameras,
        sizes: &[(usize, usize)],
        names: &[String],
        simple: bool,
        shared: bool,
    ) -> Result<Self> {
        if names.len() != cams.len() || sizes.len() != cams.len() {
            return Err(CoreError::Invalid(format!(
                "{} image names / {} image sizes for {} cameras",
                names.len(),
                sizes.len(),
                cams.len()
            )));
        }
        if shared && sizes.windows(2).any(|p| p[0] != p[1]) {
            return Err(CoreError::Invalid(
                "one shared camera for images of different sizes".into(),
            ));
        }
        let mut model = ColmapModel::default();
        for (i, (k, name)) in cams.intrinsics.iter().zip(names).enumerate() {
            let (h, w) = sizes[i];
            let id =
                u32::try_from(i + 1).map_err(|_| CoreError::Invalid("too many views".into()))?;
            if !shared || i == 0 {
                let (cx, cy) = (k[(0, 2)] + 0.5, k[(1, 2)] + 0.5);
                let (m, params) = if simple {
                    (
                        ColmapCameraModel::SimplePinhole,
                        vec![simple_pinhole_focal(k), cx, cy],
                    )
                } else {
                    (
                        ColmapCameraModel::Pinhole,
                        vec![k[(0, 0)], k[(1, 1)], cx, cy],
                    )
                };
                model.cameras.push(ColmapCamera {
                    id,
                    model: m,
                    width: w as u64,
                    height: h as u64,
                    params,
                });
            }
            let r = cams.rotation(i);
            let t = cams.translation(i);
            model.images.push(ColmapImage {
                id,
                qvec: rotation_to_qvec(&r),
                tvec: [t.x, t.y, t.z],
                camera_id: if shared { 1 } else { id },
                name: name.clone(),
                points2d: Vec::new(),
            });
        }
        Ok(model)
    }

    /// Pipeline cameras of the images in file order (`cam_from_world` from the quaternion,
    /// pinhole K in pixel-centre convention), plus the image names. `path` names errors.
    pub fn to_cameras(&self, path: &Path) -> Result<(Cameras, Vec<String>)> {
        let mut cams = Cameras {
            cam_from_world: Vec::new(),
            intrinsics: Vec::new(),
        };
        let mut names = Vec::new();
        for im in &self.images {
            let cam = self
                .cameras
                .iter()
                .find(|c| c.id == im.camera_id)
                .ok_or_else(|| {
                    CoreError::format(
                        path,
                        format!("image {}", im.id),
                        format!("unknown camera id {}", im.camera_id),
                    )
                })?;
            let k = cam
                .to_pinhole()
                .map_err(|m| CoreError::format(path, format!("camera {}", cam.id), m))?;
            let r = qvec_to_rotation(im.qvec);
            let mut m = Matrix3x4::zeros();
            m.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
            m.set_column(3, &Vector3::from(im.tvec));
            cams.cam_from_world.push(m);
            cams.intrinsics.push(k);
            names.push(im.name.clone());
        }
        Ok((cams, names))
    }
}

// ------------------------------------------------------------------------------------------
// Writing
// ------------------------------------------------------------------------------------------

/// Writes `model` into `dir` (`cameras`, `images`, `points3D`; `.bin` unless `text`). Only
/// `SIMPLE_PINHOLE` / `PINHOLE` cameras are written; each file is atomic.
pub fn write_colmap(dir: &Path, model: &ColmapModel, text: bool) -> Result<()> {
    for c in &model.cameras {
        if !matches!(
            c.model,
            ColmapCameraModel::SimplePinhole | ColmapCameraModel::Pinhole
        ) || c.params.len() != c.model.num_params()
        {
            return Err(CoreError::format(
                dir,
                format!("camera {}", c.id),
                "the writer emits SIMPLE_PINHOLE / PINHOLE with the right parameter count only",
            ));
        }
    }
    for im in &model.images {
        if im.name.is_empty()
            || im.name.contains(['\n', '\0'])
            || (text && im.name.contains(char::is_whitespace))
        {
            return Err(CoreError::format(
                dir,
                format!("image {}", im.id),
                format!("image name {:?} cannot be written", im.name),
            ));
        }
    }
    let ext = if text { "txt" } else { "bin" };
    let p = |n: &str| dir.join(format!("{n}.{ext}"));
    if text {
        write_atomic(&p("cameras"), |w| cameras_txt(w, model))?;
        write_atomic(&p("images"), |w| images_txt(w, model))?;
        write_atomic(&p("points3D"), |w| points_txt(w, model))
    } else {
        write_atomic(&p("cameras"), |w| cameras_bin(w, model))?;
        write_atomic(&p("images"), |w| images_bin(w, model))?;
        write_atomic(&p("points3D"), |w| points_bin(w, model))
    }
}

fn cameras_bin(w: &mut dyn Write, m: &ColmapModel) -> std::io::Result<()> {
    w.write_all(&(m.cameras.len() as u64).to_le_bytes())?;
    for c in &m.cameras {
        w.write_all(&c.id.to_le_bytes())?;
        w.write_all(&c.model.id().to_le_bytes())?;
        w.write_all(&c.width.to_le_bytes())?;
        w.write_all(&c.height.to_le_bytes())?;
        for p in &c.params {
            w.write_all(&p.to_le_bytes())?;
        }
    }
    Ok(())
}

fn images_bin(w: &mut dyn Write, m: &ColmapModel) -> std::io::Result<()> {
    w.write_all(&(m.images.len() as u64).to_le_bytes())?;
    for im in &m.images {
        w.write_all(&im.id.to_le_bytes())?;
        for v in im.qvec.iter().chain(&im.tvec) {
            w.write_all(&v.to_le_bytes())?;
        }
        w.write_all(&im.camera_id.to_le_bytes())?;
        w.write_all(im.name.as_bytes())?;
        w.write_all(&[0])?;
        w.write_all(&(im.points2d.len() as u64).to_le_bytes())?;
        for p in &im.points2d {
            w.write_all(&p.xy[0].to_le_bytes())?;
            w.write_all(&p.xy[1].to_le_bytes())?;
            w.write_all(&p.point3d_id.unwrap_or(INVALID_POINT3D_ID).to_le_bytes())?;
        }
    }
    Ok(())
}

fn points_bin(w: &mut dyn Write, m: &ColmapModel) -> std::io::Result<()> {
    w.write_all(&(m.points3d.len() as u64).to_le_bytes())?;
    for p in &m.points3d {
        w.write_all(&p.id.to_le_bytes())?;
        for v in &p.xyz {
            w.write_all(&v.to_le_bytes())?;
        }
        w.write_all(&p.rgb)?;
        w.write_all(&p.error.to_le_bytes())?;
        w.write_all(&(p.track.len() as u64).to_le_bytes())?;
        for (img, idx) in &p.track {
            w.write_all(&img.to_le_bytes())?;
            w.write_all(&idx.to_le_bytes())?;
        }
    }
    Ok(())
}

/// `{:?}` of f64 prints the shortest representation that round-trips exactly.
fn f(v: f64) -> String {
    format!("{v:?}")
}

fn cameras_txt(w: &mut dyn Write, m: &ColmapModel) -> std::io::Result<()> {
    writeln!(w, "# Camera list with one line of data per camera:")?;
    writeln!(w, "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]")?;
    writeln!(w, "# Number of cameras: {}", m.cameras.len())?;
    for c in &m.cameras {
        let params: Vec<String> = c.params.iter().map(|&v| f(v)).collect();
        writeln!(
            w,
            "{} {} {} {} {}",
            c.id,
            c.model.name(),
            c.width,
            c.height,
            params.join(" ")
        )?;
    }
    Ok(())
}

fn images_txt(w: &mut dyn Write, m: &ColmapModel) -> std::io::Result<()> {
    let n_obs: usize = m.images.iter().map(|i| i.points2d.len()).sum();
    writeln!(w, "# Image list with two lines of data per image:")?;
    writeln!(
        w,
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME"
    )?;
    writeln!(w, "#   POINTS2D[] as (X, Y, POINT3D_ID)")?;
    writeln!(
        w,
        "# Number of images: {}, mean observations per image: {}",
        m.images.len(),
        if m.images.is_empty() {
            0.0
        } else {
            n_obs as f64 / m.images.len() as f64
        }
    )?;
    for im in &m.images {
        let q: Vec<String> = im.qvec.iter().chain(&im.tvec).map(|&v| f(v)).collect();
        writeln!(w, "{} {} {} {}", im.id, q.join(" "), im.camera_id, im.name)?;
        let pts: Vec<String> = im
            .points2d
            .iter()
            .map(|p| {
                format!(
                    "{} {} {}",
                    f(p.xy[0]),
                    f(p.xy[1]),
                    p.point3d_id.map_or("-1".to_string(), |i| i.to_string())
                )
            })
            .collect();
        writeln!(w, "{}", pts.join(" "))?;
    }
    Ok(())
}

fn points_txt(w: &mut dyn Write, m: &ColmapModel) -> std::io::Result<()> {
    writeln!(w, "# 3D point list with one line of data per point:")?;
    writeln!(
        w,
        "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)"
    )?;
    writeln!(w, "# Number of points: {}", m.points3d.len())?;
    for p in &m.points3d {
        let track: Vec<String> = p.track.iter().map(|(a, b)| format!("{a} {b}")).collect();
        let sep = if track.is_empty() { "" } else { " " };
        writeln!(
            w,
            "{} {} {} {} {} {} {} {}{sep}{}",
            p.id,
            f(p.xyz[0]),
            f(p.xyz[1]),
            f(p.xyz[2]),
            p.rgb[0],
            p.rgb[1],
            p.rgb[2],
            f(p.error),
            track.join(" ")
        )?;
    }
    Ok(())
}

// ------------------------------------------------------------------------------------------
// Reading
// ------------------------------------------------------------------------------------------

/// Reads a COLMAP model from `dir` (binary preferred when both `cameras.bin` and
/// `cameras.txt` exist). Errors name the file, the record and the problem.
pub fn read_colmap(dir: &Path) -> Result<ColmapModel> {
    let bin = ["cameras", "images", "points3D"].map(|n| dir.join(format!("{n}.bin")));
    let txt = ["cameras", "images", "points3D"].map(|n| dir.join(format!("{n}.txt")));
    if bin[0].is_file() {
        let [c, i, p] = bin;
        Ok(ColmapModel {
            cameras: read_cameras_bin(&c)?,
            images: read_images_bin(&i)?,
            points3d: read_points_bin(&p)?,
        })
    } else if txt[0].is_file() {
        let [c, i, p] = txt;
        Ok(ColmapModel {
            cameras: read_cameras_txt(&c)?,
            images: read_images_txt(&i)?,
            points3d: read_points_txt(&p)?,
        })
    } else {
        Err(CoreError::format(
            dir,
            "",
            "no COLMAP model (cameras.bin or cameras.txt) in this directory",
        ))
    }
}

/// Little-endian cursor with errors naming the file and the record.
struct Cur {
    path: PathBuf,
    b: Vec<u8>,
    pos: usize,
}

impl Cur {
    fn open(path: &Path) -> Result<Self> {
        Ok(Self {
            path: path.to_path_buf(),
            b: std::fs::read(path).map_err(|e| CoreError::io(path, e))?,
            pos: 0,
        })
    }
    fn take(&mut self, n: usize, what: &str) -> Result<&[u8]> {
        let s = self
            .b
            .get(self.pos..self.pos.saturating_add(n))
            .ok_or_else(|| {
                CoreError::format(
                    &self.path,
                    what,
                    format!("truncated file at byte {}", self.pos),
                )
            })?;
        self.pos += n;
        Ok(s)
    }
    fn arr<const N: usize>(&mut self, what: &str) -> Result<[u8; N]> {
        let s = self.take(N, what)?;
        let mut a = [0u8; N];
        a.copy_from_slice(s);
        Ok(a)
    }
    fn u32(&mut self, what: &str) -> Result<u32> {
        Ok(u32::from_le_bytes(self.arr(what)?))
    }
    fn i32(&mut self, what: &str) -> Result<i32> {
        Ok(i32::from_le_bytes(self.arr(what)?))
    }
    fn u64(&mut self, what: &str) -> Result<u64> {
        Ok(u64::from_le_bytes(self.arr(what)?))
    }
    fn f64(&mut self, what: &str) -> Result<f64> {
        Ok(f64::from_le_bytes(self.arr(what)?))
    }
    /// A count whose records need at least `min_rec` bytes each: bounded by the remaining bytes.
    fn count(&mut self, min_rec: usize, what: &str) -> Result<usize> {
        let n = self.u64(what)?;
        let left = (self.b.len() - self.pos) as u64;
        if n.saturating_mul(min_rec as u64) > left {
            return Err(CoreError::format(
                &self.path,
                what,
                format!(
                    "count {n} exceeds what the remaining {left} bytes can hold (truncated or corrupt)"
                ),
            ));
        }
        Ok(n as usize)
    }
    fn done(&self) -> Result<()> {
        if self.pos != self.b.len() {
            return Err(CoreError::format(
                &self.path,
                "",
                format!(
                    "{} trailing bytes after the last record",
                    self.b.len() - self.pos
                ),
            ));
        }
        Ok(())
    }
    fn err(&self, what: &str, m: impl Into<String>) -> CoreError {
        CoreError::format(&self.path, what, m)
    }
}

fn read_cameras_bin(path: &Path) -> Result<Vec<ColmapCamera>> {
    let mut c = Cur::open(path)?;
    let n = c.count(24, "num_cameras")?;
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let what = format!("camera #{i}");
        let id = c.u32(&what)?;
        let mid = c.i32(&what)?;
        let model = ColmapCameraModel::from_id(mid).ok_or_else(|| {
            c.err(
                &what,
                format!("unsupported camera model id {mid} (supported: 0-6)"),
            )
        })?;
        let width = c.u64(&what)?;
        let height = c.u64(&what)?;
        let params = (0..model.num_params())
            .map(|_| c.f64(&what))
            .collect::<Result<Vec<_>>>()?;
        out.push(ColmapCamera {
            id,
            model,
            width,
            height,
            params,
        });
    }
    c.done()?;
    Ok(out)
}

fn read_images_bin(path: &Path) -> Result<Vec<ColmapImage>> {
    let mut c = Cur::open(path)?;
    let n = c.count(69, "num_images")?;
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let what = format!("image #{i}");
        let id = c.u32(&what)?;
        let mut v = [0.0; 7];
        for x in &mut v {
            *x = c.f64(&what)?;
        }
        let camera_id = c.u32(&what)?;
        let rest = c.b.get(c.pos..).unwrap_or_default();
        let nul = rest
            .iter()
            .position(|&b| b == 0)
            .ok_or_else(|| c.err(&what, "unterminated image name"))?;
        let name = String::from_utf8(rest[..nul].to_vec())
            .map_err(|_| c.err(&what, "image name is not UTF-8"))?;
        c.pos += nul + 1;
        let np = c.count(24, &what)?;
        let mut points2d = Vec::with_capacity(np);
        for _ in 0..np {
            let xy = [c.f64(&what)?, c.f64(&what)?];
            let pid = c.u64(&what)?;
            points2d.push(ColmapPoint2D {
                xy,
                point3d_id: (pid != INVALID_POINT3D_ID).then_some(pid),
            });
        }
        out.push(ColmapImage {
            id,
            qvec: [v[0], v[1], v[2], v[3]],
            tvec: [v[4], v[5], v[6]],
            camera_id,
            name,
            points2d,
        });
    }
    c.done()?;
    Ok(out)
}

fn read_points_bin(path: &Path) -> Result<Vec<ColmapPoint3D>> {
    let mut c = Cur::open(path)?;
    let n = c.count(51, "num_points")?;
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let what = format!("point #{i}");
        let id = c.u64(&what)?;
        let xyz = [c.f64(&what)?, c.f64(&what)?, c.f64(&what)?];
        let rgb: [u8; 3] = c.arr(&what)?;
        let error = c.f64(&what)?;
        let nt = c.count(8, &what)?;
        let track = (0..nt)
            .map(|_| Ok((c.u32(&what)?, c.u32(&what)?)))
            .collect::<Result<Vec<_>>>()?;
        out.push(ColmapPoint3D {
            id,
            xyz,
            rgb,
            error,
            track,
        });
    }
    c.done()?;
    Ok(out)
}

/// Data lines of a text file: `(line number, trimmed line)`, comments removed; blank lines
/// are kept (images.txt needs them) and filtered by the callers.
fn text_lines(path: &Path) -> Result<Vec<(usize, String)>> {
    let s = std::fs::read_to_string(path).map_err(|e| CoreError::io(path, e))?;
    Ok(s.lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim().to_string()))
        .filter(|(_, l)| !l.starts_with('#'))
        .collect())
}

fn num<T: std::str::FromStr>(
    path: &Path,
    line: usize,
    tok: Option<&&str>,
    what: &str,
) -> Result<T> {
    let t = tok.ok_or_else(|| {
        CoreError::format(path, format!("line {line}"), format!("missing {what}"))
    })?;
    t.parse::<T>()
        .map_err(|_| CoreError::format(path, format!("line {line}"), format!("bad {what} '{t}'")))
}

fn read_cameras_txt(path: &Path) -> Result<Vec<ColmapCamera>> {
    let mut out = Vec::new();
    for (ln, l) in text_lines(path)?.into_iter().filter(|(_, l)| !l.is_empty()) {
        let t: Vec<&str> = l.split_whitespace().collect();
        let id = num(path, ln, t.first(), "CAMERA_ID")?;
        let mname = t.get(1).copied().unwrap_or_default();
        let model = ColmapCameraModel::from_name(mname)
            .ok_or_else(|| CoreError::format(path, format!("line {ln}"), format!("unsupported camera model '{mname}' (supported: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, OPENCV_FISHEYE, FULL_OPENCV)")))?;
        let width = num(path, ln, t.get(2), "WIDTH")?;
        let height = num(path, ln, t.get(3), "HEIGHT")?;
        if t.len() != 4 + model.num_params() {
            return Err(CoreError::format(
                path,
                format!("line {ln}"),
                format!(
                    "{} expects {} parameters, found {}",
                    model.name(),
                    model.num_params(),
                    t.len().saturating_sub(4)
                ),
            ));
        }
        let params = (4..t.len())
            .map(|i| num::<f64>(path, ln, t.get(i), "parameter"))
            .collect::<Result<Vec<_>>>()?;
        out.push(ColmapCamera {
            id,
            model,
            width,
            height,
            params,
        });
    }
    Ok(out)
}

fn read_images_txt(path: &Path) -> Result<Vec<ColmapImage>> {
    let lines = text_lines(path)?;
    let mut out = Vec::new();
    let mut it = lines.into_iter();
    while let Some((ln, l)) = it.next() {
        if l.is_empty() {
            continue;
        }
        let t: Vec<&str> = l.split_whitespace().collect();
        if t.len() < 10 {
            return Err(CoreError::format(
                path,
                format!("line {ln}"),
                "image line needs IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME",
            ));
        }
        let id = num(path, ln, t.first(), "IMAGE_ID")?;
        let mut v = [0.0; 7];
        for (k, x) in v.iter_mut().enumerate() {
            *x = num(path, ln, t.get(1 + k), "pose value")?;
        }
        let camera_id = num(path, ln, t.get(8), "CAMERA_ID")?;
        let name = t[9..].join(" ");
        // The next line (possibly empty or missing at EOF) holds the observations.
        let (pln, pl) = it.next().unwrap_or((ln + 1, String::new()));
        let pt: Vec<&str> = pl.split_whitespace().collect();
        if !pt.len().is_multiple_of(3) {
            return Err(CoreError::format(
                path,
                format!("line {pln}"),
                "POINTS2D line must hold (X, Y, POINT3D_ID) triples",
            ));
        }
        let mut points2d = Vec::with_capacity(pt.len() / 3);
        for k in (0..pt.len()).step_by(3) {
            let xy = [
                num(path, pln, pt.get(k), "X")?,
                num(path, pln, pt.get(k + 1), "Y")?,
            ];
            let pid: i64 = num(path, pln, pt.get(k + 2), "POINT3D_ID")?;
            points2d.push(ColmapPoint2D {
                xy,
                point3d_id: u64::try_from(pid).ok(),
            });
        }
        out.push(ColmapImage {
            id,
            qvec: [v[0], v[1], v[2], v[3]],
            tvec: [v[4], v[5], v[6]],
            camera_id,
            name,
            points2d,
        });
    }
    Ok(out)
}

fn read_points_txt(path: &Path) -> Result<Vec<ColmapPoint3D>> {
    let mut out = Vec::new();
    for (ln, l) in text_lines(path)?.into_iter().filter(|(_, l)| !l.is_empty()) {
        let t: Vec<&str> = l.split_whitespace().collect();
        if t.len() < 8 || !(t.len() - 8).is_multiple_of(2) {
            return Err(CoreError::format(
                path,
                format!("line {ln}"),
                "point line needs POINT3D_ID X Y Z R G B ERROR and (IMAGE_ID, POINT2D_IDX) pairs",
            ));
        }
        let id = num(path, ln, t.first(), "POINT3D_ID")?;
        let xyz = [
            num(path, ln, t.get(1), "X")?,
            num(path, ln, t.get(2), "Y")?,
            num(path, ln, t.get(3), "Z")?,
        ];
        let rgb = [
            num(path, ln, t.get(4), "R")?,
            num(path, ln, t.get(5), "G")?,
            num(path, ln, t.get(6), "B")?,
        ];
        let error = num(path, ln, t.get(7), "ERROR")?;
        let track = (8..t.len())
            .step_by(2)
            .map(|k| {
                Ok((
                    num(path, ln, t.get(k), "IMAGE_ID")?,
                    num(path, ln, t.get(k + 1), "POINT2D_IDX")?,
                ))
            })
            .collect::<Result<Vec<_>>>()?;
        out.push(ColmapPoint3D {
            id,
            xyz,
            rgb,
            error,
            track,
        });
    }
    Ok(out)
}
