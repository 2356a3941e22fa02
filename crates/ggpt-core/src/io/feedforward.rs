//! Readers of feed-forward outputs (`formats.md` §5.2, `docs/formats.md` "Feed-forward
//! outputs"): VGGT's `predictions.npz` / predictions dict, MapAnything, Pi3 and the project's own
//! `ff.npz`, from [`NamedArrays`]. One implementation for the command lines (`--ff FILE`) and the
//! Python package (`FeedForward.from_vggt`, ...), which hands its numpy arrays over as named
//! arrays.
//!
//! Every reader returns the same [`FeedForwardInput`]: points `[N, h, w, 3]` (the model's world
//! frame), confidence `[N, h, w]` (≥ 1 where the model uses VGGT's `1 + exp` scale),
//! `cam_from_world` (OpenCV axes: x right, y down, z forward), K in ff pixels with the
//! pixel-centre convention (top-left pixel centre = `(0, 0)`; the principal point as the model
//! gives it, e.g. VGGT's `(w/2, h/2)`), and the images `[N, h, w, 3]` in `[0, 1]` when the arrays
//! hold them. f32 and f64 arrays are accepted; a leading batch dimension of 1 is removed and any
//! other batch is an error; non-finite values are errors naming the array and the index.

use std::path::Path;

use nalgebra::{Matrix3, Matrix3x4, Vector3};

use crate::io::arrays::NamedArrays;
use crate::io::npy::NpyData;
use crate::{Cameras, CoreError, Dims, FeedForward, Result};

/// The layouts the readers know, detected from the array names ([`detect_format`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum FfFormat {
    /// VGGT `predictions` (`extrinsic`, `intrinsic`, `depth` + `depth_conf` and/or
    /// `world_points` + `world_points_conf`, optional `images` `[S, 3, H, W]`).
    Vggt,
    /// MapAnything outputs stacked over the views (`pts3d`, `conf`, `intrinsics`,
    /// `camera_poses` camera-to-world, optional `img_no_norm`).
    MapAnything,
    /// Pi3 outputs (`points` world frame, `conf` logits, `camera_poses` camera-to-world,
    /// optional `local_points`, `images`); intrinsics given or estimated.
    Pi3,
    /// The project's `ff.npz` (`points`, `conf`, `cam_from_world`, `K`, optional `images`).
    Ggpt,
}

impl FfFormat {
    /// Name as written in files and messages.
    pub fn name(self) -> &'static str {
        match self {
            FfFormat::Vggt => "vggt",
            FfFormat::MapAnything => "mapanything",
            FfFormat::Pi3 => "pi3",
            FfFormat::Ggpt => "ggpt",
        }
    }

    /// Parses [`FfFormat::name`].
    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "vggt" => Ok(FfFormat::Vggt),
            "mapanything" => Ok(FfFormat::MapAnything),
            "pi3" => Ok(FfFormat::Pi3),
            "ggpt" => Ok(FfFormat::Ggpt),
            other => Err(CoreError::Invalid(format!(
                "unknown feed-forward format {other:?} (expected vggt, mapanything, pi3 or ggpt)"
            ))),
        }
    }
}

/// Which VGGT head gives the points.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum VggtBranch {
    /// The official GGPT demo's default (`vggt-depth`): `depth` unprojected with the predicted
    /// cameras, confidence `depth_conf`.
    #[default]
    Depth,
    /// The point head (`vggt-point`): `world_points`, confidence `world_points_conf`.
    Points,
}

impl VggtBranch {
    /// Parses `depth` / `points`.
    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "depth" => Ok(VggtBranch::Depth),
            "points" | "point" => Ok(VggtBranch::Points),
            other => Err(CoreError::Invalid(format!(
                "unknown VGGT branch {other:?} (expected depth or points)"
            ))),
        }
    }
}

/// Options of [`read_feed_forward`].
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FfReadOptions {
    /// The layout; `None` detects it from the array names.
    pub format: Option<FfFormat>,
    /// VGGT's branch (default: depth).
    pub branch: VggtBranch,
    /// Pi3: intrinsics per view (ff pixels, pixel-centre convention); `None` estimates them
    /// ([`estimate_focal`]).
    pub intrinsics: Option<Vec<Matrix3<f64>>>,
}

