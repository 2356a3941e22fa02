//! Input readers of the `ggpt-sfm` binary (also usable from code):
//!
//! * feed-forward outputs: an `.npz` of VGGT / MapAnything / Pi3 outputs or the project's
//!   `ff.npz` (`ggpt_core::io::feedforward`, layout detected from the keys), the official
//!   `ff_outputs.bin`, a scene directory
//!   (`ggpt_core::io::read_scene`), or a safetensors file with the `ff/*` keys of the
//!   `sfm_small` fixture (`ff/images_ff`, `ff/extrinsics`, `ff/intrinsics`, `ff/points`,
//!   `ff/points_conf`);
//! * matches: the raw-matcher interchange safetensors layout (`docs/sfm.md`), a
//!   `formats.md` §5.2 `matches/<matcher>.safetensors` file, a folder of such files (a scene's
//!   `matches/`), or a scene directory's matches.
//!
//! All outputs are at ff resolution, ff pixels in the pixel-centre convention, cameras
//! `cam_from_world` (OpenCV).

use std::path::Path;

use ggpt_core::io::feedforward::{FfReadOptions, read_feed_forward_file};
use ggpt_core::io::st::StFile;
use ggpt_core::{Cameras, Dims, FeedForward};
use nalgebra::{Matrix3, Matrix3x4};

use crate::convert::{PairLayout, RawKind, RawMatches};
use crate::cycle::compute_cycle_errors;
use crate::error::{Result, SfmError};
use crate::matches::Correspondences;

/// Feed-forward input of the SfM stage.
#[derive(Debug, Clone, PartialEq)]
pub struct FfInput {
    /// Scene name (file or directory stem).
    pub name: String,
    /// Views and ff resolution.
    pub dims: Dims,
    /// `[N, h, w, 3]` RGB in `[0, 1]`.
    pub images: Vec<f32>,
    /// Feed-forward points, confidence and cameras.
    pub ff: FeedForward,
    /// Image file names when known (for the COLMAP export).
    pub image_names: Vec<String>,
}

/// Matches input of the SfM stage: one correspondence set per matcher (config order) and the
/// optional ranking score.
#[derive(Debug, Clone, PartialEq)]
pub struct MatchesInput {
    /// Matcher names.
    pub names: Vec<String>,
    /// Correspondences at ff resolution with cycle errors, diagonal applied.
    pub sets: Vec<Correspondences>,
    /// `[N hw]` ranking score of each source pixel (`sp_scores` / `rank_scores`).
    pub rank_scores: Option<Vec<f32>>,
}

/// File stems that name a layout, not a scene: such a file is named after its folder.
const GENERIC_STEMS: [&str; 4] = ["predictions", "ff", "ff_outputs", "inputs"];

/// The scene name of a feed-forward file: its stem (`work/kitchen.npz` -> `kitchen`), or its
/// folder's name for a generic stem (`kitchen/predictions.npz` -> `kitchen`).
fn stem(path: &Path) -> String {
    let s = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "scene".into());
    if GENERIC_STEMS.contains(&s.as_str())
        && let Some(dir) = path.canonicalize().ok().and_then(|p| {
            p.parent()
                .and_then(|d| d.file_name())
                .map(|d| d.to_string_lossy().into_owned())
        })
    {
        return dir;
    }
    s
}

/// Cameras from flat f32 `[N, 3, 4]` (or `[N, 4, 4]`) extrinsics and `[N, 3, 3]` intrinsics.
pub fn cameras_from_flat(
    path: &Path,
    n: usize,
    ext: &[f32],
    ext_rows: usize,
    intr: &[f32],
) -> Result<Cameras> {
    if ext.len() != n * ext_rows * 4 || intr.len() != n * 9 || !(ext_rows == 3 || ext_rows == 4) {
        return Err(SfmError::format(
            path,
            "extrinsics/intrinsics",
            format!("{} / {} values for {n} views", ext.len(), intr.len()),
        ));
    }
    let mut cam_from_world = Vec::with_capacity(n);
    let mut intrinsics = Vec::with_capacity(n);
    for v in 0..n {
        let e = &ext[v * ext_rows * 4..];
        cam_from_world.push(Matrix3x4::from_fn(|r, c| e[r * 4 + c] as f64));
        let k = &intr[v * 9..];
        intrinsics.push(Matrix3::from_fn(|r, c| k[r * 3 + c] as f64));
    }
    Ok(Cameras {
        cam_from_world,
        intrinsics,
    })
}

/// Reads the feed-forward input from `path` (see the module doc for the accepted forms).
pub fn read_ff(path: &Path) -> Result<FfInput> {
    read_ff_with(path, &FfReadOptions::default())
}

