//! The project's own scene directory (lossless round trip of [`Scene`]), plus detection of the
//! other accepted layouts (official three-file dir, `formats.md` §5.1 folder).
//!
//! ```text
//! <dir>/scene.json                  manifest: format, version, name, n/h/w, parts, matchers, crc32 per file
//! <dir>/scene.safetensors           images F32 [N,h,w,3]; gt/*, ff/*, sfm/* (see below)
//! <dir>/matches/<matcher>.safetensors  formats.md §5.2 layout, coords = ff-pixel-center
//! <dir>/images/000000.png ...       u8 previews for humans (not read back)
//! ```
//!
//! `scene.safetensors` keys: `images`; `gt/points` F32 `[N,h,w,3]`, `gt/mask` BOOL `[N,h,w]`,
//! optional `gt/depth` F32 `[N,h,w]`, `gt/cam_from_world` F64 `[N,3,4]`, `gt/K` F64 `[N,3,3]`;
//! `ff/points`, `ff/conf` F32 `[N,h,w]`, `ff/cam_from_world`, `ff/K`; `sfm/points`, `sfm/mask`,
//! `sfm/cam_from_world`, `sfm/K`, `sfm/camera_success` and `sfm/points_success` 0-d BOOL. Points
//! are in the frame of their part (GT world metres, feed-forward frame, SfM frame); cameras are
//! `cam_from_world` (OpenCV) and K in ff pixels, pixel-centre convention.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::io::atomic::write_bytes_atomic;
use crate::io::matches::{check_matcher_name, encode_matches, read_matches_raw};
use crate::io::st::{StFile, StWriter, check_finite_f32};
use crate::{Cameras, CoreError, Dims, FeedForward, GroundTruth, Result, Scene, SfmResult};

/// Manifest file name.
pub const MANIFEST: &str = "scene.json";
/// Tensor file name.
pub const TENSORS: &str = "scene.safetensors";
/// `format` field of the manifest.
pub const FORMAT_NAME: &str = "ggpt-rs-scene";
/// Manifest version written (and the only one read).
pub const FORMAT_VERSION: u32 = 1;

/// Which optional parts a scene directory holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Parts {
    /// Ground truth (`gt/*`).
    pub gt: bool,
    /// `gt/depth` present (only with `gt`).
    pub gt_depth: bool,
    /// Feed-forward prediction (`ff/*`).
    pub ff: bool,
    /// SfM result (`sfm/*`).
    pub sfm: bool,
}

/// Size and CRC-32 (IEEE, lowercase hex) of one data file.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileSum {
    /// Path relative to the scene directory (`/`-separated).
    pub path: String,
    /// Size in bytes.
    pub bytes: u64,
    /// CRC-32 of the whole file, 8 lowercase hex digits.
    pub crc32: String,
}

/// Contents of `scene.json`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    /// Always [`FORMAT_NAME`].
    pub format: String,
    /// [`FORMAT_VERSION`].
    pub version: u32,
    /// Scene name.
    pub name: String,
    /// Number of views.
    pub n: usize,
    /// ff height.
    pub h: usize,
    /// ff width.
    pub w: usize,
    /// Parts present.
    pub parts: Parts,
    /// Matcher names, in scene order; file `matches/<name>.safetensors` each.
    pub matchers: Vec<String>,
    /// Checksums of `scene.safetensors` and every matches file.
    pub files: Vec<FileSum>,
}