/// A feed-forward prediction read from named arrays.
#[derive(Debug, Clone, PartialEq)]
pub struct FeedForwardInput {
    /// The layout that was read.
    pub format: FfFormat,
    /// Views and ff resolution.
    pub dims: Dims,
    /// Points, confidence and cameras.
    pub ff: FeedForward,
    /// `[N, h, w, 3]` RGB in `[0, 1]`, when the arrays hold the images.
    pub images: Option<Vec<f32>>,
}

/// Keys each layout needs, for detection and for the error listing them.
const SIGNATURES: [(FfFormat, &[&str], &str); 4] = [
    (
        FfFormat::Ggpt,
        &["points", "conf", "cam_from_world", "K"],
        "ggpt ff.npz: points, conf, cam_from_world, K [, images]",
    ),
    (
        FfFormat::Vggt,
        &["extrinsic", "intrinsic"],
        "VGGT: extrinsic, intrinsic, depth + depth_conf and/or world_points + world_points_conf [, images]",
    ),
    (
        FfFormat::MapAnything,
        &["pts3d", "camera_poses"],
        "MapAnything: pts3d, conf, intrinsics, camera_poses [, img_no_norm]",
    ),
    (
        FfFormat::Pi3,
        &["points", "camera_poses"],
        "Pi3: points, conf, camera_poses [, local_points, images]",
    ),
];

/// The layout of `arrays`, from their names; an error lists the keys found and each layout's.
pub fn detect_format(arrays: &NamedArrays) -> Result<FfFormat> {
    SIGNATURES
        .iter()
        .find(|(_, keys, _)| keys.iter().all(|k| arrays.has(k)))
        .map(|(f, _, _)| *f)
        .ok_or_else(|| {
            let expected: Vec<&str> = SIGNATURES.iter().map(|(_, _, d)| *d).collect();
            arrays.err(
                "",
                format!(
                    "not a known feed-forward layout: found keys [{}]; expected one of: {}",
                    arrays.keys().join(", "),
                    expected.join("; ")
                ),
            )
        })
}

/// Reads an `.npz` of feed-forward outputs (any layout of [`FfFormat`]).
pub fn read_feed_forward_file(path: &Path, opts: &FfReadOptions) -> Result<FeedForwardInput> {
    read_feed_forward(NamedArrays::open_npz(path)?, opts)
}

/// Reads feed-forward outputs from named arrays (see the module doc).
pub fn read_feed_forward(
    mut arrays: NamedArrays,
    opts: &FfReadOptions,
) -> Result<FeedForwardInput> {
    let format = match opts.format {
        Some(f) => f,
        None => detect_format(&arrays)?,
    };
    match format {
        FfFormat::Vggt => read_vggt(&mut arrays, opts.branch),
        FfFormat::MapAnything => read_mapanything(&mut arrays),
        FfFormat::Pi3 => read_pi3(&mut arrays, opts.intrinsics.as_deref()),
        FfFormat::Ggpt => read_ggpt(&mut arrays),
    }
}

/// `[N, h, w, 3]` dims of the point array `key`.
fn point_dims(a: &NamedArrays, key: &str) -> Result<Dims> {
    match a.get(key)?.shape.as_slice() {
        [n, h, w, 3] if *n > 0 && *h > 0 && *w > 0 => Ok(Dims {
            n: *n,
            h: *h,
            w: *w,
        }),
        s => Err(a.err(key, format!("wrong shape {s:?}, expected [N, h, w, 3]"))),
    }
}

/// Float values of `key` with exactly `shape` as f32 (f64 rounded), finite.
fn f32_values(a: &NamedArrays, key: &str, shape: &[usize]) -> Result<Vec<f32>> {
    let arr = a.shaped(key, shape)?;
    let v = arr.to_f32().ok_or_else(|| {
        a.err(
            key,
            format!("wrong dtype {}, expected <f4 or <f8", arr.data.descr()),
        )
    })?;
    crate::io::st::check_finite_f32(a.origin(), key, &v)?;
    Ok(v)
}

