//! Export of a refined scene (`pipeline.md` §9): PLY point clouds, npy / npz arrays and a COLMAP
//! sparse model.
//!
//! PLY filter (official demo behaviour): threshold `τ` = the `q` quantile (default 0.2, linear
//! interpolation like `torch.quantile`) of the confidence over **all** `N h w` pixels (uncovered
//! pixels count with confidence 0; above 10^6 values every `s`-th value in pixel order,
//! `s = floor(n / 10^6) * 5`), keep `conf >= τ`, then a seeded uniform subset of at most
//! `max_points` (kept in pixel order). Colours: `floor(255 · clamp(v, 0, 1))`.
//!
//! Files ([`export_scene`]): `ggpt_points.ply` (refined, SfM frame), `ff_points.ply` (unaligned
//! feed-forward points of the same pixels, feed-forward frame), `sfm_points.ply` (DLT points, SfM
//! frame, ≤ 10^6, no confidence filter); `points.npy`, `confidence.npy`, `covered.npy`,
//! `depth.npy` (`z` of the refined points in the SfM cameras, scene units), `scene.npz`;
//! `sparse/0/` (COLMAP). The rest of a run's folder (`config.json`, `meta.json`,
//! `refined.safetensors`, `evaluation.json`, `error_maps/`) is written by `ggpt-infer`'s
//! `run_output::RunOutput`, which calls [`export_scene`] for these files.

use std::path::{Path, PathBuf};

use ggpt_core::color::color_u8;
use ggpt_core::io::colmap::{ColmapModel, ColmapPoint3D, write_colmap};
use ggpt_core::io::npy::{NpyArray, NpyData, write_npy, write_npz};
use ggpt_core::io::ply::{PlyCloud, write_ply};
use ggpt_core::{Cameras, Scene, SfmResult};
use rand::SeedableRng;

use crate::driver::RefinedScene;
use crate::error::{SceneError, check_len};

/// Default confidence quantile of the PLY filter (`--conf-quantile`, `pipeline.md` §9.1).
pub const DEFAULT_CONF_QUANTILE: f64 = 0.2;
/// Default maximum number of PLY points (`--max-points`, `pipeline.md` §9.1).
pub const DEFAULT_MAX_POINTS: usize = 1_000_000;
/// Above this many values the quantile is computed on a strided subset (`pipeline.md` §9.1).
pub const QUANTILE_MAX_VALUES: usize = 1_000_000;
/// Stride multiplier of the quantile subset: `s = floor(n / 10^6) * 5` (`pipeline.md` §9.1).
pub const QUANTILE_STRIDE_FACTOR: usize = 5;
/// Default maximum number of COLMAP `points3D` (`pipeline.md` §9.3).
pub const DEFAULT_COLMAP_MAX_POINTS: usize = 100_000;

/// `torch.quantile(values, q)` with linear interpolation, reproducing torch's `f32` arithmetic:
/// `rank = f32(q) · (n - 1)` in `f32`, `lo = floor(rank)`, `w = rank - lo`, then torch's `lerp`
/// (`a + w (b - a)` for `w < 0.5`, else `b - (b - a)(1 - w)`). Errors on empty input, `q`
/// outside `[0, 1]` or non-finite values.
pub fn torch_quantile(values: &[f32], q: f64) -> Result<f32, SceneError> {
    if values.is_empty() {
        return Err(SceneError::Invalid("quantile of an empty array".into()));
    }
    if !(0.0..=1.0).contains(&q) {
        return Err(SceneError::Invalid(format!(
            "quantile q = {q} outside [0, 1]"
        )));
    }
    crate::error::check_finite("quantile input", values)?;
    let n = values.len();
    let rank = (q as f32) * ((n - 1) as f32);
    let lo = (rank.floor() as usize).min(n - 1);
    let hi = (rank.ceil() as usize).min(n - 1);
    let w = rank - lo as f32;
    let mut v = values.to_vec();
    let (_, &mut a, upper) = v.select_nth_unstable_by(lo, f32::total_cmp);
    let b = if hi == lo {
        a
    } else {
        upper.iter().copied().min_by(f32::total_cmp).unwrap_or(a)
    };
    Ok(if w < 0.5 {
        a + w * (b - a)
    } else {
        b - (b - a) * (1.0 - w)
    })
}