/// Writes `scene` as a project scene directory (creating `dir`); every file is written
/// atomically and the manifest last, so a partially written directory fails its checksums.
pub fn write_scene(dir: &Path, scene: &Scene) -> Result<()> {
    scene.validate()?;
    let d = scene.dims;
    let mut files = Vec::new();
    let tensors_path = dir.join(TENSORS);
    let bytes = encode_tensors(&tensors_path, scene)?;
    write_bytes_atomic(&tensors_path, &bytes)?;
    files.push(file_sum(TENSORS, &bytes));
    let mut matchers = Vec::new();
    for m in &scene.matches {
        check_matcher_name(dir, &m.matcher)?;
        if matchers.contains(&m.matcher) {
            return Err(CoreError::Invalid(format!(
                "duplicate matcher name '{}'",
                m.matcher
            )));
        }
        let rel = format!("matches/{}.safetensors", m.matcher);
        let p = dir.join(&rel);
        let bytes = encode_matches(&p, m, d.n, d.h, d.w)?;
        write_bytes_atomic(&p, &bytes)?;
        files.push(file_sum(&rel, &bytes));
        matchers.push(m.matcher.clone());
    }
    write_previews(dir, scene)?;
    let manifest = Manifest {
        format: FORMAT_NAME.to_string(),
        version: FORMAT_VERSION,
        name: scene.name.clone(),
        n: d.n,
        h: d.h,
        w: d.w,
        parts: Parts {
            gt: scene.gt.is_some(),
            gt_depth: scene.gt.as_ref().is_some_and(|g| g.depth.is_some()),
            ff: scene.ff.is_some(),
            sfm: scene.sfm.is_some(),
        },
        matchers,
        files,
    };
    let mpath = dir.join(MANIFEST);
    let json = serde_json::to_vec_pretty(&manifest)
        .map_err(|e| CoreError::format(&mpath, "", format!("cannot encode manifest: {e}")))?;
    write_bytes_atomic(&mpath, &json)
}

fn file_sum(rel: &str, bytes: &[u8]) -> FileSum {
    FileSum {
        path: rel.to_string(),
        bytes: bytes.len() as u64,
        crc32: format!("{:08x}", crc32fast::hash(bytes)),
    }
}

fn encode_tensors(path: &Path, scene: &Scene) -> Result<Vec<u8>> {
    let d = scene.dims;
    let (n, h, w) = (d.n, d.h, d.w);
    let mut st = StWriter::new();
    st.f32("images", &[n, h, w, 3], &scene.images);
    if let Some(gt) = &scene.gt {
        st.f32("gt/points", &[n, h, w, 3], &gt.points);
        st.bool("gt/mask", &[n, h, w], &gt.mask);
        if let Some(depth) = &gt.depth {
            st.f32("gt/depth", &[n, h, w], depth);
        }
        put_cameras(&mut st, "gt", &gt.cameras);
    }
    if let Some(ff) = &scene.ff {
        st.f32("ff/points", &[n, h, w, 3], &ff.points);
        st.f32("ff/conf", &[n, h, w], &ff.conf);
        put_cameras(&mut st, "ff", &ff.cameras);
    }
    if let Some(sfm) = &scene.sfm {
        st.f32("sfm/points", &[n, h, w, 3], &sfm.points);
        st.bool("sfm/mask", &[n, h, w], &sfm.mask);
        put_cameras(&mut st, "sfm", &sfm.cameras);
        st.bool("sfm/camera_success", &[], &[sfm.camera_success]);
        st.bool("sfm/points_success", &[], &[sfm.points_success]);
    }
    st.finish(path, None)
}

fn put_cameras(st: &mut StWriter, part: &str, c: &Cameras) {
    st.extrinsics(&format!("{part}/cam_from_world"), &c.cam_from_world);
    st.intrinsics(&format!("{part}/K"), &c.intrinsics);
}