/// Confidence `[N, h, w]` (a trailing axis of 1 is accepted).
fn conf_values(a: &mut NamedArrays, key: &str, d: Dims) -> Result<Vec<f32>> {
    drop_trailing_one(a, key, 3);
    f32_values(a, key, &[d.n, d.h, d.w])
}

/// Removes a trailing axis of extent 1 from `key` when it has `rank + 1` axes.
fn drop_trailing_one(a: &mut NamedArrays, key: &str, rank: usize) {
    a.reshape_with(key, |s| {
        if s.len() == rank + 1 && s.last() == Some(&1) {
            s.pop();
        }
    });
}

/// Images `[N, h, w, 3]` from `[N, h, w, 3]` or channel-first `[N, 3, h, w]` (VGGT), u8 (÷ 255)
/// or float in `[0, 1]`.
fn image_values(a: &NamedArrays, key: &str, d: Dims) -> Result<Vec<f32>> {
    let arr = a.get(key)?;
    let values: Vec<f32> = match &arr.data {
        NpyData::U8(v) => v.iter().map(|&b| f32::from(b) / 255.0).collect(),
        _ => arr.to_f32().ok_or_else(|| {
            a.err(
                key,
                format!(
                    "wrong dtype {}, expected |u1 or a float in [0, 1]",
                    arr.data.descr()
                ),
            )
        })?,
    };
    if let Some(i) = values.iter().position(|x| !(0.0..=1.0).contains(x)) {
        return Err(a.err(
            key,
            format!("value {} at flat index {i} outside [0, 1]", values[i]),
        ));
    }
    let (n, h, w) = (d.n, d.h, d.w);
    if arr.shape == [n, h, w, 3] {
        return Ok(values);
    }
    if arr.shape == [n, 3, h, w] {
        let hw = h * w;
        let mut out = vec![0f32; 3 * n * hw];
        for v in 0..n {
            for c in 0..3 {
                for p in 0..hw {
                    out[3 * (v * hw + p) + c] = values[(v * 3 + c) * hw + p];
                }
            }
        }
        return Ok(out);
    }
    Err(a.err(
        key,
        format!(
            "wrong shape {:?}, expected [{n}, {h}, {w}, 3] or [{n}, 3, {h}, {w}] (the points are N={n} at {h}x{w})",
            arr.shape
        ),
    ))
}

/// `cam_from_world` from camera-to-world poses `[N, 4, 4]` (or `[N, 3, 4]`).
fn invert_poses(a: &NamedArrays, key: &str, n: usize) -> Result<Vec<Matrix3x4<f64>>> {
    Ok(a.extrinsics(key, n)?
        .iter()
        .map(|m| {
            let r = m.fixed_view::<3, 3>(0, 0).transpose();
            let t = -(r * m.column(3));
            let mut out = Matrix3x4::zeros();
            out.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
            out.set_column(3, &t);
            out
        })
        .collect())
}

/// The images under the first of `keys` present, if any.
fn optional_images(a: &NamedArrays, keys: &[&str], d: Dims) -> Result<Option<Vec<f32>>> {
    keys.iter()
        .find(|k| a.has(k))
        .map(|k| image_values(a, k, d))
        .transpose()
}

