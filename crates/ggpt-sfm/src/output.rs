//! Writers of the `ggpt-sfm` binary's outputs: `sfm_dlt_outputs.safetensors`, the COLMAP model
//! and `summary.json`. Every file is written atomically.

use std::collections::HashMap;
use std::path::Path;

use ggpt_core::io::atomic::write_bytes_atomic;
use ggpt_core::io::colmap::{
    ColmapCamera, ColmapCameraModel, ColmapImage, ColmapModel, ColmapPoint2D, ColmapPoint3D,
    pixel_to_colmap, qvec_to_rotation, write_colmap,
};
use ggpt_core::io::st::StWriter;
use ggpt_core::{Dims, SfmResult};
use nalgebra::{Point3, Vector3};

use crate::ba::{CameraModel, MIN_DEPTH};
use crate::dlt::DltStatus;
use crate::error::Result;
use crate::pipeline::SfmOutput;

/// Serialises the SfM result as safetensors with the keys of the official
/// `sfm_dlt_outputs.bin`: `points` F32 `[N,h,w,3]` (SfM frame), `point_masks` BOOL `[N,h,w]`,
/// `intrinsics` F32 `[N,3,3]` (pixel-centre convention), `extrinsics` F32 `[N,3,4]`
/// (`cam_from_world`), plus `camera_success` / `points_success` BOOL `[]`, `dlt_count` U16 and
/// `dlt_reproj` F32 `[N,h,w]`.
pub fn encode_sfm_safetensors(
    res: &SfmResult,
    dims: Dims,
    dlt_count: &[u16],
    dlt_reproj: &[f32],
) -> Result<Vec<u8>> {
    let (n, h, w) = (dims.n, dims.h, dims.w);
    let intr: Vec<f32> = res
        .cameras
        .intrinsics
        .iter()
        .flat_map(|k| (0..9).map(move |i| k[(i / 3, i % 3)] as f32))
        .collect();
    let ext: Vec<f32> = res
        .cameras
        .cam_from_world
        .iter()
        .flat_map(|e| (0..12).map(move |i| e[(i / 4, i % 4)] as f32))
        .collect();
    let mut st = StWriter::new();
    st.f32("points", &[n, h, w, 3], &res.points);
    st.bool("point_masks", &[n, h, w], &res.mask);
    st.f32("intrinsics", &[n, 3, 3], &intr);
    st.f32("extrinsics", &[n, 3, 4], &ext);
    st.bool("camera_success", &[], &[res.camera_success]);
    st.bool("points_success", &[], &[res.points_success]);
    st.u16("dlt_count", &[n, h, w], dlt_count);
    st.f32("dlt_reproj", &[n, h, w], dlt_reproj);
    let meta = HashMap::from([("format".to_string(), "ggpt-sfm".to_string())]);
    Ok(st.finish(Path::new("sfm_dlt_outputs.safetensors"), Some(meta))?)
}

/// Which 3D points the COLMAP model `sparse/0/` holds (`ggpt-sfm run --colmap-points`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum ColmapPoints {
    /// The BA tracks (default): the points optimised by the bundle adjustment with their BA
    /// observations (see [`colmap_model`] for the filter).
    #[default]
    Ba,
    /// Every kept DLT track with its full DLT track (millions of points for large scenes: the
    /// 16-view 518 x 392 `images.bin` is about 1 GB).
    Dlt,
    /// Cameras and images only.
    None,
}

/// Settings of the COLMAP export.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ColmapExport {
    /// Which points to write.
    pub points: ColmapPoints,
    /// BA points: an observation whose reprojection error with the written camera exceeds this
    /// (pixels), or whose point lies behind that camera, is left out (`ggpt-sfm run` passes
    /// `--max-reproj-error`, the preset's value: 4 / 2 / 1 px, like COLMAP's 4 px
    /// `filter_max_reproj_error`).
    pub max_reproj_error: f64,
    /// Camera model written (the BA's).
    pub model: CameraModel,
    /// One shared camera (`true`) or one per view.
    pub shared: bool,
}

impl Default for ColmapExport {
    fn default() -> Self {
        ColmapExport {
            points: ColmapPoints::Ba,
            max_reproj_error: 4.0,
            model: CameraModel::Pinhole,
            shared: true,
        }
    }
}

/// What the COLMAP export wrote (recorded as `colmap` in `summary.json`).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ColmapSummary {
    /// Points source (`ba`, `dlt`, `none`).
    pub points: ColmapPoints,
    /// BA points: refined by the BA (`true`) or triangulated from the BA observations with the
    /// output cameras because the BA was skipped or failed (`false`).
    pub ba_points_refined: bool,
    /// Candidate points (BA tracks, or kept DLT tracks).
    pub candidates: usize,
    /// Points written to `points3D.bin`.
    pub points3d: usize,
    /// Observations written (`POINTS2D` with a `POINT3D_ID`; = sum of the track lengths).
    pub observations: usize,
    /// BA observations left out (behind the camera or reprojection error above the threshold).
    pub dropped_observations: usize,
    /// BA tracks left out (non-finite point, or fewer than two observations left).
    pub dropped_points: usize,
    /// Mean over the written points of their `ERROR` (mean reprojection error of the track,
    /// pixels); NaN when no point was written.
    pub mean_reprojection_error: f64,
    /// Largest reprojection error of a written observation (pixels); 0 when none.
    pub max_reprojection_error: f64,
}

