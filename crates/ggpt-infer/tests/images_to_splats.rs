//! The images-to-splats route (`docs/images-to-splats.md`) from the files a user has: VGGT's
//! `predictions.npz`, a matches folder and the original images (here at twice the feed-forward
//! resolution, under their own names), through `ggpt-infer run --ff --matches --images`, to a
//! COLMAP model + `images/` + `transforms.json` that pycolmap and nerfstudio read.
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

mod common;

use std::path::Path;
use std::process::Command;

use ggpt_core::io::colmap::read_colmap;
use ggpt_synth::{Regime, SynthConfig, generate};

const SCALE: usize = 2;

/// A 4-view synthetic scene written as the route's inputs; returns (scene dir, images dir).
fn route_inputs(dir: &Path) -> (std::path::PathBuf, std::path::PathBuf) {
    let scene = generate(&SynthConfig {
        views: 4,
        width: 168,
        height: 126,
        seed: 5,
        matches: true,
        ..SynthConfig::for_regime(Regime::Easy)
    })
    .unwrap()
    .scene;
    let s = dir.join("scene");
    ggpt_core::io::scene_dir::write_scene(&s, &scene).unwrap();
    ggpt_core::io::feedforward::write_vggt_predictions(
        &s.join("predictions.npz"),
        scene.ff.as_ref().unwrap(),
        &scene.images,
        scene.dims,
    )
    .unwrap();
    // the "original" images: the renders upscaled 2x, named as a camera names them
    let img = dir.join("photos");
    std::fs::create_dir_all(&img).unwrap();
    for v in 0..scene.dims.n {
        let src = image::open(s.join(format!("images/{v:06}.png"))).unwrap();
        let big = src.resize_exact(
            (SCALE * scene.dims.w) as u32,
            (SCALE * scene.dims.h) as u32,
            image::imageops::FilterType::Triangle,
        );
        big.to_rgb8()
            .save(img.join(format!("IMG_{:04}.png", 100 + v)))
            .unwrap();
    }
    (s, img)
}

