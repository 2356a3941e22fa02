//! The GGPT_eval raw sequence layout (`formats.md` §4) and its preprocessing to the feed-forward
//! resolution with GT unprojection (`pipeline.md` §2.1, §10.1).
//!
//! ```text
//! <seq>/images/000000.jpg, 000001.jpg, ...   RGB; names must be the zero-padded view index
//! <seq>/depths/000000.npy, ...               f32 [H, W] metric z-depth, <= 1e-5 = invalid
//! <seq>/extrinsics.npy                       [N, 4, 4] cam_from_world (OpenCV), f32 or f64
//! <seq>/intrinsics.npy                       [N, 3, 3] pixel-centre pinhole K (no skew), principal point centred
//! ```
//!
//! The official loader derives the image size from the principal point,
//! `W = int((cx + 0.5) * 2)`, `H = int((cy + 0.5) * 2)`, and asserts it equals the image size;
//! this reader applies the same rule per view.

use std::path::Path;

use nalgebra::{Matrix3, Matrix3x4, Vector3};

use crate::io::npy::{NpyArray, read_npy};
use crate::io::official::dir_name;
use crate::resize::{BilinearRounding, resize_bilinear, resize_nearest_exact};
use crate::{Cameras, CoreError, Dims, GroundTruth, Result, Scene};

/// GT depth above which a pixel is valid (`pipeline.md` §10.1, `formats.md` §4).
pub const DEPTH_VALID_MIN: f32 = 1e-5;
/// GT points are zeroed where the resized depth is `<=` this (fixture
/// `official_format/synth_room_s0/README.md`, `gt/points`).
pub const POINT_DEPTH_MIN: f32 = 1e-4;
/// Feed-forward width of VGGT (`pipeline.md` §2.1).
pub const FF_WIDTH: usize = 518;
/// Feed-forward heights are multiples of the ViT patch size.
pub const FF_PATCH: usize = 14;
/// Tolerance on the fixed entries of the GT matrices: the last row `0 0 0 1` of the extrinsics,
/// the zero skew / lower entries and the `1` of the intrinsics.
const HOMOGENEOUS_ROW_TOL: f64 = 1e-6;

/// A raw GGPT_eval sequence at its original resolution.
#[derive(Debug, Clone, PartialEq)]
pub struct RawSequence {
    /// Sequence folder name (the scene name).
    pub name: String,
    /// Number of views.
    pub n: usize,
    /// Original image height `H`.
    pub height: usize,
    /// Original image width `W`.
    pub width: usize,
    /// `[N, H, W, 3]` decoded RGB images.
    pub images: Vec<u8>,
    /// `[N, H, W]` GT z-depth in metres (`<= 1e-5` invalid).
    pub depths: Vec<f32>,
    /// GT `cam_from_world` (OpenCV, metres).
    pub cam_from_world: Vec<Matrix3x4<f64>>,
    /// GT K at the original resolution (pixel-centre convention).
    pub intrinsics: Vec<Matrix3<f64>>,
}

/// Reads and checks a raw sequence directory (see the module docs).
pub fn read_raw_sequence(dir: &Path) -> Result<RawSequence> {
    let names = image_names(dir)?;
    let n = names.len();
    let ext_p = dir.join("extrinsics.npy");
    let int_p = dir.join("intrinsics.npy");
    let cam_from_world = read_extrinsics(&ext_p, n)?;
    let intrinsics = read_intrinsics(&int_p, n)?;
    let (mut images, mut depths) = (Vec::new(), Vec::new());
    let (mut height, mut width) = (0, 0);
    for (i, name) in names.iter().enumerate() {
        let ip = dir.join("images").join(name);
        let bytes = std::fs::read(&ip).map_err(|e| CoreError::io(&ip, e))?;
        let img = image::load_from_memory(&bytes)
            .map_err(|e| CoreError::format(&ip, "", format!("cannot decode image: {e}")))?
            .to_rgb8();
        let (w, h) = (img.width() as usize, img.height() as usize);
        if i == 0 {
            (height, width) = (h, w);
        } else if (h, w) != (height, width) {
            return Err(CoreError::format(
                &ip,
                "",
                format!(
                    "image is {w}x{h}, view 0 is {width}x{height} (all views must share one size)"
                ),
            ));
        }
        check_centred(&int_p, i, intrinsics.get(i), h, w)?;
        images.extend_from_slice(img.as_raw());
        let dp = dir.join("depths").join(name.replace(".jpg", ".npy"));
        depths.extend(read_depth(&dp, h, w)?);
    }
    Ok(RawSequence {
        name: dir_name(dir),
        n,
        height,
        width,
        images,
        depths,
        cam_from_world,
        intrinsics,
    })
}

