//! The `ggpt-infer` scene folder (`formats.md` §5.1):
//!
//! ```text
//! <scene>/images/                       input images (.jpg/.jpeg/.png), name order = view order
//! <scene>/ff.npz                        feed-forward outputs (§5.2)   — or ff_outputs.bin
//! <scene>/matches/<matcher>.safetensors dense matches (§5.2), required unless SfM is given
//! <scene>/sfm.npz                       optional SfM (§5.3)           — or sfm_dlt_outputs.bin
//! <scene>/gt.bin                        optional official ground truth
//! ```
//!
//! `ff.npz`: `points` f32 `[N,h,w,3]`, `conf` f32 `[N,h,w]`, `cam_from_world` `[N,3,4]` or
//! `[N,4,4]` (f32/f64), `K` `[N,3,3]` (f32/f64, principal point `((w-1)/2,(h-1)/2)` within
//! 1e-3 px), `images` `[N,h,w,3]` u8 or f32 in `[0,1]` (optional here: when absent the files of
//! `images/` are decoded and resized bilinearly to `h x w`). `sfm.npz`: `cam_from_world` `[N,3,4]`,
//! `K` `[N,3,3]`, `points` f32, `mask` bool, `camera_success` / `points_success` 0-d bool
//! (`dlt_count` / `dlt_reproj` are accepted and not kept). Unknown npz keys are ignored.

use std::path::{Path, PathBuf};

use crate::io::arrays::NamedArrays;
use crate::io::feedforward::{FfFormat, FfReadOptions, read_feed_forward_file};
use crate::io::matches::read_matches;
use crate::io::npy::{NpyArray, NpyData};
use crate::io::official::{dir_name, read_ff_outputs_bin, read_gt_bin, read_sfm_dlt_outputs_bin};
use crate::resize::{BilinearRounding, resize_bilinear};
use crate::{Cameras, CoreError, Dims, FeedForward, Result, Scene, SfmResult};

pub use crate::io::feedforward::PRINCIPAL_POINT_TOL;
/// Accepted image file extensions (lower case).
const IMAGE_EXTS: [&str; 3] = ["jpg", "jpeg", "png"];

/// Reads a §5.1 folder (not validated; `crate::io::read_scene` validates).
pub fn read_infer_folder(dir: &Path) -> Result<Scene> {
    let (ff, mut images, dims) = read_ff_part(dir)?;
    let sfm = read_sfm_part(dir, dims)?;
    let gt_p = dir.join("gt.bin");
    let gt = if gt_p.is_file() {
        let g = read_gt_bin(&gt_p)?;
        check_dims(&gt_p, "points", g.dims, dims)?;
        Some(g.to_ground_truth())
    } else {
        None
    };
    let matches = read_matches_dir(dir, dims)?;
    if sfm.is_none() && matches.is_empty() {
        return Err(CoreError::format(
            dir,
            "matches",
            "neither sfm.npz / sfm_dlt_outputs.bin nor matches/*.safetensors present",
        ));
    }
    if images.is_none() {
        images = Some(read_image_dir(dir, dims)?);
    }
    let images = images.unwrap_or_default();
    Ok(Scene {
        name: dir_name(dir),
        dims,
        images,
        gt,
        ff: Some(ff),
        sfm,
        matches,
    })
}

fn check_dims(file: &Path, key: &str, got: Dims, want: Dims) -> Result<()> {
    if got != want {
        return Err(CoreError::format(
            file,
            key,
            format!(
                "N={} h={} w={} differ from the feed-forward N={} h={} w={}",
                got.n, got.h, got.w, want.n, want.h, want.w
            ),
        ));
    }
    Ok(())
}

/// Feed-forward part, its images when it has them, and the scene dims.
fn read_ff_part(dir: &Path) -> Result<(FeedForward, Option<Vec<f32>>, Dims)> {
    let npz = dir.join("ff.npz");
    if !npz.is_file() {
        let bin = dir.join("ff_outputs.bin");
        if !bin.is_file() {
            return Err(CoreError::format(
                dir,
                "ff.npz",
                "missing feed-forward outputs (ff.npz or ff_outputs.bin)",
            ));
        }
        let f = read_ff_outputs_bin(&bin)?;
        return Ok((f.to_feed_forward(), Some(f.images_ff.clone()), f.dims));
    }
    let r = read_feed_forward_file(
        &npz,
        &FfReadOptions {
            format: Some(FfFormat::Ggpt),
            ..FfReadOptions::default()
        },
    )?;
    Ok((r.ff, r.images, r.dims))
}