/// VGGT (`formats.md` feed-forward outputs): see [`FfFormat::Vggt`] and [`VggtBranch`].
fn read_vggt(a: &mut NamedArrays, branch: VggtBranch) -> Result<FeedForwardInput> {
    // `depth` is [S, H, W, 1] (or [S, H, W]); a leading batch of 1 comes first.
    a.squeeze_batch(&[
        ("world_points", 4),
        ("world_points_conf", 3),
        ("world_points_from_depth", 4),
        ("depth_conf", 3),
        ("extrinsic", 3),
        ("intrinsic", 3),
        ("images", 4),
        ("pose_enc", 2),
    ])?;
    if a.array("depth").is_some_and(|d| d.shape.len() == 5) {
        a.squeeze_batch(&[("depth", 4)])?;
    }
    drop_trailing_one(a, "depth", 3);
    let (points_key, conf_key) = match branch {
        VggtBranch::Depth => ("depth", "depth_conf"),
        VggtBranch::Points => ("world_points", "world_points_conf"),
    };
    for key in [points_key, conf_key] {
        if !a.has(key) {
            return Err(a.err(
                key,
                format!(
                    "missing for the VGGT {} branch (keys found: [{}]; the other branch is --ff-branch {})",
                    if branch == VggtBranch::Depth { "depth" } else { "points" },
                    a.keys().join(", "),
                    if branch == VggtBranch::Depth { "points" } else { "depth" },
                ),
            ));
        }
    }
    let d = match branch {
        VggtBranch::Points => point_dims(a, "world_points")?,
        VggtBranch::Depth => match a.get("depth")?.shape.as_slice() {
            [n, h, w] if *n > 0 && *h > 0 && *w > 0 => Dims {
                n: *n,
                h: *h,
                w: *w,
            },
            s => {
                return Err(a.err(
                    "depth",
                    format!("wrong shape {s:?}, expected [S, H, W, 1] or [S, H, W]"),
                ));
            }
        },
    };
    let cameras = Cameras {
        cam_from_world: a.extrinsics("extrinsic", d.n)?,
        intrinsics: a.intrinsics("intrinsic", d.n)?,
    };
    let conf = conf_values(a, conf_key, d)?;
    let points = match branch {
        VggtBranch::Points => f32_values(a, "world_points", &[d.n, d.h, d.w, 3])?,
        VggtBranch::Depth => {
            let depth = f32_values(a, "depth", &[d.n, d.h, d.w])?;
            unproject_depth(&depth, d, &cameras)?
        }
    };
    let images = optional_images(a, &["images"], d)?;
    Ok(FeedForwardInput {
        format: FfFormat::Vggt,
        dims: d,
        ff: FeedForward {
            points,
            conf,
            cameras,
        },
        images,
    })
}

/// World points of a depth map `[N, h, w]` (z-depth) with `cameras`, as VGGT's
/// `unproject_depth_map_to_point_map`: pixel `(x, y)` (pixel centres at integers),
/// `X_cam = z ((x - cx) / fx, (y - cy) / fy, 1)`, `X_world = Rᵀ (X_cam - t)`; computed in f64,
/// stored as f32.
pub fn unproject_depth(depth: &[f32], d: Dims, cameras: &Cameras) -> Result<Vec<f32>> {
    if depth.len() != d.pixels() || cameras.len() != d.n {
        return Err(CoreError::Invalid(format!(
            "unproject: {} depths / {} cameras for N={} h={} w={}",
            depth.len(),
            cameras.len(),
            d.n,
            d.h,
            d.w
        )));
    }
    let mut out = Vec::with_capacity(3 * d.pixels());
    for v in 0..d.n {
        let k = &cameras.intrinsics[v];
        let (fx, fy, cx, cy) = (k[(0, 0)], k[(1, 1)], k[(0, 2)], k[(1, 2)]);
        if !(fx != 0.0 && fy != 0.0) {
            return Err(CoreError::Invalid(format!(
                "unproject: view {v} has a zero focal length"
            )));
        }
        let r_t = cameras.rotation(v).transpose();
        let t = cameras.translation(v);
        for y in 0..d.h {
            for x in 0..d.w {
                let z = f64::from(depth[(v * d.h + y) * d.w + x]);
                let cam = Vector3::new((x as f64 - cx) / fx * z, (y as f64 - cy) / fy * z, z);
                let world = r_t * (cam - t);
                out.extend([world.x as f32, world.y as f32, world.z as f32]);
            }
        }
    }
    Ok(out)
}

/// MapAnything: see [`FfFormat::MapAnything`].
fn read_mapanything(a: &mut NamedArrays) -> Result<FeedForwardInput> {
    a.squeeze_batch(&[
        ("pts3d", 4),
        ("conf", 3),
        ("intrinsics", 3),
        ("camera_poses", 3),
        ("img_no_norm", 4),
    ])?;
    let d = point_dims(a, "pts3d")?;
    let points = f32_values(a, "pts3d", &[d.n, d.h, d.w, 3])?;
    let conf = conf_values(a, "conf", d)?;
    let cameras = Cameras {
        cam_from_world: invert_poses(a, "camera_poses", d.n)?,
        intrinsics: a.intrinsics("intrinsics", d.n)?,
    };
    let images = optional_images(a, &["img_no_norm", "images"], d)?;
    Ok(FeedForwardInput {
        format: FfFormat::MapAnything,
        dims: d,
        ff: FeedForward {
            points,
            conf,
            cameras,
        },
        images,
    })
}

