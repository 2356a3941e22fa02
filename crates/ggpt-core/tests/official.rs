//! Official torch-pickle scene dicts against `reference.safetensors` (exact equality).
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

mod common;

use common::{fixture, fixture_dir, full_scene};
use ggpt_core::io::official::{
    read_ff_outputs_bin, read_gt_bin, read_sfm_dlt_outputs_bin, write_official_safetensors,
};
use ggpt_core::io::read_scene;
use ggpt_core::io::st::StFile;

fn reference() -> StFile {
    StFile::open(&fixture("reference.safetensors")).unwrap()
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

#[test]
fn gt_bin_matches_reference_exactly() {
    let r = reference();
    let g = read_gt_bin(&fixture("gt.bin")).unwrap();
    let (n, h, w) = (g.dims.n, g.dims.h, g.dims.w);
    assert_eq!((n, h, w), (4, 42, 56));
    assert_eq!(
        bits(&g.points),
        bits(&r.f32("gt/points", &[n, h, w, 3]).unwrap())
    );
    assert_eq!(g.point_masks, r.bool("gt/point_masks", &[n, h, w]).unwrap());
    assert_eq!(
        bits(&g.intrinsics),
        bits(&r.f32("gt/intrinsics", &[n, 3, 3]).unwrap())
    );
    assert_eq!(
        bits(&g.extrinsics),
        bits(&r.f32("gt/extrinsics", &[n, 4, 4]).unwrap())
    );
    assert_eq!(
        bits(&g.images),
        bits(&r.f32("gt/images", &[n, h, w, 3]).unwrap())
    );
    // The strided points view really is non-trivial: some valid points differ from zero.
    assert!(g.points.iter().any(|&x| x != 0.0) && g.point_masks.iter().any(|&m| !m));
}

#[test]
fn ff_outputs_bin_matches_reference_exactly() {
    let r = reference();
    let f = read_ff_outputs_bin(&fixture("ff_outputs.bin")).unwrap();
    let (n, h, w) = (f.dims.n, f.dims.h, f.dims.w);
    assert_eq!(
        bits(&f.images_ff),
        bits(&r.f32("ff_outputs/images_ff", &[n, h, w, 3]).unwrap())
    );
    assert_eq!(
        bits(&f.extrinsics),
        bits(&r.f32("ff_outputs/extrinsics", &[n, 3, 4]).unwrap())
    );
    assert_eq!(
        bits(&f.intrinsics),
        bits(&r.f32("ff_outputs/intrinsics", &[n, 3, 3]).unwrap())
    );
    assert_eq!(
        bits(&f.points),
        bits(&r.f32("ff_outputs/points", &[n, h, w, 3]).unwrap())
    );
    assert_eq!(
        bits(&f.points_conf),
        bits(&r.f32("ff_outputs/points_conf", &[n, h, w]).unwrap())
    );
}

#[test]
fn sfm_dlt_outputs_bin_matches_reference_exactly() {
    let r = reference();
    let s = read_sfm_dlt_outputs_bin(&fixture("sfm_dlt_outputs.bin")).unwrap();
    let (n, h, w) = (s.dims.n, s.dims.h, s.dims.w);
    assert_eq!(
        bits(&s.intrinsics),
        bits(&r.f32("sfm_dlt_outputs/intrinsics", &[n, 3, 3]).unwrap())
    );
    assert_eq!(
        bits(&s.extrinsics),
        bits(&r.f32("sfm_dlt_outputs/extrinsics", &[n, 3, 4]).unwrap())
    );
    assert_eq!(
        bits(&s.points),
        bits(&r.f32("sfm_dlt_outputs/points", &[n, h, w, 3]).unwrap())
    );
    assert_eq!(
        s.point_masks,
        r.bool("sfm_dlt_outputs/point_masks", &[n, h, w]).unwrap()
    );
    assert_eq!(
        s.camera_success,
        r.scalar_bool("sfm_dlt_outputs/camera_success").unwrap()
    );
    assert_eq!(
        s.points_success,
        r.scalar_bool("sfm_dlt_outputs/points_success").unwrap()
    );
}

#[test]
fn official_dir_to_scene_and_reference_writer() {
    let scene = read_scene(&fixture_dir()).unwrap();
    assert_eq!(scene.name, "synth_room_s0");
    assert!(scene.gt.is_some() && scene.ff.is_some() && scene.sfm.is_some());
    let gt = scene.gt.as_ref().unwrap();
    assert_eq!(gt.cameras.cam_from_world.len(), 4);
    // Writing the scene back in the reference layout reproduces every reference tensor bit for bit.
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("ref.safetensors");
    write_official_safetensors(&out, &scene).unwrap();
    let (a, r) = (StFile::open(&out).unwrap(), reference());
    for key in a.keys() {
        let (da, sa, ba) = a.tensor(&key).unwrap();
        let (dr, sr, br) = r.tensor(&key).unwrap();
        assert_eq!((da, sa), (dr, sr), "{key}");
        assert!(ba == br, "{key} differs");
    }
    assert_eq!(a.keys().len(), 16);
    // Round trip of a synthetic scene through the writer.
    let s = full_scene(2, 3, 4);
    write_official_safetensors(&out, &s).unwrap();
    let f = StFile::open(&out).unwrap();
    assert_eq!(
        bits(&f.f32("ff_outputs/points", &[2, 3, 4, 3]).unwrap()),
        bits(&s.ff.as_ref().unwrap().points)
    );
    assert!(!f.scalar_bool("sfm_dlt_outputs/points_success").unwrap());
}

#[test]
fn corrupt_and_truncated_pickles_name_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let bytes = std::fs::read(fixture("ff_outputs.bin")).unwrap();
    let p = dir.path().join("ff_outputs.bin");
    std::fs::write(&p, &bytes[..bytes.len() / 2]).unwrap();
    let e = read_ff_outputs_bin(&p).unwrap_err().to_string();
    assert!(e.contains("ff_outputs.bin"), "{e}");
    std::fs::write(&p, b"PK\x03\x04 this is not a zip").unwrap();
    let e = read_ff_outputs_bin(&p).unwrap_err().to_string();
    assert!(
        e.contains("ff_outputs.bin") && e.contains("torch pickle"),
        "{e}"
    );
    // Flip bytes inside the stored data of the points storage (crc mismatch in the zip).
    let mut b = bytes.clone();
    let mid = b.len() / 2;
    for x in &mut b[mid..mid + 64] {
        *x ^= 0xa5;
    }
    std::fs::write(&p, &b).unwrap();
    let e = read_ff_outputs_bin(&p).unwrap_err().to_string();
    assert!(e.contains("ff_outputs.bin"), "{e}");
    // Wrong file for the reader: gt.bin lacks `points_conf`.
    let e = read_ff_outputs_bin(&fixture("gt.bin"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("gt.bin") && e.contains("[images_ff]"), "{e}");
}

#[test]
fn official_subset_without_sfm() {
    let dir = tempfile::tempdir().unwrap();
    let seq = dir.path().join("seq");
    std::fs::create_dir(&seq).unwrap();
    std::fs::copy(fixture("ff_outputs.bin"), seq.join("ff_outputs.bin")).unwrap();
    std::fs::copy(fixture("gt.bin"), seq.join("gt.bin")).unwrap();
    let s = read_scene(&seq).unwrap();
    assert!(s.sfm.is_none() && s.gt.is_some() && s.ff.is_some());
    assert_eq!(s.name, "seq");
}
