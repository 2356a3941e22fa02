//! Targets of `ggpt-core`'s readers: npy / npz, PLY, COLMAP binary and text models, project
//! scene folders (safetensors + manifest + matches), the official `.bin` torch pickles.

use std::path::Path;

use ggpt_core::io::colmap::{ColmapModel, ColmapPoint2D, ColmapPoint3D, read_colmap, write_colmap};
use ggpt_core::io::npy::{NpyArray, NpyData, encode_npy, read_npy, read_npz, write_npz};
use ggpt_core::io::official::read_official_dir;
use ggpt_core::io::ply::{PlyCloud, read_ply, write_ply};
use ggpt_core::io::read_scene;
use ggpt_core::io::scene_dir::write_scene;
use ggpt_core::io::torch_zip::{TorchValue, write_torch_zip};

use super::{err_text, seed_from_writer};
use crate::Result;
use crate::harness::{SeedFile, Target, fingerprint_debug};

/// Views, height and width of the seed scenes (small: most mutations should hit structure).
const VIEWS: usize = 2;
const HEIGHT: usize = 14;
const WIDTH: usize = 28;

/// A small synthetic room with matches (`ggpt-synth`, seed 1).
pub fn seed_scene() -> std::result::Result<ggpt_core::Scene, String> {
    let cfg = ggpt_synth::SynthConfig {
        views: VIEWS,
        width: WIDTH,
        height: HEIGHT,
        seed: 1,
        matches: true,
        ..ggpt_synth::SynthConfig::default()
    };
    ggpt_synth::generate(&cfg)
        .map(|o| o.scene)
        .map_err(|e| e.to_string())
}

fn f32_array(shape: &[usize]) -> NpyArray {
    let n: usize = shape.iter().product();
    NpyArray {
        shape: shape.to_vec(),
        data: NpyData::F32((0..n).map(|i| i as f32 * 0.25 - 3.0).collect()),
    }
}

/// `.npy` arrays of several dtypes (`read_npy`).
pub struct Npy;

impl Target for Npy {
    fn name(&self) -> &'static str {
        "npy"
    }
    fn describe(&self) -> &'static str {
        "`.npy` (f32, u8, bool, i64)"
    }
    fn seed(&self) -> Result<Vec<SeedFile>> {
        let arrays = [
            ("points.npy", f32_array(&[3, 4, 3])),
            (
                "colors.npy",
                NpyArray {
                    shape: vec![5, 3],
                    data: NpyData::U8((0..15).collect()),
                },
            ),
            (
                "mask.npy",
                NpyArray {
                    shape: vec![2, 3],
                    data: NpyData::Bool(vec![true, false, true, true, false, false]),
                },
            ),
            (
                "ids.npy",
                NpyArray {
                    shape: vec![4],
                    data: NpyData::I64(vec![1, -2, 3, 1 << 40]),
                },
            ),
        ];
        let mut out = Vec::new();
        for (name, a) in arrays {
            let bytes = encode_npy(&a).map_err(|e| crate::FuzzError::Seed {
                target: "npy".into(),
                message: e.to_string(),
            })?;
            out.push(SeedFile::new(name, bytes));
        }
        Ok(out)
    }
    fn read(&self, dir: &Path) -> std::result::Result<u64, String> {
        let mut all = Vec::new();
        for name in ["points.npy", "colors.npy", "mask.npy", "ids.npy"] {
            all.push(read_npy(&dir.join(name)).map_err(|e| err_text(&e))?);
        }
        Ok(fingerprint_debug(&all))
    }
}

/// `.npz` archives, stored and deflated (`read_npz`).
pub struct Npz;

impl Target for Npz {
    fn name(&self) -> &'static str {
        "npz"
    }
    fn describe(&self) -> &'static str {
        "`.npz` (stored and deflated zip)"
    }
    fn seed(&self) -> Result<Vec<SeedFile>> {
        seed_from_writer(self.name(), |dir| {
            let a = f32_array(&[2, 5, 3]);
            let b = NpyArray {
                shape: vec![2, 5],
                data: NpyData::Bool((0..10).map(|i| i % 3 == 0).collect()),
            };
            write_npz(
                &dir.join("stored.npz"),
                &[("points", &a), ("mask", &b)],
                true,
            )
            .map_err(|e| e.to_string())?;
            write_npz(
                &dir.join("deflated.npz"),
                &[("points", &a), ("mask", &b)],
                false,
            )
            .map_err(|e| e.to_string())
        })
    }
    fn read(&self, dir: &Path) -> std::result::Result<u64, String> {
        let a = read_npz(&dir.join("stored.npz")).map_err(|e| err_text(&e))?;
        let b = read_npz(&dir.join("deflated.npz")).map_err(|e| err_text(&e))?;
        Ok(fingerprint_debug(&(a, b)))
    }
}