#[test]
fn predictions_matches_and_images_to_a_splat_ready_folder() {
    let dir = tempfile::tempdir().unwrap();
    let (scene, photos) = route_inputs(dir.path());
    let out = dir.path().join("out");
    let o = Command::new(env!("CARGO_BIN_EXE_ggpt-infer"))
        .arg("run")
        .arg("--ff")
        .arg(scene.join("predictions.npz"))
        .arg("--matches")
        .arg(scene.join("matches"))
        .arg("--images")
        .arg(&photos)
        .args([
            "--weights",
            "shipped",
            "--seed",
            "42",
            "--device",
            "cpu",
            "--quiet",
            "--min-chunk-pixels",
            "300",
            "--min-chunk-dlt",
            "40",
            "--voxel-size",
            "0.01",
            "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "ggpt-infer run --ff failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    // images/ with the original names and bytes (linked or copied)
    let names: Vec<String> = (0..4).map(|v| format!("IMG_{:04}.png", 100 + v)).collect();
    for n in &names {
        assert_eq!(
            std::fs::read(out.join("images").join(n)).unwrap(),
            std::fs::read(photos.join(n)).unwrap(),
            "{n}"
        );
    }
    // the COLMAP model: original names, sizes, intrinsics scaled from the SfM's
    let sparse = out.join("sparse/0");
    let model = read_colmap(&sparse).unwrap();
    let got: Vec<&str> = model.images.iter().map(|i| i.name.as_str()).collect();
    assert_eq!(got, names.iter().map(String::as_str).collect::<Vec<_>>());
    let npz = ggpt_core::io::npy::read_npz(&out.join("scene.npz")).unwrap();
    let k = npz["K"].to_f64().unwrap();
    for c in &model.cameras {
        assert_eq!((c.width, c.height), (336, 252), "camera {}", c.id);
        let v = (c.id - 1) as usize;
        let kv = if model.cameras.len() == 1 {
            &k[0..9]
        } else {
            &k[9 * v..9 * v + 9]
        };
        let want = [
            kv[0] * SCALE as f64,
            kv[4] * SCALE as f64,
            (kv[2] + 0.5) * SCALE as f64,
            (kv[5] + 0.5) * SCALE as f64,
        ];
        // PINHOLE: the cameras are scaled per axis to each image's own size
        assert_eq!(
            c.model,
            ggpt_core::io::colmap::ColmapCameraModel::Pinhole,
            "camera {}",
            c.id
        );
        let params = &c.params;
        let fxy = [params[0], params[1], params[2], params[3]];
        for (a, b) in fxy.iter().zip(&want) {
            assert!((a - b).abs() < 1e-9, "camera {}: {fxy:?} vs {want:?}", c.id);
        }
    }
    // transforms.json: the same cameras, in nerfstudio's layout
    let t: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("transforms.json")).unwrap()).unwrap();
    assert_eq!(t["frames"].as_array().unwrap().len(), 4);
    assert_eq!(t["frames"][0]["file_path"], "images/IMG_0100.png");
    assert_eq!(t["ply_file_path"], "ggpt_points.ply");
    let meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("meta.json")).unwrap()).unwrap();
    // `scene/predictions.npz` is named after its folder, not the layout's file name
    assert_eq!(meta["scene"], "scene", "{meta}");
    let files = meta["files"].as_array().unwrap();
    assert!(files.iter().any(|f| f == "images") && files.iter().any(|f| f == "transforms.json"));
    // independent readers: pycolmap reads the model with these names and sizes, and the frames
    // of transforms.json round-trip to its poses and intrinsics
    if common::python_module_available(
        "predictions_matches_and_images_to_a_splat_ready_folder",
        "pycolmap",
        "pycolmap==4.2.1",
        "the splat-ready folder",
    ) {
        let py = common::run_python_check("check_colmap_model.py", &sparse);
        assert_eq!(py["ok"], true, "{py}");
        let py_names: Vec<&str> = py["images"]
            .as_array()
            .unwrap()
            .iter()
            .map(|i| i["name"].as_str().unwrap())
            .collect();
        assert_eq!(
            py_names,
            names.iter().map(String::as_str).collect::<Vec<_>>()
        );
        let tr = common::run_python_check("check_transforms.py", &out);
        assert_eq!(tr["ok"], true, "{tr}");
        assert!(tr["max_pose_difference"].as_f64().unwrap() <= 1e-6, "{tr}");
        assert_eq!(tr["sizes"][0], serde_json::json!([336, 252]));
    }
}

#[test]
fn bad_route_inputs_give_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let (scene, photos) = route_inputs(dir.path());
    let run = |args: &[&std::ffi::OsStr]| {
        let o = Command::new(env!("CARGO_BIN_EXE_ggpt-infer"))
            .arg("run")
            .args(args)
            .args(["--weights", "shipped", "--quiet", "--out"])
            .arg(dir.path().join("out"))
            .output()
            .unwrap();
        assert!(!o.status.success());
        String::from_utf8_lossy(&o.stderr).into_owned()
    };
    let pred = scene.join("predictions.npz");
    // one image too few
    std::fs::remove_file(photos.join("IMG_0103.png")).unwrap();
    let e = run(&[
        "--ff".as_ref(),
        pred.as_os_str(),
        "--matches".as_ref(),
        scene.join("matches").as_os_str(),
        "--images".as_ref(),
        photos.as_os_str(),
    ]);
    assert!(e.contains("3 images") && e.contains("4 views"), "{e}");
    // not a feed-forward file
    let bogus = dir.path().join("bogus.npz");
    ggpt_core::io::npy::write_npz(
        &bogus,
        &[(
            "foo",
            &ggpt_core::io::npy::NpyArray::new(
                vec![1],
                ggpt_core::io::npy::NpyData::F32(vec![0.0]),
            )
            .unwrap(),
        )],
        false,
    )
    .unwrap();
    let e = run(&[
        "--ff".as_ref(),
        bogus.as_os_str(),
        "--matches".as_ref(),
        scene.join("matches").as_os_str(),
    ]);
    assert!(
        e.contains("bogus.npz") && e.contains("foo") && e.contains("VGGT"),
        "{e}"
    );
    // --ff without --matches
    let e = run(&["--ff".as_ref(), pred.as_os_str()]);
    assert!(e.contains("--matches"), "{e}");
}