/// Pi3: see [`FfFormat::Pi3`]. The confidence logits `c` become `1 + exp(c)` (the official GGPT
/// Pi3 wrapper), on VGGT's scale.
fn read_pi3(a: &mut NamedArrays, intrinsics: Option<&[Matrix3<f64>]>) -> Result<FeedForwardInput> {
    a.squeeze_batch(&[
        ("points", 4),
        ("local_points", 4),
        ("camera_poses", 3),
        ("images", 4),
    ])?;
    if a.array("conf").is_some_and(|c| c.shape.len() == 5) {
        a.squeeze_batch(&[("conf", 4)])?;
    }
    let d = point_dims(a, "points")?;
    let points = f32_values(a, "points", &[d.n, d.h, d.w, 3])?;
    let logits = conf_values(a, "conf", d)?;
    let conf: Vec<f32> = logits
        .iter()
        .map(|&c| 1.0 + c.exp().min(f32::MAX))
        .collect();
    let cam_from_world = invert_poses(a, "camera_poses", d.n)?;
    let intrinsics = match intrinsics {
        Some(k) if k.len() == d.n => k.to_vec(),
        Some(k) => {
            return Err(CoreError::Invalid(format!(
                "Pi3: {} intrinsics given for {} views",
                k.len(),
                d.n
            )));
        }
        None => {
            // camera-frame points: `local_points` when given, else the world points moved into
            // each camera
            let local = if a.has("local_points") {
                f32_values(a, "local_points", &[d.n, d.h, d.w, 3])?
            } else {
                to_camera_frame(&points, d, &cam_from_world)
            };
            (0..d.n)
                .map(|v| {
                    let px = d.h * d.w;
                    let f = estimate_focal(&local[3 * v * px..3 * (v + 1) * px], d.h, d.w)
                        .ok_or_else(|| {
                            a.err(
                                "points",
                                format!(
                                    "view {v}: cannot estimate the focal length (no point in front of the camera); give the intrinsics"
                                ),
                            )
                        })?;
                    let (cx, cy) = (d.w as f64 / 2.0, d.h as f64 / 2.0);
                    Ok(Matrix3::new(f, 0.0, cx, 0.0, f, cy, 0.0, 0.0, 1.0))
                })
                .collect::<Result<Vec<_>>>()?
        }
    };
    let images = optional_images(a, &["images"], d)?;
    Ok(FeedForwardInput {
        format: FfFormat::Pi3,
        dims: d,
        ff: FeedForward {
            points,
            conf,
            cameras: Cameras {
                cam_from_world,
                intrinsics,
            },
        },
        images,
    })
}

/// `[N, h, w, 3]` world points moved into each view's camera frame.
fn to_camera_frame(points: &[f32], d: Dims, cam_from_world: &[Matrix3x4<f64>]) -> Vec<f32> {
    let px = d.h * d.w;
    let mut out = Vec::with_capacity(points.len());
    for (v, m) in cam_from_world.iter().enumerate() {
        let r = m.fixed_view::<3, 3>(0, 0);
        let t = m.column(3);
        for p in points[3 * v * px..3 * (v + 1) * px].chunks_exact(3) {
            let c = r * Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])) + t;
            out.extend([c.x as f32, c.y as f32, c.z as f32]);
        }
    }
    out
}