/// `images/` must hold exactly `000000.jpg .. {N-1:06}.jpg` (poses are looked up by index).
fn image_names(dir: &Path) -> Result<Vec<String>> {
    let idir = dir.join("images");
    let rd = std::fs::read_dir(&idir).map_err(|e| CoreError::io(&idir, e))?;
    let mut names = Vec::new();
    for e in rd {
        let e = e.map_err(|e| CoreError::io(&idir, e))?;
        names.push(e.file_name().to_string_lossy().into_owned());
    }
    names.sort();
    if names.is_empty() {
        return Err(CoreError::format(&idir, "", "no images"));
    }
    for (i, name) in names.iter().enumerate() {
        let want = format!("{i:06}.jpg");
        if *name != want {
            return Err(CoreError::format(
                idir.join(name),
                "",
                format!("image {i} must be named {want} (views are matched to poses by index)"),
            ));
        }
    }
    Ok(names)
}

/// A finite `<f4` / `<f8` array of exactly `shape` (`[N, r, c]`, one matrix per view), as f64.
/// A non-finite entry is reported with its view (the key) and its row / column.
fn float_array(path: &Path, a: &NpyArray, shape: &[usize; 3]) -> Result<Vec<f64>> {
    if a.shape != shape {
        return Err(CoreError::format(
            path,
            "",
            format!("wrong shape {:?}, expected {shape:?}", a.shape),
        ));
    }
    let v = a.to_f64().ok_or_else(|| {
        CoreError::format(
            path,
            "",
            format!("wrong dtype {}, expected <f4 or <f8", a.data.descr()),
        )
    })?;
    if let Some(i) = v.iter().position(|x| !x.is_finite()) {
        let (rows, cols) = (shape[1], shape[2]);
        let (view, row, col) = (i / (rows * cols), i / cols % rows, i % cols);
        return Err(CoreError::format(
            path,
            format!("view {view}"),
            format!("non-finite value {} at row {row}, column {col}", v[i]),
        ));
    }
    Ok(v)
}

fn read_extrinsics(path: &Path, n: usize) -> Result<Vec<Matrix3x4<f64>>> {
    let v = float_array(path, &read_npy(path)?, &[n, 4, 4])?;
    let mut out = Vec::with_capacity(n);
    for (i, m) in v.chunks_exact(16).enumerate() {
        let last = [m[12], m[13], m[14], m[15] - 1.0];
        if last.iter().any(|x| x.abs() > HOMOGENEOUS_ROW_TOL) {
            return Err(CoreError::format(
                path,
                format!("view {i}"),
                "last row of cam_from_world is not 0 0 0 1",
            ));
        }
        out.push(Matrix3x4::from_row_slice(&m[..12]));
    }
    Ok(out)
}

fn read_intrinsics(path: &Path, n: usize) -> Result<Vec<Matrix3<f64>>> {
    let v = float_array(path, &read_npy(path)?, &[n, 3, 3])?;
    let mut out = Vec::with_capacity(n);
    for (i, m) in v.chunks_exact(9).enumerate() {
        // Pinhole without skew: everything but fx, cx, fy, cy is 0 0 / 0 0 1 (the unprojection
        // and the resize to ff resolution use only fx, fy, cx, cy).
        let fixed = [(1, 0.0), (3, 0.0), (6, 0.0), (7, 0.0), (8, 1.0)];
        if fixed
            .iter()
            .any(|&(j, want)| (m[j] - want).abs() > HOMOGENEOUS_ROW_TOL)
        {
            return Err(CoreError::format(
                path,
                format!("view {i}"),
                "not a pinhole K [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (skew or last row)",
            ));
        }
        out.push(Matrix3::from_row_slice(m));
    }
    Ok(out)
}