/// The PLY confidence threshold `τ` (`pipeline.md` §9.1): [`torch_quantile`] of `conf` (all
/// pixels, pixel order), on every `s`-th value when there are more than 10^6 values.
pub fn confidence_threshold(conf: &[f32], q: f64) -> Result<f32, SceneError> {
    let n = conf.len();
    if n > QUANTILE_MAX_VALUES {
        let s = (n / QUANTILE_MAX_VALUES) * QUANTILE_STRIDE_FACTOR;
        let sub: Vec<f32> = conf.iter().step_by(s).copied().collect();
        torch_quantile(&sub, q)
    } else {
        torch_quantile(conf, q)
    }
}

/// Seeded uniform subset of `indices` of size `max` (all of them when there are fewer), kept in
/// the input order. The same seed and input always give the same subset.
pub fn subsample(indices: &[u32], max: usize, seed: u64) -> Vec<u32> {
    if indices.len() <= max {
        return indices.to_vec();
    }
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let mut pick = rand::seq::index::sample(&mut rng, indices.len(), max).into_vec();
    pick.sort_unstable();
    pick.into_iter()
        .filter_map(|i| indices.get(i).copied())
        .collect()
}

/// Pixels kept by the PLY filter: `conf >= τ`, then [`subsample`] to `max_points`.
pub fn select_points(
    conf: &[f32],
    q: f64,
    max_points: usize,
    seed: u64,
) -> Result<(f32, Vec<u32>), SceneError> {
    select_points_voxel(conf, None, q, max_points, seed)
}

/// [`select_points`] with the voxel filter (`Some((points [P, 3], side))`,
/// [`crate::splat::voxel_filter`]) between the confidence filter and the subset.
pub fn select_points_voxel(
    conf: &[f32],
    voxel: Option<(&[f32], f64)>,
    q: f64,
    max_points: usize,
    seed: u64,
) -> Result<(f32, Vec<u32>), SceneError> {
    let tau = confidence_threshold(conf, q)?;
    let mut keep: Vec<u32> = conf
        .iter()
        .enumerate()
        .filter(|(_, c)| **c >= tau)
        .map(|(p, _)| p as u32)
        .collect();
    if let Some((points, side)) = voxel {
        keep = crate::splat::voxel_filter(points, conf, &keep, side);
    }
    Ok((tau, subsample(&keep, max_points, seed)))
}

/// COLMAP export options (`pipeline.md` §9.3).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct ColmapExportOptions {
    /// Text files instead of binary (`--colmap-text`).
    pub text: bool,
    /// Write the filtered refined points as `points3D` (`--colmap-points none` -> false).
    pub points: bool,
    /// Maximum number of `points3D` (seeded subset).
    pub max_points: usize,
    /// One image resolution `(H, W)` for every view to rescale the cameras to, over the
    /// sizes of `ExportOptions::image_sizes` (`--colmap-resolution WxH`); `None`: those sizes,
    /// else the ff resolution.
    pub resolution: Option<(usize, usize)>,
    /// One shared camera (as the BA used).
    pub shared_camera: bool,
    /// `SIMPLE_PINHOLE` instead of `PINHOLE`.
    pub simple_pinhole: bool,
}

impl Default for ColmapExportOptions {
    fn default() -> Self {
        ColmapExportOptions {
            text: false,
            points: true,
            max_points: DEFAULT_COLMAP_MAX_POINTS,
            resolution: None,
            shared_camera: true,
            simple_pinhole: false,
        }
    }
}

