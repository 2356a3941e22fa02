//! Writers of the `ggpt-sfm` binary's outputs: `sfm_dlt_outputs.safetensors`, the COLMAP model
//! and `summary.json`. Every file is written atomically.

use std::collections::HashMap;
use std::path::Path;

use ggpt_core::io::atomic::write_bytes_atomic;
use ggpt_core::io::colmap::{
    ColmapCamera, ColmapCameraModel, ColmapImage, ColmapModel, ColmapPoint2D, ColmapPoint3D, pixel_to_colmap, rotation_to_qvec, write_colmap,
};
use ggpt_core::{Dims, SfmResult};

use crate::ba::CameraModel;
use crate::dlt::DltStatus;
use crate::error::Result;
use crate::pipeline::SfmOutput;
use crate::st::{OutTensor, serialize};

/// Serialises the SfM result as safetensors with the keys of the official
/// `sfm_dlt_outputs.bin`: `points` F32 `[N,h,w,3]` (SfM frame), `point_masks` BOOL `[N,h,w]`,
/// `intrinsics` F32 `[N,3,3]` (pixel-centre convention), `extrinsics` F32 `[N,3,4]`
/// (`cam_from_world`), plus `camera_success` / `points_success` BOOL `[]`, `dlt_count` U16 and
/// `dlt_reproj` F32 `[N,h,w]`.
pub fn encode_sfm_safetensors(res: &SfmResult, dims: Dims, dlt_count: &[u16], dlt_reproj: &[f32]) -> Result<Vec<u8>> {
    let (n, h, w) = (dims.n, dims.h, dims.w);
    let intr: Vec<f32> = res.cameras.intrinsics.iter().flat_map(|k| (0..9).map(move |i| k[(i / 3, i % 3)] as f32)).collect();
    let ext: Vec<f32> = res.cameras.cam_from_world.iter().flat_map(|e| (0..12).map(move |i| e[(i / 4, i % 4)] as f32)).collect();
    let tensors = vec![
        OutTensor::f32("points", vec![n, h, w, 3], &res.points),
        OutTensor::bool("point_masks", vec![n, h, w], &res.mask),
        OutTensor::f32("intrinsics", vec![n, 3, 3], &intr),
        OutTensor::f32("extrinsics", vec![n, 3, 4], &ext),
        OutTensor::bool("camera_success", vec![], &[res.camera_success]),
        OutTensor::bool("points_success", vec![], &[res.points_success]),
        OutTensor::u16("dlt_count", vec![n, h, w], dlt_count),
        OutTensor::f32("dlt_reproj", vec![n, h, w], dlt_reproj),
    ];
    let meta = HashMap::from([("format".to_string(), "ggpt-sfm".to_string())]);
    serialize(&tensors, Some(meta))
}

/// Builds the COLMAP model of a run (`formats.md` §6.2, corner convention, ids from 1) at ff
/// resolution: one shared camera (or one per view) of the BA model, the SfM cameras, and every
/// kept DLT track as a 3D point (colour of its source pixel, error = mean reprojection error)
/// with one track element per visible view.
pub fn colmap_model(out: &SfmOutput, images: &[f32], image_names: &[String], model: CameraModel, shared: bool) -> ColmapModel {
    let dims = out.correspondences.dims;
    let (n, h, w) = (dims.n, dims.h, dims.w);
    let hw = h * w;
    let nt = n * hw;
    let cams = &out.result.cameras;
    let camera = |id: u32, v: usize| {
        let k = &cams.intrinsics[v];
        let (cx, cy) = (k[(0, 2)] + 0.5, k[(1, 2)] + 0.5);
        let (m, params) = match model {
            CameraModel::Pinhole => (ColmapCameraModel::Pinhole, vec![k[(0, 0)], k[(1, 1)], cx, cy]),
            CameraModel::SimplePinhole => (ColmapCameraModel::SimplePinhole, vec![(k[(0, 0)] + k[(1, 1)]) / 2.0, cx, cy]),
        };
        ColmapCamera { id, model: m, width: w as u64, height: h as u64, params }
    };
    let mut cm = ColmapModel::default();
    if shared {
        cm.cameras.push(camera(1, 0));
    } else {
        cm.cameras.extend((0..n).map(|v| camera(v as u32 + 1, v)));
    }
    for v in 0..n {
        let e = &cams.cam_from_world[v];
        let r = e.fixed_view::<3, 3>(0, 0).into_owned();
        let name = image_names.get(v).cloned().unwrap_or_else(|| format!("{v:06}.jpg"));
        cm.images.push(ColmapImage {
            id: v as u32 + 1,
            qvec: rotation_to_qvec(&r),
            tvec: [e[(0, 3)], e[(1, 3)], e[(2, 3)]],
            camera_id: if shared { 1 } else { v as u32 + 1 },
            name,
            points2d: Vec::new(),
        });
    }
    let corr = &out.correspondences;
    let vis = &out.dlt_visibility;
    for tr in out.dlt.tracks.iter().filter(|t| t.status == DltStatus::Kept) {
        let j = tr.track;
        let id = cm.points3d.len() as u64 + 1;
        let mut track = Vec::new();
        for t in 0..n {
            if vis.get(t * nt + j).copied().unwrap_or(false) {
                let i = 2 * (t * nt + j);
                let xy = pixel_to_colmap([corr.matches[i] as f64, corr.matches[i + 1] as f64]);
                let im = &mut cm.images[t];
                track.push((t as u32 + 1, im.points2d.len() as u32));
                im.points2d.push(ColmapPoint2D { xy, point3d_id: Some(id) });
            }
        }
        let rgb = images.get(3 * j..3 * j + 3).map(|c| c.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).collect::<Vec<u8>>()).unwrap_or_default();
        cm.points3d.push(ColmapPoint3D {
            id,
            xyz: tr.point,
            rgb: [rgb.first().copied().unwrap_or(0), rgb.get(1).copied().unwrap_or(0), rgb.get(2).copied().unwrap_or(0)],
            error: tr.reproj_mean,
            track,
        });
    }
    cm
}

/// Writes `dir/sfm_dlt_outputs.safetensors`, `dir/sparse/0/` (COLMAP binary) and
/// `dir/summary.json`.
pub fn write_outputs(dir: &Path, out: &SfmOutput, images: &[f32], image_names: &[String], model: CameraModel, shared: bool) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| crate::SfmError::Io { path: dir.to_path_buf(), source: e })?;
    let dims = out.correspondences.dims;
    let bytes = encode_sfm_safetensors(&out.result, dims, &out.dlt_count, &out.dlt_reproj)?;
    write_bytes_atomic(&dir.join("sfm_dlt_outputs.safetensors"), &bytes)?;
    let sparse = dir.join("sparse").join("0");
    std::fs::create_dir_all(&sparse).map_err(|e| crate::SfmError::Io { path: sparse.clone(), source: e })?;
    write_colmap(&sparse, &colmap_model(out, images, image_names, model, shared), false)?;
    let json = serde_json::to_vec_pretty(&out.summary).map_err(|e| crate::SfmError::Invalid(format!("summary.json: {e}")))?;
    write_bytes_atomic(&dir.join("summary.json"), &json)?;
    Ok(())
}