/// Official rule: `int((cx + 0.5) * 2) == W` and `int((cy + 0.5) * 2) == H`.
fn check_centred(
    path: &Path,
    i: usize,
    k: Option<&Matrix3<f64>>,
    h: usize,
    w: usize,
) -> Result<()> {
    let k = k.ok_or_else(|| CoreError::format(path, format!("view {i}"), "missing intrinsics"))?;
    let (cw, ch) = (
        ((k[(0, 2)] + 0.5) * 2.0).trunc(),
        ((k[(1, 2)] + 0.5) * 2.0).trunc(),
    );
    if cw != w as f64 || ch != h as f64 {
        return Err(CoreError::format(
            path,
            format!("view {i}"),
            format!(
                "principal point ({}, {}) implies a {cw}x{ch} image, the image is {w}x{h} (principal point must be centred)",
                k[(0, 2)],
                k[(1, 2)]
            ),
        ));
    }
    if !(k[(0, 0)] > 0.0 && k[(1, 1)] > 0.0) {
        return Err(CoreError::format(
            path,
            format!("view {i}"),
            "focal lengths must be positive",
        ));
    }
    Ok(())
}

fn read_depth(path: &Path, h: usize, w: usize) -> Result<Vec<f32>> {
    let a = read_npy(path)?;
    if a.shape != [h, w] {
        return Err(CoreError::format(
            path,
            "",
            format!(
                "depth shape {:?} differs from the image size [{h}, {w}]",
                a.shape
            ),
        ));
    }
    // Spec: float32; float64 is accepted too (rounded to f32, like the official float cast).
    let v = a.to_f32().ok_or_else(|| {
        CoreError::format(
            path,
            "",
            format!("wrong dtype {}, expected <f4 (or <f8)", a.data.descr()),
        )
    })?;
    if let Some(i) = v.iter().position(|x| !x.is_finite()) {
        return Err(CoreError::format(
            path,
            "",
            format!(
                "non-finite depth {} at row {}, column {}",
                v[i],
                i / w,
                i % w
            ),
        ));
    }
    Ok(v)
}

/// Python's `round` (half to even) of a non-negative value.
fn round_half_even(x: f64) -> f64 {
    let r = x.round();
    if (x - x.trunc()).abs() == 0.5 && r % 2.0 != 0.0 {
        r - 1.0
    } else {
        r
    }
}

/// Feed-forward size `(h, w)` for an `H x W` input: `w = width`,
/// `h = round(H * (width / W) / 14) * 14` (Python rounding, `pipeline.md` §2.1).
/// A zero `width_in` gives `(0, width)`.
pub fn ff_size(height: usize, width_in: usize, width: usize) -> (usize, usize) {
    if width_in == 0 {
        return (0, width);
    }
    let patches =
        round_half_even(height as f64 * (width as f64 / width_in as f64) / FF_PATCH as f64)
            as usize;
    (patches.max(1).saturating_mul(FF_PATCH), width)
}