/// Export options (`pipeline.md` §9).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct ExportOptions {
    /// Confidence quantile of the PLY filter (`--conf-quantile`).
    pub conf_quantile: f64,
    /// Maximum PLY points (`--max-points`).
    pub max_points: usize,
    /// Seed of the subsampling.
    pub seed: u64,
    /// Write the `confidence` PLY property.
    pub ply_confidence: bool,
    /// Write the PLY files.
    pub ply: bool,
    /// Write the npy / npz arrays.
    pub arrays: bool,
    /// COLMAP model (`None`: not written).
    pub colmap: Option<ColmapExportOptions>,
    /// Image file names for COLMAP, `images/` and `transforms.json` (`None`: the names of
    /// `image_files`, else `000000.png`, ...).
    pub image_names: Option<Vec<String>>,
    /// The original image files, one per view (`--images DIR`): copied (hard-linked) into
    /// `images/`, their names and sizes used by the COLMAP model and `transforms.json`. `None`:
    /// the ff images are written there as PNGs, the cameras at the ff resolution.
    pub image_files: Option<Vec<PathBuf>>,
    /// `(H, W)` of each original image (read from `image_files` by the caller).
    pub image_sizes: Option<Vec<(usize, usize)>>,
    /// Write the splat-ready part with the COLMAP model: `images/` and nerfstudio's
    /// `transforms.json` (`crate::splat`).
    pub splat: bool,
    /// Keep one refined point per cube of this side (scene units) in the PLY / COLMAP points,
    /// the most confident (`--voxel-size`); `None`: no voxel filter.
    pub voxel_size: Option<f64>,
}

impl Default for ExportOptions {
    fn default() -> Self {
        ExportOptions {
            conf_quantile: DEFAULT_CONF_QUANTILE,
            max_points: DEFAULT_MAX_POINTS,
            seed: crate::driver::DEFAULT_SEED,
            ply_confidence: true,
            ply: true,
            arrays: true,
            colmap: Some(ColmapExportOptions::default()),
            image_names: None,
            image_files: None,
            image_sizes: None,
            splat: true,
            voxel_size: None,
        }
    }
}

/// What was written.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ExportSummary {
    /// Confidence threshold `τ`.
    pub threshold: f32,
    /// Points in `ggpt_points.ply` / `ff_points.ply`.
    pub ply_points: usize,
    /// Points in `sfm_points.ply`.
    pub sfm_points: usize,
    /// COLMAP `points3D`.
    pub colmap_points: usize,
    /// Files written (relative to the output folder).
    pub files: Vec<String>,
}

fn p3(a: &[f32], p: usize) -> [f32; 3] {
    match a.get(3 * p..3 * p + 3) {
        Some(s) => [s[0], s[1], s[2]],
        None => [0.0; 3],
    }
}

fn colors(images: &[f32], pixels: &[u32]) -> Vec<[u8; 3]> {
    pixels
        .iter()
        .map(|&p| p3(images, p as usize).map(color_u8))
        .collect()
}

/// Depth `z` of every refined point in its own view's camera (`cam_from_world_sfm`), `[P]`.
pub fn depth_map(points: &[f32], cameras: &Cameras, hw: usize) -> Result<Vec<f32>, SceneError> {
    if hw == 0 || points.len() != 3 * hw * cameras.len() {
        return Err(SceneError::Invalid(format!(
            "depth: {} point values for {} cameras of {hw} pixels",
            points.len(),
            cameras.len()
        )));
    }
    Ok(points
        .chunks_exact(3)
        .enumerate()
        .map(|(p, x)| {
            let m = &cameras.cam_from_world[p / hw];
            (m[(2, 0)] * f64::from(x[0])
                + m[(2, 1)] * f64::from(x[1])
                + m[(2, 2)] * f64::from(x[2])
                + m[(2, 3)]) as f32
        })
        .collect())
}

fn arr(shape: Vec<usize>, data: NpyData) -> Result<NpyArray, SceneError> {
    Ok(NpyArray::new(shape, data)?)
}

