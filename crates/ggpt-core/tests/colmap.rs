//! COLMAP model writer / reader (binary and text) and convention conversions.
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

use ggpt_core::Cameras;
use ggpt_core::io::colmap::{
    ColmapCamera, ColmapCameraModel, ColmapModel, ColmapPoint2D, ColmapPoint3D, pixel_to_colmap,
    qvec_to_rotation, read_colmap, rotation_to_qvec, write_colmap,
};
use nalgebra::{Matrix3, Matrix3x4, Rotation3, Vector3};

fn cams() -> Cameras {
    let r0 = Rotation3::from_euler_angles(0.1, -0.4, 2.9).into_inner();
    let r1 = Rotation3::from_euler_angles(-3.0, 0.2, 0.05).into_inner(); // large angle: w small
    let mk = |r: Matrix3<f64>, t: Vector3<f64>| {
        let mut m = Matrix3x4::zeros();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
        m.set_column(3, &t);
        m
    };
    Cameras {
        cam_from_world: vec![
            mk(r0, Vector3::new(0.1, 0.2, -0.3)),
            mk(r1, Vector3::new(-1.0, 5.0, 2.0)),
        ],
        intrinsics: vec![Matrix3::new(400.0, 0.0, 258.5, 0.0, 401.0, 195.5, 0.0, 0.0, 1.0); 2],
    }
}

fn model() -> ColmapModel {
    let names = vec!["000000.jpg".to_string(), "b.png".to_string()];
    let mut m = ColmapModel::from_cameras(&cams(), 392, 518, &names, false, false).unwrap();
    m.images[0].points2d = vec![
        ColmapPoint2D {
            xy: pixel_to_colmap([10.0, 20.0]),
            point3d_id: Some(1),
        },
        ColmapPoint2D {
            xy: [0.1, 1.0 / 3.0],
            point3d_id: None,
        },
    ];
    m.images[1].points2d = vec![ColmapPoint2D {
        xy: [5.5, 6.5],
        point3d_id: Some(1),
    }];
    m.points3d = vec![
        ColmapPoint3D {
            id: 1,
            xyz: [1.0, -2.0, 1.0 / 7.0],
            rgb: [1, 2, 255],
            error: 0.0,
            track: vec![(1, 0), (2, 0)],
        },
        ColmapPoint3D {
            id: 7,
            xyz: [0.0; 3],
            rgb: [0; 3],
            error: 0.25,
            track: vec![],
        },
    ];
    m
}

#[test]
fn binary_and_text_roundtrip_exactly() {
    let m = model();
    for text in [false, true] {
        let dir = tempfile::tempdir().unwrap();
        write_colmap(dir.path(), &m, text).unwrap();
        let ext = if text { "txt" } else { "bin" };
        for f in ["cameras", "images", "points3D"] {
            assert!(dir.path().join(format!("{f}.{ext}")).is_file());
        }
        assert_eq!(read_colmap(dir.path()).unwrap(), m, "text={text}");
    }
}

#[test]
fn binary_layout_matches_spec() {
    let dir = tempfile::tempdir().unwrap();
    let m = model();
    write_colmap(dir.path(), &m, false).unwrap();
    let c = std::fs::read(dir.path().join("cameras.bin")).unwrap();
    assert_eq!(c.len(), 8 + 2 * (4 + 4 + 8 + 8 + 4 * 8));
    assert_eq!(&c[0..8], &2u64.to_le_bytes());
    assert_eq!(&c[8..12], &1u32.to_le_bytes());
    assert_eq!(&c[12..16], &1i32.to_le_bytes()); // PINHOLE
    assert_eq!(&c[16..24], &518u64.to_le_bytes());
    assert_eq!(&c[24..32], &392u64.to_le_bytes());
    assert_eq!(&c[48..56], &259.0f64.to_le_bytes()); // cx_colmap = cx + 0.5 = w / 2
    let i = std::fs::read(dir.path().join("images.bin")).unwrap();
    assert_eq!(
        i.len(),
        8 + (4 + 56 + 4 + 11 + 8 + 2 * 24) + (4 + 56 + 4 + 6 + 8 + 24)
    );
    let p = std::fs::read(dir.path().join("points3D.bin")).unwrap();
    assert_eq!(
        p.len(),
        8 + (8 + 24 + 3 + 8 + 8 + 16) + (8 + 24 + 3 + 8 + 8)
    );
}