/// [`read_ff`] with the options of the `.npz` readers (VGGT branch, Pi3 intrinsics, a forced
/// layout; `ggpt_core::io::feedforward`).
pub fn read_ff_with(path: &Path, opts: &FfReadOptions) -> Result<FfInput> {
    if path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("npz"))
    {
        let r = read_feed_forward_file(path, opts)?;
        let images = r.images.ok_or_else(|| {
            SfmError::format(
                path,
                "images",
                "no images in the feed-forward outputs (the SfM ranks its tracks by image texture): save them with the prediction (VGGT's `images`)",
            )
        })?;
        return Ok(FfInput {
            name: stem(path),
            dims: r.dims,
            images,
            ff: r.ff,
            image_names: Vec::new(),
        });
    }
    if path.is_dir() {
        let scene = ggpt_core::io::read_scene(path)?;
        let ff = scene.ff.ok_or_else(|| {
            SfmError::format(
                path,
                "ff",
                "the scene directory has no feed-forward outputs",
            )
        })?;
        return Ok(FfInput {
            name: scene.name,
            dims: scene.dims,
            images: scene.images,
            ff,
            image_names: Vec::new(),
        });
    }
    // safetensors: 8-byte header length, then the JSON header starting with '{'
    let is_st = {
        use std::io::Read;
        let mut head = [0u8; 9];
        let mut f = std::fs::File::open(path).map_err(|e| SfmError::Io {
            path: path.to_path_buf(),
            source: e,
        })?;
        f.read_exact(&mut head).is_ok() && head[8] == b'{'
    };
    if !is_st {
        let b = ggpt_core::io::official::read_ff_outputs_bin(path)?;
        let n = b.dims.n;
        let rows = if b.extrinsics.len() == n * 16 { 4 } else { 3 };
        let cameras = cameras_from_flat(path, n, &b.extrinsics, rows, &b.intrinsics)?;
        let ff = FeedForward {
            points: b.points,
            conf: b.points_conf,
            cameras,
        };
        return Ok(FfInput {
            name: stem(path),
            dims: b.dims,
            images: b.images_ff,
            ff,
            image_names: Vec::new(),
        });
    }
    let f = StFile::open(path)?;
    let prefix = if f.has("ff/points") { "ff/" } else { "" };
    let key = |k: &str| format!("{prefix}{k}");
    let pts = f.f32_tensor(&key("points"))?;
    let (n, h, w) = match pts.shape.as_slice() {
        [n, h, w, 3] => (*n, *h, *w),
        s => {
            return Err(SfmError::format(
                path,
                key("points"),
                format!("shape {s:?} is not [N, h, w, 3]"),
            ));
        }
    };
    let dims = Dims { n, h, w };
    let images = f.f32_tensor(&key("images_ff"))?;
    f.expect_shape(&key("images_ff"), &images, &[n, h, w, 3])?;
    let conf_key = if f.has(&key("points_conf")) {
        key("points_conf")
    } else {
        key("conf")
    };
    let conf = f.f32_tensor(&conf_key)?;
    f.expect_shape(&conf_key, &conf, &[n, h, w])?;
    let ext = f.f32_tensor(&key("extrinsics"))?;
    let rows = match ext.shape.as_slice() {
        [m, r, 4] if *m == n && (*r == 3 || *r == 4) => *r,
        s => {
            return Err(SfmError::format(
                path,
                key("extrinsics"),
                format!("shape {s:?} is not [N={n}, 3|4, 4]"),
            ));
        }
    };
    let intr = f.f32_tensor(&key("intrinsics"))?;
    f.expect_shape(&key("intrinsics"), &intr, &[n, 3, 3])?;
    let cameras = cameras_from_flat(path, n, &ext.data, rows, &intr.data)?;
    let ff = FeedForward {
        points: pts.data,
        conf: conf.data,
        cameras,
    };
    Ok(FfInput {
        name: stem(path),
        dims,
        images: images.data,
        ff,
        image_names: Vec::new(),
    })
}