/// `ERROR` of a COLMAP `points3D` entry without observations: COLMAP's "undefined" marker
/// (`Point3D::HasError()` is false, so COLMAP's / pycolmap's mean reprojection error skips it).
pub const COLMAP_UNDEFINED_ERROR: f64 = -1.0;

/// Builds the COLMAP model of §9.3: `cameras` at the images' resolution `sizes[v] = (H, W)`
/// ([`crate::splat::scale_cameras`]; one shared camera only when every image has the same size),
/// images `1..N` named `names` with their poses and no `POINTS2D`, and `points` (pixel indices of refined
/// points) as `points3D` with colour, `ERROR` = [`COLMAP_UNDEFINED_ERROR`] and an **empty
/// track**. A refined dense point is not triangulated from feature observations, so it has no
/// track and no reprojection error to store ([project] deviation from the spec's one-element
/// pixel tracks with error 0, whose stored error was not the reprojection error: pycolmap's
/// reprojection check rejected it).
pub fn colmap_model(
    refined: &RefinedScene,
    images: &[f32],
    cameras: &Cameras,
    sizes: &[(usize, usize)],
    names: &[String],
    points: &[u32],
    opts: &ColmapExportOptions,
) -> Result<ColmapModel, SceneError> {
    let d = refined.dims;
    let shared = opts.shared_camera && sizes.windows(2).all(|p| p[0] == p[1]);
    let mut model =
        ColmapModel::from_cameras_sized(cameras, sizes, names, opts.simple_pinhole, shared)?;
    let px = d.pixels();
    for (i, &p) in points.iter().enumerate() {
        let p = p as usize;
        if p >= px {
            return Err(SceneError::Invalid(format!(
                "colmap: pixel {p} beyond {} views",
                d.n
            )));
        }
        let id = i as u64 + 1;
        let xyz = p3(&refined.points, p).map(f64::from);
        model.points3d.push(ColmapPoint3D {
            id,
            xyz,
            rgb: p3(images, p).map(color_u8),
            error: COLMAP_UNDEFINED_ERROR,
            track: Vec::new(),
        });
    }
    Ok(model)
}

/// The image names of the export: `opts.image_names`, else the file names of
/// `opts.image_files`, else `000000.png`, ...
fn image_names(opts: &ExportOptions, n: usize) -> Result<Vec<String>, SceneError> {
    let names: Vec<String> = match (&opts.image_names, &opts.image_files) {
        (Some(v), _) => v.clone(),
        (None, Some(files)) => files
            .iter()
            .map(|f| {
                f.file_name()
                    .map(|s| s.to_string_lossy().into_owned())
                    .ok_or_else(|| {
                        SceneError::Invalid(format!("image {}: no file name", f.display()))
                    })
            })
            .collect::<Result<_, _>>()?,
        (None, None) => (0..n).map(|i| format!("{i:06}.png")).collect(),
    };
    if names.len() != n {
        return Err(SceneError::Invalid(format!(
            "export: {} image names for {n} views",
            names.len()
        )));
    }
    Ok(names)
}