/// Binary PLY point clouds with and without confidence (`read_ply`).
pub struct Ply;

impl Target for Ply {
    fn name(&self) -> &'static str {
        "ply"
    }
    fn describe(&self) -> &'static str {
        "binary PLY (xyz, rgb, confidence)"
    }
    fn seed(&self) -> Result<Vec<SeedFile>> {
        seed_from_writer(self.name(), |dir| {
            let points: Vec<[f32; 3]> = (0..20)
                .map(|i| [i as f32, -(i as f32) * 0.5, 2.0])
                .collect();
            let colors: Vec<[u8; 3]> = (0..20u8).map(|i| [i, 255 - i, 7]).collect();
            let conf: Vec<f32> = (0..20).map(|i| 1.0 + i as f32).collect();
            write_ply(
                &dir.join("plain.ply"),
                &PlyCloud {
                    points: points.clone(),
                    colors: colors.clone(),
                    confidence: None,
                },
            )
            .map_err(|e| e.to_string())?;
            write_ply(
                &dir.join("conf.ply"),
                &PlyCloud {
                    points,
                    colors,
                    confidence: Some(conf),
                },
            )
            .map_err(|e| e.to_string())
        })
    }
    fn read(&self, dir: &Path) -> std::result::Result<u64, String> {
        let a = read_ply(&dir.join("plain.ply")).map_err(|e| err_text(&e))?;
        let b = read_ply(&dir.join("conf.ply")).map_err(|e| err_text(&e))?;
        Ok(fingerprint_debug(&(a, b)))
    }
}

/// A COLMAP model with cameras, images, 2D points and 3D tracks (`read_colmap`).
pub struct Colmap {
    /// Text (`.txt`) instead of binary (`.bin`).
    pub text: bool,
}

fn seed_colmap_model() -> std::result::Result<ColmapModel, String> {
    let scene = seed_scene()?;
    let ff = scene.ff.as_ref().ok_or("seed scene without feed-forward")?;
    let names: Vec<String> = (0..VIEWS).map(|i| format!("view_{i:03}.png")).collect();
    let mut model = ColmapModel::from_cameras(&ff.cameras, HEIGHT, WIDTH, &names, false, false)
        .map_err(|e| e.to_string())?;
    for (i, img) in model.images.iter_mut().enumerate() {
        img.points2d = (0..3)
            .map(|k| ColmapPoint2D {
                xy: [1.5 + k as f64, 2.5 + i as f64],
                point3d_id: if k < 2 { Some(k as u64 + 1) } else { None },
            })
            .collect();
    }
    model.points3d = (0..2u32)
        .map(|k| ColmapPoint3D {
            id: u64::from(k) + 1,
            xyz: [0.1 * f64::from(k), 0.2, 1.5],
            rgb: [10, 20, 30],
            error: 0.25,
            track: vec![(1, k), (2, k)],
        })
        .collect();
    Ok(model)
}

impl Target for Colmap {
    fn name(&self) -> &'static str {
        if self.text {
            "colmap-txt"
        } else {
            "colmap-bin"
        }
    }
    fn describe(&self) -> &'static str {
        if self.text {
            "COLMAP text model"
        } else {
            "COLMAP binary model"
        }
    }
    fn seed(&self) -> Result<Vec<SeedFile>> {
        let text = self.text;
        seed_from_writer(self.name(), |dir| {
            write_colmap(dir, &seed_colmap_model()?, text).map_err(|e| e.to_string())
        })
    }
    fn read(&self, dir: &Path) -> std::result::Result<u64, String> {
        read_colmap(dir)
            .map(|m| fingerprint_debug(&m))
            .map_err(|e| err_text(&e))
    }
}

/// A project scene folder (`manifest.json`, safetensors, matches; `read_scene`, which
/// validates the whole scene).
pub struct SceneDir;

impl Target for SceneDir {
    fn name(&self) -> &'static str {
        "scene-dir"
    }
    fn describe(&self) -> &'static str {
        "project scene folder (safetensors, manifest, matches)"
    }
    fn seed(&self) -> Result<Vec<SeedFile>> {
        seed_from_writer(self.name(), |dir| {
            write_scene(dir, &seed_scene()?).map_err(|e| e.to_string())
        })
    }
    fn read(&self, dir: &Path) -> std::result::Result<u64, String> {
        read_scene(dir)
            .map(|s| fingerprint_debug(&s))
            .map_err(|e| err_text(&e))
    }
}