/// Reads the matches from `path` for a scene of dims `dims` (see the module doc).
/// Shape mismatches between the matches and the images are errors naming the file and key.
pub fn read_matches(path: &Path, dims: Dims) -> Result<MatchesInput> {
    if path.is_dir() {
        if ggpt_core::io::detect_layout(path).is_ok() {
            let scene = ggpt_core::io::read_scene(path)?;
            if scene.dims != dims {
                return Err(SfmError::Shape(format!(
                    "{}: matches are for N={} h={} w={}, the feed-forward images are N={} h={} w={}",
                    path.display(),
                    scene.dims.n,
                    scene.dims.h,
                    scene.dims.w,
                    dims.n,
                    dims.h,
                    dims.w
                )));
            }
            return from_match_sets(path, &scene.matches, dims);
        }
        // a matches folder (a scene's `matches/`): every `*.safetensors` in name order
        let mut files: Vec<std::path::PathBuf> = std::fs::read_dir(path)
            .map_err(|e| SfmError::Io {
                path: path.to_path_buf(),
                source: e,
            })?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|e| e == "safetensors"))
            .collect();
        files.sort();
        if files.is_empty() {
            return Err(SfmError::format(
                path,
                "matches",
                "neither a scene folder nor a folder of matches (*.safetensors)",
            ));
        }
        let mut out = MatchesInput {
            names: Vec::new(),
            sets: Vec::new(),
            rank_scores: None,
        };
        for f in &files {
            let m = read_match_file(f, dims)?;
            out.names.extend(m.names);
            out.sets.extend(m.sets);
            if out.rank_scores.is_none() {
                out.rank_scores = m.rank_scores;
            }
        }
        return Ok(out);
    }
    read_match_file(path, dims)
}

/// One matches file: a project `<matcher>.safetensors` (`pred_matches`, ...) or the raw-matcher
/// interchange layout ([`read_raw_matches`]).
fn read_match_file(path: &Path, dims: Dims) -> Result<MatchesInput> {
    let f = StFile::open(path)?;
    if f.has("pred_matches") {
        let mf = ggpt_core::io::matches::read_matches(path)?;
        if (mf.n, mf.h, mf.w) != (dims.n, dims.h, dims.w) {
            return Err(SfmError::format(
                path,
                "pred_matches",
                format!(
                    "matches are for N={} h={} w={}, the images are N={} h={} w={}",
                    mf.n, mf.h, mf.w, dims.n, dims.h, dims.w
                ),
            ));
        }
        return from_match_sets(path, std::slice::from_ref(&mf.set), dims);
    }
    read_raw_matches(&f, dims)
}

/// Reads the feed-forward input (`ff`, see [`read_ff`]) and the matches (`matches`, see
/// [`read_matches`]); when both name the same scene directory it is read only once (a 16-view
/// 518 x 392 scene with two matchers is ~1.4 GB).
pub fn read_inputs(ff: &Path, matches: &Path) -> Result<(FfInput, MatchesInput)> {
    let same_dir = ff.is_dir() && matches.is_dir() && {
        match (std::fs::canonicalize(ff), std::fs::canonicalize(matches)) {
            (Ok(a), Ok(b)) => a == b,
            _ => ff == matches,
        }
    };
    if same_dir {
        let scene = ggpt_core::io::read_scene(ff)?;
        let m = from_match_sets(matches, &scene.matches, scene.dims)?;
        let ffo = scene.ff.ok_or_else(|| {
            SfmError::format(ff, "ff", "the scene directory has no feed-forward outputs")
        })?;
        return Ok((
            FfInput {
                name: scene.name,
                dims: scene.dims,
                images: scene.images,
                ff: ffo,
                image_names: Vec::new(),
            },
            m,
        ));
    }
    let f = read_ff(ff)?;
    let m = read_matches(matches, f.dims)?;
    Ok((f, m))
}

fn from_match_sets(path: &Path, sets: &[ggpt_core::MatchSet], dims: Dims) -> Result<MatchesInput> {
    if sets.is_empty() {
        return Err(SfmError::format(path, "matches", "no matches found"));
    }
    let mut out = MatchesInput {
        names: Vec::new(),
        sets: Vec::new(),
        rank_scores: None,
    };
    for s in sets {
        out.names.push(s.matcher.clone());
        out.sets.push(Correspondences::from_match_set(s, dims)?);
        if out.rank_scores.is_none() {
            out.rank_scores = s.rank_scores.clone();
        }
    }
    Ok(out)
}