/// The focal length (pixels) that best maps camera-frame points `[h, w, 3]` to their pixels
/// (pixel centres at integers, principal point `(w/2, h/2)` as VGGT's and Pi3's): the least
/// squares `f = Σ ((x - cx) X/Z + (y - cy) Y/Z) / Σ ((X/Z)² + (Y/Z)²)` over the points in front
/// of the camera. MoGe's `recover_focal_shift` (the official GGPT Pi3 wrapper) also solves for a
/// depth shift; Pi3's local points need none. `None` without a usable point.
pub fn estimate_focal(local: &[f32], h: usize, w: usize) -> Option<f64> {
    let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
    let (mut num, mut den) = (0.0, 0.0);
    for (p, c) in local.chunks_exact(3).enumerate() {
        let (x, y, z) = (f64::from(c[0]), f64::from(c[1]), f64::from(c[2]));
        if !(z > 1e-9 && x.is_finite() && y.is_finite() && z.is_finite()) {
            continue;
        }
        let (u, v) = ((p % w) as f64 - cx, (p / w) as f64 - cy);
        let (a, b) = (x / z, y / z);
        num += u * a + v * b;
        den += a * a + b * b;
    }
    (den > 0.0 && num > 0.0).then(|| num / den)
}

/// A feed-forward prediction in VGGT's `predictions.npz` layout (what VGGT's demo saves, with a
/// leading batch of 1, float32): `extrinsic`, `intrinsic`, `world_points` +
/// `world_points_conf` (the points and confidence), `depth` `[1, S, H, W, 1]` (their z-depth in
/// their camera) + `depth_conf` (the confidence), `images` `[1, S, 3, H, W]`. Written by
/// `ggpt-synth --vggt-predictions` and `scripts/export_ff.py`; read by [`read_feed_forward`].
pub fn vggt_arrays(
    ff: &FeedForward,
    images: &[f32],
    d: Dims,
) -> Result<Vec<(&'static str, crate::io::npy::NpyArray)>> {
    use crate::io::npy::NpyArray;
    let (n, h, w) = (d.n, d.h, d.w);
    let hw = h * w;
    if ff.points.len() != 3 * n * hw || ff.conf.len() != n * hw || images.len() != 3 * n * hw {
        return Err(CoreError::Invalid(format!(
            "VGGT arrays: {} points / {} confidences / {} image values for N={n} h={h} w={w}",
            ff.points.len(),
            ff.conf.len(),
            images.len()
        )));
    }
    let mut ext = Vec::with_capacity(12 * n);
    let mut k = Vec::with_capacity(9 * n);
    let mut depth = Vec::with_capacity(n * hw);
    for v in 0..n {
        let m = &ff.cameras.cam_from_world[v];
        ext.extend((0..12).map(|i| m[(i / 4, i % 4)] as f32));
        let kk = &ff.cameras.intrinsics[v];
        k.extend((0..9).map(|i| kk[(i / 3, i % 3)] as f32));
        let (r, t) = (ff.cameras.rotation(v), ff.cameras.translation(v));
        for p in ff.points[3 * v * hw..3 * (v + 1) * hw].chunks_exact(3) {
            let x = Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            depth.push((r * x + t).z as f32);
        }
    }
    let mut chw = vec![0f32; 3 * n * hw];
    for v in 0..n {
        for p in 0..hw {
            for c in 0..3 {
                chw[(v * 3 + c) * hw + p] = images[3 * (v * hw + p) + c];
            }
        }
    }
    let f = |shape: Vec<usize>, data: Vec<f32>| NpyArray::new(shape, NpyData::F32(data));
    Ok(vec![
        ("extrinsic", f(vec![1, n, 3, 4], ext)?),
        ("intrinsic", f(vec![1, n, 3, 3], k)?),
        ("world_points", f(vec![1, n, h, w, 3], ff.points.clone())?),
        ("world_points_conf", f(vec![1, n, h, w], ff.conf.clone())?),
        ("depth", f(vec![1, n, h, w, 1], depth)?),
        ("depth_conf", f(vec![1, n, h, w], ff.conf.clone())?),
        ("images", f(vec![1, n, 3, h, w], chw)?),
    ])
}

/// Writes [`vggt_arrays`] as an `.npz`, atomically.
pub fn write_vggt_predictions(
    path: &Path,
    ff: &FeedForward,
    images: &[f32],
    d: Dims,
) -> Result<()> {
    let arrays = vggt_arrays(ff, images, d)?;
    let refs: Vec<(&str, &crate::io::npy::NpyArray)> =
        arrays.iter().map(|(k, a)| (*k, a)).collect();
    crate::io::npy::write_npz(path, &refs, false)
}