#[test]
fn cameras_convert_back() {
    let dir = tempfile::tempdir().unwrap();
    write_colmap(dir.path(), &model(), false).unwrap();
    let (c, names) = read_colmap(dir.path())
        .unwrap()
        .to_cameras(dir.path())
        .unwrap();
    assert_eq!(names, vec!["000000.jpg", "b.png"]);
    let want = cams();
    for v in 0..2 {
        assert!((c.cam_from_world[v] - want.cam_from_world[v]).abs().max() < 1e-12);
        assert_eq!(c.intrinsics[v], want.intrinsics[v]);
    }
    // qw >= 0 and the quaternion is Hamilton: R(q) reproduces R.
    let r = want.rotation(1);
    let q = rotation_to_qvec(&r);
    assert!(q[0] >= 0.0);
    assert!((qvec_to_rotation(q) - r).abs().max() < 1e-12);
    // 90 degrees about z: Hamilton (cos 45, 0, 0, sin 45).
    let rz = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
    let q = rotation_to_qvec(&rz);
    assert!((q[0] - q[3]).abs() < 1e-12 && (q[0] - 0.5f64.sqrt()).abs() < 1e-12);
    // Shared SIMPLE_PINHOLE.
    let m =
        ColmapModel::from_cameras(&want, 392, 518, &["a".into(), "b".into()], true, true).unwrap();
    assert_eq!(m.cameras.len(), 1);
    assert_eq!(m.cameras[0].model, ColmapCameraModel::SimplePinhole);
    assert!(m.images.iter().all(|i| i.camera_id == 1));
}

#[test]
fn reader_accepts_all_models_and_rejects_distortion() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("cameras.txt"),
        "# c\n\n1 SIMPLE_RADIAL 10 8 5 5 4 0\n2 RADIAL 10 8 5 5 4 0 0\n3 OPENCV 10 8 5 6 5 4 0 0 0 0\n4 FULL_OPENCV 10 8 5 6 5 4 0 0 0 0 0 0 0 0\n5 OPENCV_FISHEYE 10 8 5 6 5 4 0 0 0 0\n6 OPENCV 10 8 5 6 5 4 0.1 0 0 0\n",
    )
    .unwrap();
    // Lenient images.txt: extra blank lines, missing final points line.
    std::fs::write(dir.path().join("images.txt"), "# i\n1 1 0 0 0 0 0 0 1 a.jpg\n\n\n2 1 0 0 0 0 0 0 2 b.jpg\n1.5 2.5 -1\n3 1 0 0 0 1 2 3 6 c.jpg").unwrap();
    std::fs::write(dir.path().join("points3D.txt"), "").unwrap();
    std::fs::write(dir.path().join("rigs.txt"), "# ignored\n").unwrap();
    let m = read_colmap(dir.path()).unwrap();
    assert_eq!(m.cameras.len(), 6);
    assert_eq!(m.images.len(), 3);
    assert_eq!(
        m.images[1].points2d,
        vec![ColmapPoint2D {
            xy: [1.5, 2.5],
            point3d_id: None
        }]
    );
    assert!(m.images[2].points2d.is_empty());
    for c in &m.cameras[..4] {
        let k = c.to_pinhole().unwrap();
        assert_eq!((k[(0, 2)], k[(1, 2)]), (4.5, 3.5));
    }
    assert!(m.cameras[4].to_pinhole().unwrap_err().contains("FISHEYE"));
    assert!(
        m.cameras[5]
            .to_pinhole()
            .unwrap_err()
            .contains("distortion")
    );
    let e = m.to_cameras(dir.path()).unwrap_err().to_string();
    assert!(e.contains("[camera 6]") && e.contains("distortion"), "{e}");
}