fn read_sfm_part(dir: &Path, dims: Dims) -> Result<Option<SfmResult>> {
    let npz = dir.join("sfm.npz");
    if !npz.is_file() {
        let bin = dir.join("sfm_dlt_outputs.bin");
        if !bin.is_file() {
            return Ok(None);
        }
        let s = read_sfm_dlt_outputs_bin(&bin)?;
        check_dims(&bin, "points", s.dims, dims)?;
        return Ok(Some(s.to_sfm_result()));
    }
    let z = NamedArrays::open_npz(&npz)?;
    let (n, h, w) = (dims.n, dims.h, dims.w);
    let pshape = z.get("points")?.shape.clone();
    if pshape != [n, h, w, 3] {
        return Err(z.err(
            "points",
            format!(
                "shape {pshape:?} differs from the feed-forward [N, h, w, 3] = [{n}, {h}, {w}, 3]"
            ),
        ));
    }
    Ok(Some(SfmResult {
        points: z.f32_exact("points", &[n, h, w, 3])?,
        mask: z.bools("mask", &[n, h, w])?,
        cameras: Cameras {
            cam_from_world: z.extrinsics("cam_from_world", n)?,
            intrinsics: z.intrinsics("K", n)?,
        },
        camera_success: z.scalar_bool("camera_success")?,
        points_success: z.scalar_bool("points_success")?,
    }))
}

fn read_matches_dir(dir: &Path, dims: Dims) -> Result<Vec<crate::MatchSet>> {
    let mdir = dir.join("matches");
    if !mdir.is_dir() {
        return Ok(Vec::new());
    }
    let mut files: Vec<PathBuf> = std::fs::read_dir(&mdir)
        .map_err(|e| CoreError::io(&mdir, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "safetensors"))
        .collect();
    files.sort();
    let mut out = Vec::new();
    for p in files {
        let m = read_matches(&p)?;
        check_dims(
            &p,
            "pred_matches",
            Dims {
                n: m.n,
                h: m.h,
                w: m.w,
            },
            dims,
        )?;
        out.push(m.set);
    }
    Ok(out)
}

/// Decodes `images/*` (name order) and resizes each bilinearly to `h x w` when needed.
fn read_image_dir(dir: &Path, dims: Dims) -> Result<Vec<f32>> {
    read_images(&list_images(&dir.join("images"), Some(dims.n))?, dims)
}

/// The image files (`.jpg`, `.jpeg`, `.png`, any case) of `dir` in name order: the view order
/// of every reader. `n`: the number of views they must be (an error names the folder).
pub fn list_images(dir: &Path, n: Option<usize>) -> Result<Vec<PathBuf>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| CoreError::io(dir, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension().is_some_and(|e| {
                IMAGE_EXTS.contains(&e.to_string_lossy().to_ascii_lowercase().as_str())
            })
        })
        .collect();
    files.sort();
    if let Some(n) = n
        && files.len() != n
    {
        return Err(CoreError::format(
            dir,
            "",
            format!(
                "{} images (.jpg/.jpeg/.png), the feed-forward outputs have N={n}",
                files.len()
            ),
        ));
    }
    if files.is_empty() {
        return Err(CoreError::format(dir, "", "no image (.jpg/.jpeg/.png)"));
    }
    Ok(files)
}

/// The size `(h, w)` of each image file, read from its header (no decoding).
pub fn image_sizes(files: &[PathBuf]) -> Result<Vec<(usize, usize)>> {
    files
        .iter()
        .map(|p| {
            image::image_dimensions(p)
                .map(|(w, h)| (h as usize, w as usize))
                .map_err(|e| CoreError::format(p, "", format!("cannot read the image size: {e}")))
        })
        .collect()
}

