//! A Gaussian-splatting / nerfstudio-ready output (`docs/images-to-splats.md`): the cameras at
//! each image's own resolution, an `images/` folder beside `sparse/0` with the images under the
//! names the COLMAP model and `transforms.json` use, nerfstudio's `transforms.json`, and a
//! voxel filter for the initialisation point cloud.
//!
//! Cameras: the SfM cameras (`cam_from_world`, OpenCV axes; K in ff pixels, pixel-centre
//! convention) scaled per axis to an image of `(H, W)` pixels: `f_x' = f_x W / w`,
//! `c_x' = (c_x + 0.5) W / w - 0.5` (the principal point is scaled, not reset), the same for `y`.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use ggpt_core::io::atomic::write_json_atomic;
use ggpt_core::{Cameras, Dims};
use nalgebra::{Matrix4, Vector3};

use crate::error::SceneError;

/// Folder of the images beside `sparse/0`.
pub const IMAGES_DIR: &str = "images";
/// nerfstudio's camera file.
pub const TRANSFORMS_JSON: &str = "transforms.json";

/// `cameras` (ff resolution `dims`) scaled to images of `sizes[v] = (H, W)` pixels (see the
/// module doc).
pub fn scale_cameras(cameras: &Cameras, dims: Dims, sizes: &[(usize, usize)]) -> Cameras {
    let mut out = cameras.clone();
    for (k, &(hh, ww)) in out.intrinsics.iter_mut().zip(sizes) {
        let (sx, sy) = (ww as f64 / dims.w as f64, hh as f64 / dims.h as f64);
        k[(0, 0)] *= sx;
        k[(1, 1)] *= sy;
        k[(0, 2)] = (k[(0, 2)] + 0.5) * sx - 0.5;
        k[(1, 2)] = (k[(1, 2)] + 0.5) * sy - 0.5;
    }
    out
}

/// nerfstudio's `transforms.json` of `cameras` (already at the images' resolution `sizes`):
/// per frame `file_path` = `images/<name>`, `fl_x`, `fl_y`, `cx`, `cy` (nerfstudio's pixel
/// convention: the top-left pixel's corner at 0, so `c = c_pixel-centre + 0.5`), `w`, `h` and
/// `transform_matrix` = camera-to-world in nerfstudio's OpenGL camera axes (x right, y up,
/// z back: OpenCV's y and z negated); the world frame is the SfM frame as it is
/// (`applied_transform` = identity, so the PLY `ply_file_path` needs no transform either).
pub fn transforms_json(
    cameras: &Cameras,
    sizes: &[(usize, usize)],
    names: &[String],
    ply_file_path: Option<&str>,
) -> serde_json::Value {
    let frames: Vec<serde_json::Value> = (0..cameras.len())
        .map(|v| {
            let k = &cameras.intrinsics[v];
            let (h, w) = sizes[v];
            let r = cameras.rotation(v);
            let t = cameras.translation(v);
            let rt = r.transpose();
            let centre: Vector3<f64> = -(rt * t);
            let mut c2w = Matrix4::identity();
            for i in 0..3 {
                // OpenCV -> OpenGL camera axes: columns 1 (y) and 2 (z) negated
                c2w[(i, 0)] = rt[(i, 0)];
                c2w[(i, 1)] = -rt[(i, 1)];
                c2w[(i, 2)] = -rt[(i, 2)];
                c2w[(i, 3)] = centre[i];
            }
            let rows: Vec<Vec<f64>> = (0..4)
                .map(|i| (0..4).map(|j| c2w[(i, j)]).collect())
                .collect();
            serde_json::json!({
                "file_path": format!("{IMAGES_DIR}/{}", names[v]),
                "fl_x": k[(0, 0)],
                "fl_y": k[(1, 1)],
                "cx": k[(0, 2)] + 0.5,
                "cy": k[(1, 2)] + 0.5,
                "w": w,
                "h": h,
                "transform_matrix": rows,
            })
        })
        .collect();
    let mut out = serde_json::json!({
        "camera_model": "PINHOLE",
        "applied_transform": [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]],
        "frames": frames,
    });
    if let Some(p) = ply_file_path {
        out["ply_file_path"] = p.into();
    }
    out
}

/// Writes `images/` into `out`: the files `sources` (one per view) under `names`, hard-linked
/// when possible and copied otherwise; without sources, the ff images `[N, h, w, 3]` in `[0, 1]`
/// as PNGs. Every file is written atomically (a temporary file, then a rename).
pub fn write_images(
    out: &Path,
    names: &[String],
    sources: Option<&[PathBuf]>,
    images_ff: &[f32],
    dims: Dims,
) -> Result<(), SceneError> {
    let dir = out.join(IMAGES_DIR);
    std::fs::create_dir_all(&dir).map_err(|e| ggpt_core::CoreError::io(&dir, e))?;
    for (v, name) in names.iter().enumerate() {
        let dest = dir.join(name);
        match sources.and_then(|s| s.get(v)) {
            Some(src) => link_or_copy(src, &dest)?,
            None => {
                let hw = dims.hw();
                let rgb: Vec<u8> = images_ff[3 * v * hw..3 * (v + 1) * hw]
                    .iter()
                    .map(|&x| ggpt_core::color::color_u8(x))
                    .collect();
                ggpt_core::io::png::write_rgb8(&dest, dims.w, dims.h, &rgb)?;
            }
        }
    }
    Ok(())
}