fn row_major_3x4(m: &[nalgebra::Matrix3x4<f64>]) -> Vec<f32> {
    m.iter()
        .flat_map(|m| m.transpose().iter().map(|&x| x as f32).collect::<Vec<_>>())
        .collect()
}

fn row_major_4x4(m: &[nalgebra::Matrix3x4<f64>]) -> Vec<f32> {
    m.iter()
        .flat_map(|m| {
            m.transpose()
                .iter()
                .map(|&x| x as f32)
                .chain([0.0, 0.0, 0.0, 1.0])
                .collect::<Vec<_>>()
        })
        .collect()
}

fn row_major_3x3(m: &[nalgebra::Matrix3<f64>]) -> Vec<f32> {
    m.iter()
        .flat_map(|m| m.transpose().iter().map(|&x| x as f32).collect::<Vec<_>>())
        .collect()
}

/// The three official torch pickles `gt.bin`, `ff_outputs.bin`, `sfm_dlt_outputs.bin`
/// (`read_official_dir`).
pub struct OfficialBin;

impl Target for OfficialBin {
    fn name(&self) -> &'static str {
        "official-bin"
    }
    fn describe(&self) -> &'static str {
        "official torch pickles (`gt.bin`, `ff_outputs.bin`, `sfm_dlt_outputs.bin`)"
    }
    fn seed(&self) -> Result<Vec<SeedFile>> {
        seed_from_writer(self.name(), |dir| {
            let s = seed_scene()?;
            let (n, h, w) = (VIEWS, HEIGHT, WIDTH);
            let ff = s.ff.as_ref().ok_or("no ff")?;
            let gt = s.gt.as_ref().ok_or("no gt")?;
            let e = |e: ggpt_core::CoreError| e.to_string();
            write_torch_zip(
                &dir.join("ff_outputs.bin"),
                &[
                    ("images_ff", TorchValue::f32(&s.images, &[n, h, w, 3])),
                    (
                        "extrinsics",
                        TorchValue::f32(&row_major_3x4(&ff.cameras.cam_from_world), &[n, 3, 4]),
                    ),
                    (
                        "intrinsics",
                        TorchValue::f32(&row_major_3x3(&ff.cameras.intrinsics), &[n, 3, 3]),
                    ),
                    ("points", TorchValue::f32(&ff.points, &[n, h, w, 3])),
                    ("points_conf", TorchValue::f32(&ff.conf, &[n, h, w])),
                ],
            )
            .map_err(e)?;
            write_torch_zip(
                &dir.join("gt.bin"),
                &[
                    ("points", TorchValue::f32(&gt.points, &[n, h, w, 3])),
                    ("point_masks", TorchValue::bool(&gt.mask, &[n, h, w])),
                    (
                        "intrinsics",
                        TorchValue::f32(&row_major_3x3(&gt.cameras.intrinsics), &[n, 3, 3]),
                    ),
                    (
                        "extrinsics",
                        TorchValue::f32(&row_major_4x4(&gt.cameras.cam_from_world), &[n, 4, 4]),
                    ),
                    ("images", TorchValue::f32(&s.images, &[n, h, w, 3])),
                ],
            )
            .map_err(e)?;
            let mask: Vec<bool> = (0..n * h * w).map(|i| i % 4 == 0).collect();
            let points: Vec<f32> = ff
                .points
                .iter()
                .enumerate()
                .map(|(i, &x)| if mask[i / 3] { x } else { 0.0 })
                .collect();
            write_torch_zip(
                &dir.join("sfm_dlt_outputs.bin"),
                &[
                    (
                        "intrinsics",
                        TorchValue::f32(&row_major_3x3(&ff.cameras.intrinsics), &[n, 3, 3]),
                    ),
                    (
                        "extrinsics",
                        TorchValue::f32(&row_major_3x4(&ff.cameras.cam_from_world), &[n, 3, 4]),
                    ),
                    ("camera_success", TorchValue::Bool(true)),
                    ("points", TorchValue::f32(&points, &[n, h, w, 3])),
                    ("point_masks", TorchValue::bool(&mask, &[n, h, w])),
                    ("points_success", TorchValue::Bool(true)),
                ],
            )
            .map_err(e)
        })
    }
    fn read(&self, dir: &Path) -> std::result::Result<u64, String> {
        read_official_dir(dir)
            .map(|s| fingerprint_debug(&s))
            .map_err(|e| err_text(&e))
    }
}