/// Writes `images/{i:06d}.png` previews (u8, `round(255 * clamp(v, 0, 1))`).
fn write_previews(dir: &Path, scene: &Scene) -> Result<()> {
    let d = scene.dims;
    let view = 3 * d.hw();
    for (i, px) in scene.images.chunks_exact(view.max(1)).enumerate().take(d.n) {
        let bytes: Vec<u8> = px
            .iter()
            .map(|&v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
            .collect();
        let path = dir.join("images").join(format!("{i:06}.png"));
        crate::io::png::write_rgb8(&path, d.w, d.h, &bytes)?;
    }
    Ok(())
}

/// Reads and checks `scene.json`.
pub fn read_manifest(dir: &Path) -> Result<Manifest> {
    let path = dir.join(MANIFEST);
    let bytes = std::fs::read(&path).map_err(|e| CoreError::io(&path, e))?;
    let m: Manifest = serde_json::from_slice(&bytes)
        .map_err(|e| CoreError::format(&path, "", format!("invalid manifest JSON: {e}")))?;
    if m.format != FORMAT_NAME {
        return Err(CoreError::format(
            &path,
            "format",
            format!("'{}' is not {FORMAT_NAME}", m.format),
        ));
    }
    if m.version != FORMAT_VERSION {
        return Err(CoreError::format(
            &path,
            "version",
            format!(
                "unsupported version {} (this build reads {FORMAT_VERSION})",
                m.version
            ),
        ));
    }
    if m.n == 0 || m.h == 0 || m.w == 0 {
        return Err(CoreError::format(
            &path,
            "n/h/w",
            format!("empty scene: n={} h={} w={}", m.n, m.h, m.w),
        ));
    }
    if m.parts.gt_depth && !m.parts.gt {
        return Err(CoreError::format(
            &path,
            "parts.gt_depth",
            "gt_depth without gt",
        ));
    }
    for name in &m.matchers {
        check_matcher_name(&path, name)?;
    }
    Ok(m)
}

/// Reads a data file listed in the manifest and checks its size and CRC-32.
fn read_checked(dir: &Path, m: &Manifest, rel: &str) -> Result<(PathBuf, Vec<u8>)> {
    let path = dir.join(rel);
    let sum = m.files.iter().find(|f| f.path == rel).ok_or_else(|| {
        CoreError::format(
            dir.join(MANIFEST),
            "files",
            format!("no checksum entry for {rel}"),
        )
    })?;
    // A mismatch is in the data file or in the manifest: the message names both.
    let manifest = dir.join(MANIFEST);
    let bytes = std::fs::read(&path).map_err(|e| {
        CoreError::format(
            &path,
            "",
            format!("cannot read the file listed in {}: {e}", manifest.display()),
        )
    })?;
    if bytes.len() as u64 != sum.bytes {
        return Err(CoreError::format(
            &path,
            "bytes",
            format!(
                "size {} differs from the {} of {} (truncated or replaced file, or edited manifest)",
                bytes.len(),
                sum.bytes,
                manifest.display()
            ),
        ));
    }
    let crc = format!("{:08x}", crc32fast::hash(&bytes));
    if crc != sum.crc32.to_ascii_lowercase() {
        return Err(CoreError::format(
            &path,
            "crc32",
            format!(
                "checksum mismatch: file has {crc}, {} says {} (corrupt file or edited manifest)",
                manifest.display(),
                sum.crc32
            ),
        ));
    }
    Ok((path, bytes))
}

/// Reads a project scene directory (no `Scene::validate`; [`read_scene`] adds it).
pub(crate) fn read_project_scene(dir: &Path) -> Result<Scene> {
    let m = read_manifest(dir)?;
    let (path, bytes) = read_checked(dir, &m, TENSORS)?;
    let f = StFile::from_bytes(&path, bytes)?;
    let manifest = dir.join(MANIFEST);
    let layout = |e| with_layout_source(e, &manifest);
    check_keys(&f, &m).map_err(layout)?;
    let (n, h, w) = (m.n, m.h, m.w);
    let images = f.f32_finite("images", &[n, h, w, 3]).map_err(layout)?;
    let gt = if m.parts.gt {
        Some(read_gt(&f, &m).map_err(layout)?)
    } else {
        None
    };
    let ff = if m.parts.ff {
        Some(read_ff(&f, n, h, w).map_err(layout)?)
    } else {
        None
    };
    let sfm = if m.parts.sfm {
        Some(read_sfm(&f, n, h, w).map_err(layout)?)
    } else {
        None
    };
    let mut matches = Vec::new();
    for name in &m.matchers {
        let rel = format!("matches/{name}.safetensors");
        read_checked(dir, &m, &rel)?;
        let mf = read_matches_raw(&dir.join(&rel))?;
        if (mf.n, mf.h, mf.w) != (n, h, w) {
            return Err(CoreError::format(
                dir.join(&rel),
                "pred_matches",
                format!(
                    "N={} h={} w={} differ from N={n} h={h} w={w} of {}",
                    mf.n,
                    mf.h,
                    mf.w,
                    dir.join(MANIFEST).display()
                ),
            ));
        }
        let mut set = mf.set;
        set.matcher = name.clone();
        matches.push(set);
    }
    Ok(Scene {
        name: m.name.clone(),
        dims: Dims { n, h, w },
        images,
        gt,
        ff,
        sfm,
        matches,
    })
}

/// A shape or key mismatch of `scene.safetensors` is in that file or in the manifest that
/// describes it (`N`, `h`, `w`, parts): the message then names the manifest too.
fn with_layout_source(e: CoreError, manifest: &Path) -> CoreError {
    match e {
        CoreError::Format { path, key, message }
            if message.contains("shape") || message.contains("manifest's parts") =>
        {
            CoreError::Format {
                path,
                key,
                message: format!("{message} (layout from {})", manifest.display()),
            }
        }
        other => other,
    }
}

/// Every tensor the manifest implies must exist and no other may.
fn check_keys(f: &StFile, m: &Manifest) -> Result<()> {
    let mut want = vec!["images".to_string()];
    let cams = |p: &str| [format!("{p}/cam_from_world"), format!("{p}/K")];
    if m.parts.gt {
        want.extend(["gt/points".into(), "gt/mask".into()]);
        want.extend(cams("gt"));
        if m.parts.gt_depth {
            want.push("gt/depth".into());
        }
    }
    if m.parts.ff {
        want.extend(["ff/points".into(), "ff/conf".into()]);
        want.extend(cams("ff"));
    }
    if m.parts.sfm {
        want.extend([
            "sfm/points".into(),
            "sfm/mask".into(),
            "sfm/camera_success".into(),
            "sfm/points_success".into(),
        ]);
        want.extend(cams("sfm"));
    }
    for k in &want {
        if !f.has(k) {
            return Err(f.err(k, "missing tensor (required by the manifest's parts)"));
        }
    }
    for k in f.keys() {
        if !want.contains(&k) {
            return Err(f.err(
                &k,
                "unexpected tensor (not implied by the manifest's parts)",
            ));
        }
    }
    Ok(())
}

fn read_cameras(f: &StFile, part: &str, n: usize) -> Result<Cameras> {
    Ok(Cameras {
        cam_from_world: f.extrinsics_f64(&format!("{part}/cam_from_world"), n)?,
        intrinsics: f.intrinsics_f64(&format!("{part}/K"), n)?,
    })
}

fn read_gt(f: &StFile, m: &Manifest) -> Result<GroundTruth> {
    let (n, h, w) = (m.n, m.h, m.w);
    let depth = if m.parts.gt_depth {
        Some(f.f32_finite("gt/depth", &[n, h, w])?)
    } else {
        None
    };
    Ok(GroundTruth {
        points: f.f32_finite("gt/points", &[n, h, w, 3])?,
        mask: f.bool("gt/mask", &[n, h, w])?,
        depth,
        cameras: read_cameras(f, "gt", n)?,
    })
}

fn read_ff(f: &StFile, n: usize, h: usize, w: usize) -> Result<FeedForward> {
    let conf = f.f32("ff/conf", &[n, h, w])?;
    check_finite_f32(f.path(), "ff/conf", &conf)?;
    Ok(FeedForward {
        points: f.f32_finite("ff/points", &[n, h, w, 3])?,
        conf,
        cameras: read_cameras(f, "ff", n)?,
    })
}

fn read_sfm(f: &StFile, n: usize, h: usize, w: usize) -> Result<SfmResult> {
    Ok(SfmResult {
        points: f.f32_finite("sfm/points", &[n, h, w, 3])?,
        mask: f.bool("sfm/mask", &[n, h, w])?,
        cameras: read_cameras(f, "sfm", n)?,
        camera_success: f.scalar_bool("sfm/camera_success")?,
        points_success: f.scalar_bool("sfm/points_success")?,
    })
}