/// `dest` becomes a hard link to `src` (or a copy where links do not work: another file
/// system), atomically.
fn link_or_copy(src: &Path, dest: &Path) -> Result<(), SceneError> {
    let io = |p: &Path, e| SceneError::Core(ggpt_core::CoreError::io(p, e));
    let tmp = dest.with_extension(format!(
        "{}.tmp{}",
        dest.extension().and_then(|e| e.to_str()).unwrap_or(""),
        std::process::id()
    ));
    let _ = std::fs::remove_file(&tmp);
    if std::fs::hard_link(src, &tmp).is_err() {
        std::fs::copy(src, &tmp).map_err(|e| io(src, e))?;
    }
    std::fs::rename(&tmp, dest).map_err(|e| io(dest, e))?;
    Ok(())
}

/// Writes `transforms.json` into `out`, atomically.
pub fn write_transforms(out: &Path, value: &serde_json::Value) -> Result<(), SceneError> {
    write_json_atomic(&out.join(TRANSFORMS_JSON), value)?;
    Ok(())
}

/// Of the pixels `keep` (ascending), one per cube of side `voxel` (scene units) of their points
/// `[P, 3]`: the most confident (the lower pixel index on ties); ascending pixel order.
pub fn voxel_filter(points: &[f32], conf: &[f32], keep: &[u32], voxel: f64) -> Vec<u32> {
    let mut best: HashMap<[i64; 3], u32> = HashMap::new();
    for &p in keep {
        let i = p as usize;
        let cell = [0, 1, 2].map(|a| (f64::from(points[3 * i + a]) / voxel).floor() as i64);
        best.entry(cell)
            .and_modify(|b| {
                if conf[i] > conf[*b as usize] {
                    *b = p;
                }
            })
            .or_insert(p);
    }
    let mut out: Vec<u32> = best.into_values().collect();
    out.sort_unstable();
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix3, Matrix3x4, Rotation3};

    #[test]
    fn scaled_principal_point_and_gl_axes() {
        let k = Matrix3::new(10.0, 0.0, 2.0, 0.0, 12.0, 1.5, 0.0, 0.0, 1.0);
        let r = Rotation3::from_euler_angles(0.1, 0.2, 0.3).into_inner();
        let mut m = Matrix3x4::zeros();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
        m.set_column(3, &Vector3::new(1.0, 2.0, 3.0));
        let cams = Cameras {
            cam_from_world: vec![m],
            intrinsics: vec![k],
        };
        let d = Dims { n: 1, h: 4, w: 5 };
        let s = scale_cameras(&cams, d, &[(8, 20)]);
        let ks = s.intrinsics[0];
        // x 4x, y 2x; the centre (w-1)/2 = 2 maps to (20-1)/2, (h-1)/2 = 1.5 to (8-1)/2
        assert_eq!(
            (ks[(0, 0)], ks[(1, 1)], ks[(0, 2)], ks[(1, 2)]),
            (40.0, 24.0, 9.5, 3.5)
        );
        let j = transforms_json(&s, &[(8, 20)], &["a.png".into()], Some("p.ply"));
        let f = &j["frames"][0];
        assert_eq!(f["file_path"], "images/a.png");
        assert_eq!((f["cx"].as_f64(), f["w"].as_u64()), (Some(10.0), Some(20)));
        // camera-to-world: the camera centre, and the OpenGL z axis = minus the viewing direction
        let t = &f["transform_matrix"];
        let c = -(r.transpose() * Vector3::new(1.0, 2.0, 3.0));
        for i in 0..3 {
            assert!((t[i][3].as_f64().unwrap() - c[i]).abs() < 1e-12);
            assert!((t[i][2].as_f64().unwrap() + r[(2, i)]).abs() < 1e-12);
        }
        assert_eq!(j["ply_file_path"], "p.ply");
    }

    #[test]
    fn voxel_filter_keeps_the_most_confident_per_cell() {
        let points = [0.1, 0.1, 0.1, 0.2, 0.2, 0.2, 1.5, 0.0, 0.0, 0.15, 0.1, 0.1];
        let conf = [1.0, 3.0, 1.0, 3.0];
        assert_eq!(voxel_filter(&points, &conf, &[0, 1, 2, 3], 1.0), vec![1, 2]);
        assert_eq!(voxel_filter(&points, &conf, &[0, 2], 1.0), vec![0, 2]);
    }
}