/// Resizes a raw sequence to the feed-forward resolution (`width` wide, usually
/// [`FF_WIDTH`]) and unprojects GT: images bilinear (`align_corners = false`, no antialias,
/// `u8 / 255` first), depth nearest-exact, mask `depth > 1e-5`, `fx *= w / W`, `fy *= h / H`,
/// principal point `((w-1)/2, (h-1)/2)`, points `world_from_cam(D K^-1 (x, y, 1))` in the GT
/// world frame (metres), zero where `D <= 1e-4`. Returns a scene with images and GT only.
pub fn prepare_ff_resolution(raw: &RawSequence, width: usize) -> Result<Scene> {
    let (hin, win) = (raw.height, raw.width);
    if raw.n == 0 || hin == 0 || win == 0 || width == 0 {
        return Err(CoreError::Invalid(format!(
            "raw sequence '{}' is empty or width is 0",
            raw.name
        )));
    }
    let (px, n) = (hin * win, raw.n);
    let sizes = [
        ("images", raw.images.len(), 3 * n * px),
        ("depths", raw.depths.len(), n * px),
        ("cam_from_world", raw.cam_from_world.len(), n),
        ("intrinsics", raw.intrinsics.len(), n),
    ];
    for (what, got, want) in sizes {
        if got != want {
            return Err(CoreError::Invalid(format!(
                "raw sequence '{}': {what} has {got} entries, expected {want} ({n} views of {win}x{hin})",
                raw.name
            )));
        }
    }
    let (h, w) = ff_size(hin, win, width);
    let dims = Dims { n: raw.n, h, w };
    let (mut images, mut depth, mut intrinsics) = (Vec::new(), Vec::new(), Vec::new());
    for v in 0..raw.n {
        let img: Vec<f32> = raw
            .images
            .get(v * hin * win * 3..(v + 1) * hin * win * 3)
            .unwrap_or_default()
            .iter()
            .map(|&b| f32::from(b) / 255.0)
            .collect();
        images.extend(resize_bilinear(
            &img,
            hin,
            win,
            3,
            h,
            w,
            BilinearRounding::Separable,
        )?);
        let d = raw
            .depths
            .get(v * hin * win..(v + 1) * hin * win)
            .unwrap_or_default();
        depth.extend(resize_nearest_exact(d, hin, win, h, w));
        let k0 = raw
            .intrinsics
            .get(v)
            .ok_or_else(|| CoreError::Invalid(format!("view {v}: missing intrinsics")))?;
        let mut k = *k0;
        k[(0, 0)] *= w as f64 / win as f64;
        k[(1, 1)] *= h as f64 / hin as f64;
        k[(0, 2)] = (w as f64 - 1.0) / 2.0;
        k[(1, 2)] = (h as f64 - 1.0) / 2.0;
        intrinsics.push(k);
    }
    let cameras = Cameras {
        cam_from_world: raw.cam_from_world.clone(),
        intrinsics,
    };
    let mask: Vec<bool> = depth.iter().map(|&d| d > DEPTH_VALID_MIN).collect();
    let points = unproject(&dims, &depth, &cameras);
    let gt = GroundTruth {
        points,
        mask,
        depth: Some(depth),
        cameras,
    };
    let scene = Scene {
        name: raw.name.clone(),
        dims,
        images,
        gt: Some(gt),
        ff: None,
        sfm: None,
        matches: Vec::new(),
    };
    scene.validate()?;
    Ok(scene)
}

/// GT world points `[N, h, w, 3]` from z-depth (ff pixels, pixel-centre convention), zero where
/// the depth is `<= 1e-4`.
pub fn unproject(d: &Dims, depth: &[f32], cams: &Cameras) -> Vec<f32> {
    let mut out = vec![0.0f32; 3 * d.pixels()];
    for v in 0..d.n.min(cams.len()) {
        let Some(&k) = cams.intrinsics.get(v) else {
            break;
        };
        let (r, t) = (cams.rotation(v), cams.translation(v));
        for y in 0..d.h {
            for x in 0..d.w {
                let p = d.index(v, y, x);
                let z = depth.get(p).copied().unwrap_or(0.0);
                if z <= POINT_DEPTH_MIN {
                    continue;
                }
                let z = f64::from(z);
                let xc = Vector3::new(
                    (x as f64 - k[(0, 2)]) / k[(0, 0)] * z,
                    (y as f64 - k[(1, 2)]) / k[(1, 1)] * z,
                    z,
                );
                let xw = r.transpose() * (xc - t);
                if let Some(o) = out.get_mut(3 * p..3 * p + 3) {
                    o.copy_from_slice(&[xw.x as f32, xw.y as f32, xw.z as f32]);
                }
            }
        }
    }
    out
}