/// Decodes `files` (one per view) as `[N, h, w, 3]` RGB in `[0, 1]`, each resized bilinearly to
/// the ff resolution `h x w` when needed.
pub fn read_images(files: &[PathBuf], dims: Dims) -> Result<Vec<f32>> {
    let mut out = Vec::with_capacity(3 * dims.pixels());
    for p in files {
        let bytes = std::fs::read(p).map_err(|e| CoreError::io(p, e))?;
        let img = image::load_from_memory(&bytes)
            .map_err(|e| CoreError::format(p, "", format!("cannot decode image: {e}")))?
            .to_rgb8();
        let (w, h) = (img.width() as usize, img.height() as usize);
        let f: Vec<f32> = img.as_raw().iter().map(|&b| f32::from(b) / 255.0).collect();
        out.extend(if (h, w) == (dims.h, dims.w) {
            f
        } else {
            resize_bilinear(&f, h, w, 3, dims.h, dims.w, BilinearRounding::Separable)?
        });
    }
    Ok(out)
}

fn cams_arrays(c: &Cameras) -> Result<(NpyArray, NpyArray)> {
    let n = c.len();
    let e: Vec<f64> = c
        .cam_from_world
        .iter()
        .flat_map(|m| m.transpose().iter().copied().collect::<Vec<_>>())
        .collect();
    let k: Vec<f64> = c
        .intrinsics
        .iter()
        .flat_map(|m| m.transpose().iter().copied().collect::<Vec<_>>())
        .collect();
    Ok((
        NpyArray::new(vec![n, 3, 4], NpyData::F64(e))?,
        NpyArray::new(vec![n, 3, 3], NpyData::F64(k))?,
    ))
}

/// Writes `scene` as a §5.1 folder: `ff.npz` (f64 cameras, f32 `images` so the round trip is
/// lossless), `sfm.npz` when present, `matches/<matcher>.safetensors`, PNG previews in
/// `images/`. Ground truth is not written (the official `gt.bin` is a torch pickle). Atomic per file.
pub fn write_infer_folder(dir: &Path, scene: &Scene) -> Result<()> {
    scene.validate()?;
    let d = scene.dims;
    let (n, h, w) = (d.n, d.h, d.w);
    let ff = scene
        .ff
        .as_ref()
        .ok_or_else(|| CoreError::Invalid("a §5.1 folder needs feed-forward outputs".into()))?;
    let (e, k) = cams_arrays(&ff.cameras)?;
    let points = NpyArray::new(vec![n, h, w, 3], NpyData::F32(ff.points.clone()))?;
    let conf = NpyArray::new(vec![n, h, w], NpyData::F32(ff.conf.clone()))?;
    let images = NpyArray::new(vec![n, h, w, 3], NpyData::F32(scene.images.clone()))?;
    crate::io::npy::write_npz(
        &dir.join("ff.npz"),
        &[
            ("points", &points),
            ("conf", &conf),
            ("cam_from_world", &e),
            ("K", &k),
            ("images", &images),
        ],
        false,
    )?;
    if let Some(s) = &scene.sfm {
        let (e, k) = cams_arrays(&s.cameras)?;
        let points = NpyArray::new(vec![n, h, w, 3], NpyData::F32(s.points.clone()))?;
        let mask = NpyArray::new(vec![n, h, w], NpyData::Bool(s.mask.clone()))?;
        let cs = NpyArray::new(vec![], NpyData::Bool(vec![s.camera_success]))?;
        let ps = NpyArray::new(vec![], NpyData::Bool(vec![s.points_success]))?;
        let arrays = [
            ("cam_from_world", &e),
            ("K", &k),
            ("points", &points),
            ("mask", &mask),
            ("camera_success", &cs),
            ("points_success", &ps),
        ];
        crate::io::npy::write_npz(&dir.join("sfm.npz"), &arrays, false)?;
    }
    for m in &scene.matches {
        crate::io::matches::check_matcher_name(dir, &m.matcher)?;
        crate::io::matches::write_matches(
            &dir.join("matches")
                .join(format!("{}.safetensors", m.matcher)),
            m,
            n,
            h,
            w,
        )?;
    }
    for (i, px) in scene
        .images
        .chunks_exact((3 * d.hw()).max(1))
        .enumerate()
        .take(n)
    {
        let bytes: Vec<u8> = px
            .iter()
            .map(|&v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
            .collect();
        let path = dir.join("images").join(format!("{i:06}.png"));
        crate::io::png::write_rgb8(&path, w, h, &bytes)?;
    }
    Ok(())
}