#[test]
fn prefers_binary_and_rejects_bad_files() {
    let dir = tempfile::tempdir().unwrap();
    let m = model();
    write_colmap(dir.path(), &m, false).unwrap();
    std::fs::write(dir.path().join("cameras.txt"), "garbage that would fail\n").unwrap();
    assert_eq!(read_colmap(dir.path()).unwrap(), m);
    // Truncated binary names file and record.
    let p = dir.path().join("images.bin");
    let b = std::fs::read(&p).unwrap();
    std::fs::write(&p, &b[..b.len() - 5]).unwrap();
    let e = read_colmap(dir.path()).unwrap_err().to_string();
    assert!(
        e.contains("images.bin") && e.contains("[image #1]") && e.contains("truncated"),
        "{e}"
    );
    // Huge count.
    let mut b2 = b.clone();
    b2[..8].copy_from_slice(&u64::MAX.to_le_bytes());
    std::fs::write(&p, &b2).unwrap();
    let e = read_colmap(dir.path()).unwrap_err().to_string();
    assert!(e.contains("[num_images]"), "{e}");
    std::fs::write(&p, &b).unwrap();
    // Unknown model id.
    let p = dir.path().join("cameras.bin");
    let mut c = std::fs::read(&p).unwrap();
    c[12..16].copy_from_slice(&11i32.to_le_bytes());
    std::fs::write(&p, &c).unwrap();
    let e = read_colmap(dir.path()).unwrap_err().to_string();
    assert!(
        e.contains("cameras.bin") && e.contains("[camera #0]") && e.contains("model id 11"),
        "{e}"
    );
    // Text errors name the line.
    let t = tempfile::tempdir().unwrap();
    std::fs::write(t.path().join("cameras.txt"), "1 PINHOLE 10 8 5 5 4\n").unwrap();
    std::fs::write(t.path().join("images.txt"), "").unwrap();
    std::fs::write(t.path().join("points3D.txt"), "").unwrap();
    let e = read_colmap(t.path()).unwrap_err().to_string();
    assert!(
        e.contains("cameras.txt") && e.contains("[line 1]") && e.contains("expects 4"),
        "{e}"
    );
    // Writer refuses distortion models.
    let mut m2 = model();
    m2.cameras[0] = ColmapCamera {
        id: 1,
        model: ColmapCameraModel::Opencv,
        width: 1,
        height: 1,
        params: vec![0.0; 8],
    };
    assert!(write_colmap(t.path(), &m2, false).is_err());
}

/// SIMPLE_PINHOLE uses the official focal rule `f = (fx + fy) / 2` (`sfm.md` §7.1), written and
/// read back through the one writer (`ggpt-sfm`'s `sparse/0` uses it too).
#[test]
fn simple_pinhole_focal_is_the_mean_of_fx_and_fy() {
    let c = cams(); // fx = 400, fy = 401
    let m =
        ColmapModel::from_cameras(&c, 392, 518, &["a".into(), "b".into()], true, false).unwrap();
    assert_eq!(m.cameras.len(), 2);
    for cam in &m.cameras {
        assert_eq!(cam.model, ColmapCameraModel::SimplePinhole);
        assert_eq!(cam.params, vec![400.5, 259.0, 196.0]);
    }
    assert_eq!(
        ggpt_core::io::colmap::simple_pinhole_focal(&c.intrinsics[0]),
        400.5
    );
    let dir = tempfile::tempdir().unwrap();
    write_colmap(dir.path(), &m, true).unwrap();
    let back = read_colmap(dir.path()).unwrap();
    let k = back.cameras[0].to_pinhole().unwrap();
    assert_eq!(
        (k[(0, 0)], k[(1, 1)], k[(0, 2)], k[(1, 2)]),
        (400.5, 400.5, 258.5, 195.5)
    );
}