/// Reads the raw-matcher interchange layout (`docs/sfm.md`), keys optionally prefixed `match/`:
/// `m{i}_warp` `[N, N, Hm, Wm, 2]` + `m{i}_overlap` `[N, N, Hm, Wm]` (RoMa: normalised edge
/// coordinates at matcher resolution, `[s, t]` = warp of view `s` into `t`), or `m{i}_flow`
/// `[N, N, 2, Ho, Wo]` + `m{i}_covisibility` `[N, N, Ho, Wo]` (UFM: flow in output pixels), or
/// `m{i}_pixwarp` `[N, N, Hm, Wm, 2]` + `m{i}_score` (generic matcher, matcher-pixel
/// coordinates); `i = 0, 1, ...` consecutive; optional `sp_scores` / `rank_scores` `[N, h*w]`.
pub fn read_raw_matches(f: &StFile, dims: Dims) -> Result<MatchesInput> {
    let path = f.path().to_path_buf();
    let prefix = if f.keys().iter().any(|k| k.starts_with("match/")) {
        "match/"
    } else {
        ""
    };
    let (n, h, w) = (dims.n, dims.h, dims.w);
    let hw = h * w;
    let mut out = MatchesInput {
        names: Vec::new(),
        sets: Vec::new(),
        rank_scores: None,
    };
    for i in 0.. {
        let k = |s: &str| format!("{prefix}m{i}_{s}");
        let (kind, pk, sk, name) = if f.has(&k("warp")) {
            (
                RawKind::RomaWarp,
                k("warp"),
                k("overlap"),
                format!("roma-{i}"),
            )
        } else if f.has(&k("pixwarp")) {
            (
                RawKind::PixelWarp,
                k("pixwarp"),
                k("score"),
                format!("generic-{i}"),
            )
        } else if f.has(&k("flow")) {
            (
                RawKind::UfmFlow,
                k("flow"),
                k("covisibility"),
                format!("ufm-{i}"),
            )
        } else {
            break;
        };
        let primary = f.f32_tensor(&pk)?;
        let score = f.f32_tensor(&sk)?;
        let raw = RawMatches {
            kind,
            layout: PairLayout::SourceTarget,
            primary: &primary.data,
            primary_shape: &primary.shape,
            score: &score.data,
            score_shape: &score.shape,
        };
        let what = format!("{pk} / {sk}");
        let (matches, scores) = raw.to_ff(n, h, w, &what).map_err(|e| match e {
            SfmError::Shape(m) => SfmError::format(&path, &pk, m),
            e => e,
        })?;
        let mut corr = Correspondences {
            dims,
            matches,
            scores,
            cycle: vec![0.0; n * n * hw],
        };
        corr.apply_diagonal();
        corr.sanitize();
        compute_cycle_errors(&mut corr)?;
        corr.apply_diagonal();
        out.names.push(name);
        out.sets.push(corr);
    }
    if out.sets.is_empty() {
        return Err(SfmError::format(
            &path,
            format!("{prefix}m0_*"),
            "no matcher output found (expected m0_warp/m0_overlap, m0_flow/m0_covisibility or m0_pixwarp/m0_score, or pred_matches)",
        ));
    }
    for rk in ["sp_scores", "rank_scores"] {
        let key = format!("{prefix}{rk}");
        if f.has(&key) {
            let r = f.f32_tensor(&key)?;
            f.expect_shape(&key, &r, &[n, hw])?;
            out.rank_scores = Some(r.data);
            break;
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ggpt_core::io::st::StWriter;

    fn write(dir: &Path, name: &str, t: StWriter) -> std::path::PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, t.finish(&p, None).unwrap()).unwrap();
        p
    }

    fn ff_tensors(n: usize, h: usize, w: usize, img_h: usize) -> StWriter {
        let px = n * h * w;
        let mut ext = Vec::new();
        let mut k = Vec::new();
        for _ in 0..n {
            ext.extend([
                1.0f32, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0,
            ]);
            k.extend([
                10.0f32,
                0.0,
                (w as f32 - 1.0) / 2.0,
                0.0,
                10.0,
                (h as f32 - 1.0) / 2.0,
                0.0,
                0.0,
                1.0,
            ]);
        }
        let mut t = StWriter::new();
        t.f32("ff/points", &[n, h, w, 3], &vec![1.0; 3 * px]);
        t.f32(
            "ff/images_ff",
            &[n, img_h, w, 3],
            &vec![0.5; 3 * n * img_h * w],
        );
        t.f32("ff/points_conf", &[n, h, w], &vec![1.0; px]);
        t.f32("ff/extrinsics", &[n, 3, 4], &ext);
        t.f32("ff/intrinsics", &[n, 3, 3], &k);
        t
    }

    #[test]
    fn ff_safetensors_ok_and_shape_errors() {
        let dir = tempfile::tempdir().unwrap();
        let p = write(dir.path(), "ok.safetensors", ff_tensors(2, 3, 4, 3));
        let ff = read_ff(&p).unwrap();
        assert_eq!(ff.dims, Dims { n: 2, h: 3, w: 4 });
        assert_eq!(ff.ff.cameras.intrinsics[1][(0, 2)], 1.5);
        let p = write(dir.path(), "bad.safetensors", ff_tensors(2, 3, 4, 5));
        let e = read_ff(&p).unwrap_err().to_string();
        assert!(
            e.contains("bad.safetensors") && e.contains("ff/images_ff"),
            "{e}"
        );
    }

    #[test]
    fn vggt_predictions_npz() {
        use ggpt_core::io::npy::{NpyArray, NpyData, write_npz};
        let dir = tempfile::tempdir().unwrap();
        let (n, h, w) = (2usize, 3usize, 4usize);
        let f = |shape: &[usize], v: f32| {
            NpyArray::new(
                shape.to_vec(),
                NpyData::F32(vec![v; shape.iter().product()]),
            )
            .unwrap()
        };
        let mut ext = f(&[1, n, 3, 4], 0.0);
        let mut k = f(&[1, n, 3, 3], 0.0);
        if let (NpyData::F32(e), NpyData::F32(kk)) = (&mut ext.data, &mut k.data) {
            for v in 0..n {
                for i in 0..3 {
                    e[12 * v + 5 * i] = 1.0;
                }
                kk[9 * v..9 * v + 9]
                    .copy_from_slice(&[5.0, 0.0, 2.0, 0.0, 5.0, 1.5, 0.0, 0.0, 1.0]);
            }
        }
        let arrays = [
            ("extrinsic", ext),
            ("intrinsic", k),
            ("depth", f(&[1, n, h, w, 1], 2.0)),
            ("depth_conf", f(&[1, n, h, w], 3.0)),
            ("images", f(&[1, n, 3, h, w], 0.5)),
        ];
        let p = dir.path().join("predictions.npz");
        let refs: Vec<(&str, &NpyArray)> = arrays.iter().map(|(k, a)| (*k, a)).collect();
        write_npz(&p, &refs, false).unwrap();
        let ff = read_ff(&p).unwrap();
        assert_eq!(ff.dims, Dims { n, h, w });
        // a generic file name: the scene is named after the folder
        let folder = dir.path().canonicalize().unwrap();
        assert_eq!(ff.name, folder.file_name().unwrap().to_string_lossy());
        // pixel (x=2, y=1) of view 0 sits on the principal point's ray: (0, 0, 2)
        let i = 3 * (w + 2);
        assert_eq!(&ff.ff.points[i..i + 3], &[0.0, -0.2, 2.0]);
        let no_images = dir.path().join("no_images.npz");
        write_npz(&no_images, &refs[..4], false).unwrap();
        let e = read_ff(&no_images).unwrap_err().to_string();
        assert!(e.contains("no_images.npz") && e.contains("[images]"), "{e}");
    }

    #[test]
    fn raw_matches_shape_errors_and_ufm_conversion() {
        let dir = tempfile::tempdir().unwrap();
        let (n, h, w) = (2, 3, 4);
        let hw = h * w;
        // UFM-style flow +1 px in x everywhere, covisibility 0.9
        let mut flow = vec![0f32; n * n * 2 * hw];
        for p in 0..n * n {
            flow[p * 2 * hw..p * 2 * hw + hw]
                .iter_mut()
                .for_each(|v| *v = 1.0);
        }
        let mut t = StWriter::new();
        t.f32("match/m0_flow", &[n, n, 2, h, w], &flow);
        t.f32(
            "match/m0_covisibility",
            &[n, n, h, w],
            &vec![0.9; n * n * hw],
        );
        let p = write(dir.path(), "m.safetensors", t);
        let m = read_matches(&p, Dims { n, h, w }).unwrap();
        assert_eq!(m.sets.len(), 1);
        let c = &m.sets[0];
        let i = c.idx(1, 0, 0);
        assert_eq!(
            (c.matches[2 * i], c.matches[2 * i + 1], c.scores[i]),
            (1.0, 0.0, 0.9)
        );
        let j = c.idx(1, 0, 3); // x = 3 -> 4 leaves the image: score 0
        assert_eq!(c.scores[j], 0.0);
        assert!(m.rank_scores.is_none());
        let e = read_matches(&p, Dims { n: 3, h, w })
            .unwrap_err()
            .to_string();
        assert!(e.contains("m0_flow") && e.contains("N=3"), "{e}");
        let mut t = StWriter::new();
        t.f32("x", &[1], &[0.0]);
        let empty = write(dir.path(), "e.safetensors", t);
        let e = read_matches(&empty, Dims { n, h, w })
            .unwrap_err()
            .to_string();
        assert!(e.contains("no matcher output"), "{e}");
    }
}