/// Projects the world point `x` into image `im` with camera `cam` of a COLMAP model built here
/// (`SIMPLE_PINHOLE` / `PINHOLE`): COLMAP pixels (corner convention), `None` behind the camera
/// (`z <= MIN_DEPTH`).
fn project_colmap(cam: &ColmapCamera, im: &ColmapImage, x: &Point3<f64>) -> Option<[f64; 2]> {
    let p = qvec_to_rotation(im.qvec) * x.coords + Vector3::from(im.tvec);
    let (fx, fy, cx, cy) = match (cam.model, cam.params.as_slice()) {
        (ColmapCameraModel::SimplePinhole, [f, cx, cy]) => (*f, *f, *cx, *cy),
        (ColmapCameraModel::Pinhole, [fx, fy, cx, cy]) => (*fx, *fy, *cx, *cy),
        _ => return None,
    };
    (p.z > MIN_DEPTH).then(|| [fx * p.x / p.z + cx, fy * p.y / p.z + cy])
}

fn source_rgb(images: &[f32], j: usize) -> [u8; 3] {
    let c = |i: usize| {
        images
            .get(3 * j + i)
            .map_or(0, |v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
    };
    [c(0), c(1), c(2)]
}

/// Builds the COLMAP model of a run (`formats.md` §6.2, corner convention `x_colmap = x + 0.5`,
/// Hamilton `(qw, qx, qy, qz)` of `cam_from_world`, ids from 1) at ff resolution: one shared camera
/// (or one per view) of the BA model, the SfM cameras (images `1..N`, named `image_names[v]` or
/// `000000.jpg, ...`), and as `points3D`:
///
/// * [`ColmapPoints::Ba`]: each BA track `i` ([`SfmOutput::ba_points`], in ascending track id)
///   with its BA observations (one per observing view, the view's own pixel included). An
///   observation is kept when the point lies in front of the written camera and reprojects within
///   [`ColmapExport::max_reproj_error`] px; a track is written when its point is finite and at
///   least two observations remain. Point ids are consecutive from 1 in track order; `ERROR` is
///   the mean reprojection error of the kept observations (px), the colour that of the track's
///   source pixel;
/// * [`ColmapPoints::Dlt`]: every kept DLT track with one element per visible view, `ERROR` = its
///   DLT mean reprojection error;
/// * [`ColmapPoints::None`]: no point.
///
/// Each image's `POINTS2D` are listed in ascending point id; observations are `x + 0.5` of the
/// ff-pixel match (f64).
pub fn colmap_model(
    out: &SfmOutput,
    images: &[f32],
    image_names: &[String],
    export: &ColmapExport,
) -> Result<(ColmapModel, ColmapSummary)> {
    let dims = out.correspondences.dims;
    let (n, h, w) = (dims.n, dims.h, dims.w);
    let hw = h * w;
    let nt = n * hw;
    let cams = &out.result.cameras;
    let shared = export.shared;
    let names: Vec<String> = (0..n)
        .map(|v| {
            image_names
                .get(v)
                .cloned()
                .unwrap_or_else(|| format!("{v:06}.jpg"))
        })
        .collect();
    let simple = export.model == CameraModel::SimplePinhole;
    let mut cm = ColmapModel::from_cameras(cams, h, w, &names, simple, shared)?;
    let mut summary = ColmapSummary {
        points: export.points,
        ba_points_refined: out.ba_points_refined,
        candidates: 0,
        points3d: 0,
        observations: 0,
        dropped_observations: 0,
        dropped_points: 0,
        mean_reprojection_error: f64::NAN,
        max_reprojection_error: 0.0,
    };
    match export.points {
        ColmapPoints::None => {}
        ColmapPoints::Ba => {
            let bt = &out.ba_tracks;
            summary.candidates = bt.points.len();
            // observations per point, in view order (the BA list is per view, then per point)
            let mut per_point: Vec<Vec<(usize, [f64; 2])>> = vec![Vec::new(); bt.points.len()];
            for o in &bt.observations {
                if let Some(list) = per_point.get_mut(o.point) {
                    list.push((o.view, o.xy));
                }
            }
            for (pi, obs) in per_point.iter().enumerate() {
                let x = out.ba_points.get(pi).copied().unwrap_or(Point3::new(
                    f64::NAN,
                    f64::NAN,
                    f64::NAN,
                ));
                if !x.iter().all(|c| c.is_finite()) {
                    summary.dropped_points += 1;
                    summary.dropped_observations += obs.len();
                    continue;
                }
                let mut kept: Vec<(usize, [f64; 2], f64)> = Vec::with_capacity(obs.len());
                for &(v, xy) in obs {
                    let Some(im) = cm.images.get(v) else { continue };
                    let cam = if shared {
                        &cm.cameras[0]
                    } else {
                        &cm.cameras[v]
                    };
                    let uv = pixel_to_colmap(xy);
                    if let Some(p) = project_colmap(cam, im, &x) {
                        let err = ((p[0] - uv[0]).powi(2) + (p[1] - uv[1]).powi(2)).sqrt();
                        if err <= export.max_reproj_error {
                            kept.push((v, uv, err));
                        }
                    }
                }
                summary.dropped_observations += obs.len() - kept.len();
                if kept.len() < 2 {
                    summary.dropped_points += 1;
                    summary.dropped_observations += kept.len();
                    continue;
                }
                let id = cm.points3d.len() as u64 + 1;
                let mut track = Vec::with_capacity(kept.len());
                let mut err_sum = 0.0;
                for &(v, uv, err) in &kept {
                    let im = &mut cm.images[v];
                    track.push((v as u32 + 1, im.points2d.len() as u32));
                    im.points2d.push(ColmapPoint2D {
                        xy: uv,
                        point3d_id: Some(id),
                    });
                    err_sum += err;
                    summary.max_reprojection_error = summary.max_reprojection_error.max(err);
                }
                let j = bt.track_ids.get(pi).copied().unwrap_or(usize::MAX);
                cm.points3d.push(ColmapPoint3D {
                    id,
                    xyz: [x.x, x.y, x.z],
                    rgb: source_rgb(images, j),
                    error: err_sum / kept.len() as f64,
                    track,
                });
            }
        }
        ColmapPoints::Dlt => {
            let corr = &out.correspondences;
            let vis = &out.dlt_visibility;
            for tr in out
                .dlt
                .tracks
                .iter()
                .filter(|t| t.status == DltStatus::Kept)
            {
                summary.candidates += 1;
                let j = tr.track;
                let id = cm.points3d.len() as u64 + 1;
                let mut track = Vec::new();
                for t in 0..n {
                    if vis.get(t * nt + j).copied().unwrap_or(false) {
                        let i = 2 * (t * nt + j);
                        let xy =
                            pixel_to_colmap([corr.matches[i] as f64, corr.matches[i + 1] as f64]);
                        let im = &mut cm.images[t];
                        track.push((t as u32 + 1, im.points2d.len() as u32));
                        im.points2d.push(ColmapPoint2D {
                            xy,
                            point3d_id: Some(id),
                        });
                    }
                }
                cm.points3d.push(ColmapPoint3D {
                    id,
                    xyz: tr.point,
                    rgb: source_rgb(images, j),
                    error: tr.reproj_mean,
                    track,
                });
            }
        }
    }
    summary.points3d = cm.points3d.len();
    summary.observations = cm.points3d.iter().map(|p| p.track.len()).sum();
    if !cm.points3d.is_empty() {
        summary.mean_reprojection_error =
            cm.points3d.iter().map(|p| p.error).sum::<f64>() / cm.points3d.len() as f64;
    }
    if export.points == ColmapPoints::Dlt {
        summary.max_reprojection_error = f64::NAN;
    }
    Ok((cm, summary))
}

/// Writes `dir/sfm_dlt_outputs.safetensors`, `dir/sparse/0/` (COLMAP binary, content chosen by
/// `colmap`, see [`colmap_model`]) and `dir/summary.json` (the run's [`crate::pipeline::SfmSummary`]
/// plus `colmap`: the [`ColmapSummary`]). Returns the COLMAP summary.
pub fn write_outputs(
    dir: &Path,
    out: &SfmOutput,
    images: &[f32],
    image_names: &[String],
    colmap: &ColmapExport,
) -> Result<ColmapSummary> {
    std::fs::create_dir_all(dir).map_err(|e| crate::SfmError::Io {
        path: dir.to_path_buf(),
        source: e,
    })?;
    let dims = out.correspondences.dims;
    let bytes = encode_sfm_safetensors(&out.result, dims, &out.dlt_count, &out.dlt_reproj)?;
    write_bytes_atomic(&dir.join("sfm_dlt_outputs.safetensors"), &bytes)?;
    let sparse = dir.join("sparse").join("0");
    std::fs::create_dir_all(&sparse).map_err(|e| crate::SfmError::Io {
        path: sparse.clone(),
        source: e,
    })?;
    let (model, cs) = colmap_model(out, images, image_names, colmap)?;
    write_colmap(&sparse, &model, false)?;
    let json_err = |e: serde_json::Error| {
        crate::SfmError::Invalid(format!("{}: {e}", dir.join("summary.json").display()))
    };
    let mut value = serde_json::to_value(&out.summary).map_err(json_err)?;
    if let Some(obj) = value.as_object_mut() {
        obj.insert(
            "colmap".into(),
            serde_json::to_value(&cs).map_err(json_err)?,
        );
    }
    let json = serde_json::to_vec_pretty(&value).map_err(json_err)?;
    write_bytes_atomic(&dir.join("summary.json"), &json)?;
    Ok(cs)
}