/// Writes the export files of §9 (PLY, npy / npz, COLMAP and the splat-ready part, as `opts`
/// selects) into `dir` (created if needed) and returns what was written. `scene` provides the
/// images and the unaligned feed-forward points, `sfm` the cameras and DLT points, `refined` the
/// output of [`crate::driver::refine_scene`].
pub fn export_scene(
    dir: &Path,
    scene: &Scene,
    sfm: &SfmResult,
    refined: &RefinedScene,
    opts: &ExportOptions,
) -> Result<ExportSummary, SceneError> {
    std::fs::create_dir_all(dir).map_err(|e| ggpt_core::CoreError::io(dir, e))?;
    let d = refined.dims;
    let px = d.pixels();
    check_len("export: refined points", refined.points.len(), 3 * px)?;
    check_len("export: refined confidence", refined.conf.len(), px)?;
    check_len("export: images", scene.images.len(), 3 * px)?;
    check_len("export: sfm points", sfm.points.len(), 3 * px)?;
    check_len("export: sfm mask", sfm.mask.len(), px)?;
    let ff = scene.ff.as_ref().ok_or_else(|| {
        SceneError::Invalid("export: the scene has no feed-forward prediction".into())
    })?;
    check_len("export: ff points", ff.points.len(), 3 * px)?;
    let mut files = Vec::new();
    if let Some(v) = opts.voxel_size
        && !(v.is_finite() && v > 0.0)
    {
        return Err(SceneError::Invalid(format!(
            "export: voxel size {v} must be positive"
        )));
    }
    let (tau, keep) = select_points_voxel(
        &refined.conf,
        opts.voxel_size.map(|v| (refined.points.as_slice(), v)),
        opts.conf_quantile,
        opts.max_points,
        opts.seed,
    )?;
    let mut sfm_count = 0;
    if opts.ply {
        let cols = colors(&scene.images, &keep);
        let conf_of = |c: &[f32]| {
            opts.ply_confidence.then(|| {
                keep.iter()
                    .map(|&p| c.get(p as usize).copied().unwrap_or(0.0))
                    .collect()
            })
        };
        let refined_cloud = PlyCloud {
            points: keep
                .iter()
                .map(|&p| p3(&refined.points, p as usize))
                .collect(),
            colors: cols.clone(),
            confidence: conf_of(&refined.conf),
        };
        write_ply(&dir.join("ggpt_points.ply"), &refined_cloud)?;
        let ff_cloud = PlyCloud {
            points: keep.iter().map(|&p| p3(&ff.points, p as usize)).collect(),
            colors: cols,
            confidence: conf_of(&ff.conf),
        };
        write_ply(&dir.join("ff_points.ply"), &ff_cloud)?;
        let dlt: Vec<u32> = sfm
            .mask
            .iter()
            .enumerate()
            .filter(|(_, m)| **m)
            .map(|(p, _)| p as u32)
            .collect();
        let dlt = subsample(&dlt, opts.max_points, opts.seed);
        sfm_count = dlt.len();
        let sfm_cloud = PlyCloud {
            points: dlt.iter().map(|&p| p3(&sfm.points, p as usize)).collect(),
            colors: colors(&scene.images, &dlt),
            confidence: None,
        };
        write_ply(&dir.join("sfm_points.ply"), &sfm_cloud)?;
        files.extend(["ggpt_points.ply", "ff_points.ply", "sfm_points.ply"].map(String::from));
    }
    if opts.arrays {
        let (n, h, w) = (d.n, d.h, d.w);
        let points = arr(vec![n, h, w, 3], NpyData::F32(refined.points.clone()))?;
        let conf = arr(vec![n, h, w], NpyData::F32(refined.conf.clone()))?;
        let covered = arr(vec![n, h, w], NpyData::Bool(refined.covered.clone()))?;
        let depth = arr(
            vec![n, h, w],
            NpyData::F32(depth_map(&refined.points, &sfm.cameras, d.hw())?),
        )?;
        let cams = arr(
            vec![n, 3, 4],
            NpyData::F64(
                sfm.cameras
                    .cam_from_world
                    .iter()
                    .flat_map(|m| (0..12).map(move |i| m[(i / 4, i % 4)]))
                    .collect(),
            ),
        )?;
        let ks = arr(
            vec![n, 3, 3],
            NpyData::F64(
                sfm.cameras
                    .intrinsics
                    .iter()
                    .flat_map(|m| (0..9).map(move |i| m[(i / 3, i % 3)]))
                    .collect(),
            ),
        )?;
        let imgs = arr(
            vec![n, h, w, 3],
            NpyData::U8(scene.images.iter().map(|&v| color_u8(v)).collect()),
        )?;
        write_npy(&dir.join("points.npy"), &points)?;
        write_npy(&dir.join("confidence.npy"), &conf)?;
        write_npy(&dir.join("covered.npy"), &covered)?;
        write_npy(&dir.join("depth.npy"), &depth)?;
        let members = [
            ("points", &points),
            ("confidence", &conf),
            ("covered", &covered),
            ("depth", &depth),
            ("cam_from_world", &cams),
            ("K", &ks),
            ("images_ff", &imgs),
        ];
        write_npz(&dir.join("scene.npz"), &members, false)?;
        files.extend(
            [
                "points.npy",
                "confidence.npy",
                "covered.npy",
                "depth.npy",
                "scene.npz",
            ]
            .map(String::from),
        );
    }
    let mut colmap_count = 0;
    if let Some(c) = &opts.colmap {
        let names = image_names(opts, d.n)?;
        let sizes: Vec<(usize, usize)> = match (c.resolution, &opts.image_sizes) {
            (Some(r), _) => vec![r; d.n],
            (None, Some(s)) if s.len() == d.n => s.clone(),
            (None, Some(s)) => {
                return Err(SceneError::Invalid(format!(
                    "export: {} image sizes for {} views",
                    s.len(),
                    d.n
                )));
            }
            (None, None) => vec![(d.h, d.w); d.n],
        };
        let pts = if c.points {
            subsample(&keep, c.max_points, opts.seed)
        } else {
            Vec::new()
        };
        colmap_count = pts.len();
        let cams = crate::splat::scale_cameras(&sfm.cameras, d, &sizes);
        let model = colmap_model(refined, &scene.images, &cams, &sizes, &names, &pts, c)?;
        write_colmap(&dir.join("sparse/0"), &model, c.text)?;
        files.push("sparse/0".into());
        if opts.splat {
            crate::splat::write_images(dir, &names, opts.image_files.as_deref(), &scene.images, d)?;
            let ply = opts.ply.then_some("ggpt_points.ply");
            let t = crate::splat::transforms_json(&cams, &sizes, &names, ply);
            crate::splat::write_transforms(dir, &t)?;
            files.push(crate::splat::IMAGES_DIR.into());
            files.push(crate::splat::TRANSFORMS_JSON.into());
        }
    }
    let summary = ExportSummary {
        threshold: tau,
        ply_points: keep.len(),
        sfm_points: sfm_count,
        colmap_points: colmap_count,
        files,
    };
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantile_matches_torch() {
        // torch.quantile(torch.tensor([1., 2., 3., 4., 5.]), 0.2) = 1.8
        let got = torch_quantile(&[5.0, 1.0, 4.0, 2.0, 3.0], 0.2).unwrap();
        assert!((got - 1.8).abs() < 1e-6, "{got}");
        // torch.quantile(torch.tensor([0., 0., 0., 10.]), 0.2) = 0.0 (rank 0.6 between 0 and 0)
        assert_eq!(torch_quantile(&[0.0, 10.0, 0.0, 0.0], 0.2).unwrap(), 0.0);
        // torch.quantile(torch.tensor([0., 0., 1., 2., 3., 4., 5., 6., 7., 8.]), 0.2) = 0.8
        // (rank 0.2*9 = 1.8 -> lerp(0, 1, 0.8) = 1 - 1*(1-0.8) = 0.8 in f32: 0.79999995)
        let v = [0.0, 0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0];
        let got = torch_quantile(&v, 0.2).unwrap();
        let rank = 0.2f32 * 9.0;
        let w = rank - 1.0;
        assert_eq!(got, 1.0 - 1.0 * (1.0 - w));
        assert!((got - 0.8).abs() < 1e-6);
        // Single value, q = 0 and q = 1.
        assert_eq!(torch_quantile(&[3.5], 0.2).unwrap(), 3.5);
        assert_eq!(torch_quantile(&[4.0, 1.0, 2.0], 0.0).unwrap(), 1.0);
        assert_eq!(torch_quantile(&[4.0, 1.0, 2.0], 1.0).unwrap(), 4.0);
        // torch.quantile(torch.tensor([1., 3.]), 0.25) = 1.5
        assert_eq!(torch_quantile(&[3.0, 1.0], 0.25).unwrap(), 1.5);
        assert!(torch_quantile(&[], 0.2).is_err());
        assert!(torch_quantile(&[1.0], 1.5).is_err());
        assert!(torch_quantile(&[f32::NAN], 0.5).is_err());
    }

    #[test]
    fn strided_quantile_above_a_million() {
        // n = 2,000,001 -> s = 10: values 0..n, subset 0, 10, 20, ... (200,001 values, max 2,000,000).
        let n = 2_000_001usize;
        let v: Vec<f32> = (0..n).map(|i| i as f32).collect();
        let t = confidence_threshold(&v, 0.2).unwrap();
        // rank = 0.2 * 200000 = 40000 -> value 400000.
        assert_eq!(t, 400_000.0);
        // Exactly 10^6 values: no striding.
        let v: Vec<f32> = (0..1_000_000).map(|i| i as f32).collect();
        let rank = 0.2f32 * 999_999.0;
        let lo = rank.floor();
        let w = rank - lo;
        let want = if w < 0.5 {
            lo + w
        } else {
            (lo + 1.0) - (1.0 - w)
        };
        assert_eq!(confidence_threshold(&v, 0.2).unwrap(), want);
    }

    #[test]
    fn subsample_is_deterministic_uniform_and_ordered() {
        let idx: Vec<u32> = (0..1000).collect();
        let a = subsample(&idx, 100, 42);
        let b = subsample(&idx, 100, 42);
        let c = subsample(&idx, 100, 43);
        assert_eq!(a, b);
        assert_ne!(a, c);
        assert_eq!(a.len(), 100);
        assert!(a.windows(2).all(|w| w[0] < w[1]));
        assert_eq!(subsample(&idx[..50], 100, 42), idx[..50].to_vec());
        // Roughly uniform: each half gets a fair share.
        let low = a.iter().filter(|&&p| p < 500).count();
        assert!((30..=70).contains(&low), "{low}");
    }

    #[test]
    fn select_counts_uncovered_zeros() {
        // 10 pixels, 4 uncovered (conf 0): q = 0.2 -> rank 1.8 between 0 and 0 -> τ = 0: all kept.
        let conf = [0.0, 0.0, 0.0, 0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0];
        let (t, keep) = select_points(&conf, 0.2, 100, 1).unwrap();
        assert_eq!(t, 0.0);
        assert_eq!(keep.len(), 10);
        // With q = 0.5: rank 4.5 -> lerp(1, 2, 0.5) = 1.5 -> 5 pixels kept.
        let (t, keep) = select_points(&conf, 0.5, 100, 1).unwrap();
        assert_eq!(t, 1.5);
        assert_eq!(keep, vec![5, 6, 7, 8, 9]);
    }

    #[test]
    fn export_scene_writes_readable_files() {
        use crate::driver::tests::{MockRefiner, fixture_opts, fixture_scene};
        use ggpt_core::io::{colmap::read_colmap, npy::read_npy, npy::read_npz, ply::read_ply};
        let (scene, sfm) = fixture_scene();
        let mut m = MockRefiner {
            offset_per_chunk: 0.0,
            calls: vec![],
            seen: vec![],
        };
        let refined = crate::driver::refine_scene(&scene, &sfm, &mut m, &fixture_opts()).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let colmap = ColmapExportOptions {
            resolution: Some((84, 112)),
            max_points: 50,
            ..ColmapExportOptions::default()
        };
        let opts = ExportOptions {
            max_points: 2000,
            colmap: Some(colmap),
            ..ExportOptions::default()
        };
        let sum = export_scene(dir.path(), &scene, &sfm, &refined, &opts).unwrap();
        let (tau, keep) = select_points(&refined.conf, 0.2, 2000, 42).unwrap();
        assert_eq!((sum.threshold, sum.ply_points), (tau, keep.len()));
        assert_eq!(keep.len(), 2000); // more than 2000 pass the filter: subsampled
        let ply = read_ply(&dir.path().join("ggpt_points.ply")).unwrap();
        assert_eq!(ply.points.len(), 2000);
        let p0 = keep[0] as usize;
        assert_eq!(
            ply.points[0],
            [
                refined.points[3 * p0],
                refined.points[3 * p0 + 1],
                refined.points[3 * p0 + 2]
            ]
        );
        assert_eq!(
            ply.colors[0],
            [0, 1, 2].map(|a| color_u8(scene.images[3 * p0 + a]))
        );
        assert!(ply.confidence.as_ref().unwrap().iter().all(|&c| c >= tau));
        let ffp = read_ply(&dir.path().join("ff_points.ply")).unwrap();
        let ff = scene.ff.as_ref().unwrap();
        assert_eq!(
            ffp.points[0],
            [
                ff.points[3 * p0],
                ff.points[3 * p0 + 1],
                ff.points[3 * p0 + 2]
            ]
        );
        let sp = read_ply(&dir.path().join("sfm_points.ply")).unwrap();
        assert_eq!(
            sp.points.len(),
            2000.min(sfm.mask.iter().filter(|&&b| b).count())
        );
        assert!(sp.confidence.is_none());
        let pts = read_npy(&dir.path().join("points.npy")).unwrap();
        assert_eq!(pts.shape, vec![4, 42, 56, 3]);
        assert_eq!(pts.to_f32().unwrap(), refined.points);
        let depth = read_npy(&dir.path().join("depth.npy"))
            .unwrap()
            .to_f32()
            .unwrap();
        // Depth = z of the refined point in its own SfM camera.
        let c = &sfm.cameras.cam_from_world[0];
        let x = &refined.points[0..3];
        let z = c[(2, 0)] * f64::from(x[0])
            + c[(2, 1)] * f64::from(x[1])
            + c[(2, 2)] * f64::from(x[2])
            + c[(2, 3)];
        assert!((f64::from(depth[0]) - z).abs() < 1e-5);
        let npz = read_npz(&dir.path().join("scene.npz")).unwrap();
        for k in [
            "points",
            "confidence",
            "covered",
            "depth",
            "cam_from_world",
            "K",
            "images_ff",
        ] {
            assert!(npz.contains_key(k), "scene.npz lacks {k}");
        }
        assert_eq!(npz["K"].shape, vec![4, 3, 3]);
        let model = read_colmap(&dir.path().join("sparse/0")).unwrap();
        assert_eq!(model.cameras.len(), 1); // shared camera
        assert_eq!(model.cameras[0].width, 112);
        let k = &sfm.cameras.intrinsics[0];
        assert!((model.cameras[0].params[0] - k[(0, 0)] * 2.0).abs() < 1e-9);
        assert_eq!(model.cameras[0].params[2], 56.0); // cx_colmap = W / 2
        assert_eq!(model.images.len(), 4);
        assert_eq!(model.points3d.len(), 50);
        // Refined points without tracks: no observation anywhere, COLMAP's undefined error.
        let obs: usize = model.images.iter().map(|i| i.points2d.len()).sum();
        assert_eq!(obs, 0);
        let colmap_pts = subsample(&keep, 50, crate::driver::DEFAULT_SEED);
        for (p, &px) in model.points3d.iter().zip(&colmap_pts) {
            assert!(
                p.track.is_empty() && p.error == COLMAP_UNDEFINED_ERROR,
                "point {}",
                p.id
            );
            assert_eq!(p.xyz, p3(&refined.points, px as usize).map(f64::from));
            assert_eq!(p.rgb, p3(&scene.images, px as usize).map(color_u8));
        }
        // every file listed was written; the run files are not the export's
        assert!(sum.files.iter().all(|f| dir.path().join(f).exists()));
        assert!(!dir.path().join("meta.json").exists());
    }
}