/// Allowed distance of a `ff.npz` principal point from one of the accepted conventions, pixels.
pub const PRINCIPAL_POINT_TOL: f64 = 1e-3;

/// The project's `ff.npz` (`formats.md` §5.2): `points` `[N,h,w,3]`, `conf` `[N,h,w]` (f32, or
/// f64 rounded to f32),
/// `cam_from_world` `[N,3,4]` or `[N,4,4]`, `K` `[N,3,3]` with the principal point at the image
/// centre `((w-1)/2, (h-1)/2)` or VGGT's `(w/2, h/2)` (within [`PRINCIPAL_POINT_TOL`]), optional
/// `images` `[N,h,w,3]` u8 or f32 in `[0, 1]`.
fn read_ggpt(z: &mut NamedArrays) -> Result<FeedForwardInput> {
    let d = point_dims(z, "points")?;
    let (n, h, w) = (d.n, d.h, d.w);
    let points = f32_values(z, "points", &[n, h, w, 3])?;
    let conf = f32_values(z, "conf", &[n, h, w])?;
    let cameras = Cameras {
        cam_from_world: z.extrinsics("cam_from_world", n)?,
        intrinsics: z.intrinsics("K", n)?,
    };
    // Accepted: the image centre ((w-1)/2, (h-1)/2) and VGGT's native (w/2, h/2) [project: the
    // spec's §5.2 lists only the centre, but the BA keeps the given principal point, sfm.md §7.1,
    // and VGGT's output is what real users feed].
    let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    let (vx, vy) = (w as f64 / 2.0, h as f64 / 2.0);
    for (i, k) in cameras.intrinsics.iter().enumerate() {
        let near = |x: f64, y: f64| {
            (k[(0, 2)] - x).abs() <= PRINCIPAL_POINT_TOL
                && (k[(1, 2)] - y).abs() <= PRINCIPAL_POINT_TOL
        };
        if !near(cx, cy) && !near(vx, vy) {
            return Err(z.err(
                "K",
                format!("view {i}: principal point ({}, {}) is neither the image centre ({cx}, {cy}) nor VGGT's ({vx}, {vy})", k[(0, 2)], k[(1, 2)]),
            ));
        }
    }
    let images = if z.has("images") {
        Some(z.images("images", d)?)
    } else {
        None
    };
    Ok(FeedForwardInput {
        format: FfFormat::Ggpt,
        dims: d,
        ff: FeedForward {
            points,
            conf,
            cameras,
        },
        images,
    })
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use super::*;
    use crate::io::npy::NpyArray;

    fn arr(shape: &[usize], v: Vec<f32>) -> NpyArray {
        NpyArray::new(shape.to_vec(), NpyData::F32(v)).unwrap()
    }

    /// A 2-view 2x3 scene: view 0 identity, view 1 shifted; depth 2 everywhere.
    fn vggt_input(batch: bool) -> NamedArrays {
        let (n, h, w) = (2usize, 2usize, 3usize);
        let mut ext = Vec::new();
        let mut k = Vec::new();
        for v in 0..n {
            ext.extend([
                1.0, 0.0, 0.0, v as f32, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0,
            ]);
            k.extend([4.0f32, 0.0, 1.5, 0.0, 4.0, 1.0, 0.0, 0.0, 1.0]);
        }
        let b = |s: &[usize]| {
            if batch {
                [&[1], s].concat()
            } else {
                s.to_vec()
            }
        };
        let px = n * h * w;
        let mut m = BTreeMap::new();
        m.insert("extrinsic".into(), arr(&b(&[n, 3, 4]), ext));
        m.insert("intrinsic".into(), arr(&b(&[n, 3, 3]), k));
        m.insert("depth".into(), arr(&b(&[n, h, w, 1]), vec![2.0; px]));
        m.insert("depth_conf".into(), arr(&b(&[n, h, w]), vec![3.0; px]));
        m.insert(
            "world_points".into(),
            arr(&b(&[n, h, w, 3]), vec![0.5; 3 * px]),
        );
        m.insert(
            "world_points_conf".into(),
            arr(&b(&[n, h, w]), vec![5.0; px]),
        );
        m.insert(
            "images".into(),
            arr(
                &b(&[n, 3, h, w]),
                (0..3 * px).map(|i| i as f32 / 100.0).collect(),
            ),
        );
        NamedArrays::new("predictions.npz", m)
    }

    #[test]
    fn vggt_depth_branch_unprojects_with_the_cameras() {
        for batch in [false, true] {
            let r = read_feed_forward(vggt_input(batch), &FfReadOptions::default()).unwrap();
            assert_eq!(r.format, FfFormat::Vggt);
            assert_eq!(r.dims, Dims { n: 2, h: 2, w: 3 });
            assert_eq!(r.ff.conf, vec![3.0; 12]);
            // view 1 pixel (x=0, y=1): cam = 2 * ((0 - 1.5)/4, (1 - 1)/4, 1); world = cam - t
            let p = 3 * (6 + 3);
            assert_eq!(&r.ff.points[p..p + 3], &[-0.75 - 1.0, 0.0, 2.0]);
            // images transposed to [N, h, w, 3]: pixel 1 of view 0, channel 2 = value (2*6+1)
            let img = r.images.unwrap();
            assert_eq!(img[3 + 2], 13.0 / 100.0);
        }
        let pts = read_feed_forward(
            vggt_input(false),
            &FfReadOptions {
                branch: VggtBranch::Points,
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!(pts.ff.points, vec![0.5; 36]);
        assert_eq!(pts.ff.conf, vec![5.0; 12]);
    }

    #[test]
    fn bad_arrays_give_clear_errors() {
        let mut m = BTreeMap::new();
        m.insert("foo".to_string(), arr(&[1], vec![0.0]));
        let e = read_feed_forward(NamedArrays::new("x.npz", m), &FfReadOptions::default())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("x.npz") && e.contains("[foo]") && e.contains("VGGT"),
            "{e}"
        );

        let mut a = vggt_input(false);
        a.reshape_with("depth", |s| s.insert(0, 2));
        let e = read_feed_forward(a, &FfReadOptions::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("batch of 2") || e.contains("wrong shape"), "{e}");

        let mut a = vggt_input(false);
        a.set_f32("depth_conf", 5, f32::NAN);
        let e = read_feed_forward(a, &FfReadOptions::default()).unwrap_err();
        assert!(
            matches!(&e, CoreError::NonFinite { key, index: 5, .. } if key == "depth_conf"),
            "{e}"
        );
        let mut a = vggt_input(false);
        a.remove("depth");
        let e = read_feed_forward(a, &FfReadOptions::default())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("[depth]") && e.contains("--ff-branch points"),
            "{e}"
        );
    }

    #[test]
    fn vggt_predictions_round_trip() {
        let a = read_feed_forward(vggt_input(true).clone(), &FfReadOptions::default()).unwrap();
        let images = a.images.clone().unwrap();
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("predictions.npz");
        write_vggt_predictions(&p, &a.ff, &images, a.dims).unwrap();
        let opts = FfReadOptions {
            branch: VggtBranch::Points,
            ..Default::default()
        };
        let b = read_feed_forward_file(&p, &opts).unwrap();
        assert_eq!(b.ff.points, a.ff.points);
        assert_eq!(b.ff.conf, a.ff.conf);
        assert_eq!(b.images.unwrap(), images);
        assert_eq!(b.ff.cameras, a.ff.cameras);
        // the depth branch re-unprojects the written depth onto the same rays
        let c = read_feed_forward_file(&p, &FfReadOptions::default()).unwrap();
        for (x, y) in c.ff.points.iter().zip(&a.ff.points) {
            assert!((x - y).abs() < 1e-5, "{x} vs {y}");
        }
    }

    #[test]
    fn pi3_focal_is_recovered_from_local_points() {
        let (h, w, f) = (4usize, 6usize, 7.5);
        let mut local = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let z = 1.0 + (x + y) as f64 * 0.1;
                local.extend([
                    ((x as f64 - 3.0) / f * z) as f32,
                    ((y as f64 - 2.0) / f * z) as f32,
                    z as f32,
                ]);
            }
        }
        let est = estimate_focal(&local, h, w).unwrap();
        assert!((est - f).abs() < 1e-4, "{est}");
    }
}
