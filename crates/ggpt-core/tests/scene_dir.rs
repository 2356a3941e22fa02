//! Project scene directory: lossless round trip and rejection of every bad-input class.
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

mod common;

use std::path::Path;

use common::full_scene;
use ggpt_core::io::read_scene;
use ggpt_core::io::scene_dir::{MANIFEST, Manifest, TENSORS, read_manifest, write_scene};
use ggpt_core::io::st::{Dtype, StFile, StWriter};

fn written() -> (tempfile::TempDir, ggpt_core::Scene) {
    let dir = tempfile::tempdir().unwrap();
    let scene = full_scene(2, 3, 4);
    write_scene(dir.path(), &scene).unwrap();
    (dir, scene)
}

/// Recomputes size + crc32 of every file in the manifest (to test the layers below the checksum).
fn fix_checksums(dir: &Path) {
    let mut m: Manifest = read_manifest(dir).unwrap();
    for f in &mut m.files {
        let b = std::fs::read(dir.join(&f.path)).unwrap();
        f.bytes = b.len() as u64;
        f.crc32 = format!("{:08x}", crc32fast_hash(&b));
    }
    std::fs::write(dir.join(MANIFEST), serde_json::to_vec(&m).unwrap()).unwrap();
}

fn crc32fast_hash(b: &[u8]) -> u32 {
    // Bitwise CRC-32 (IEEE), independent of the implementation under test.
    let mut crc = 0xffff_ffffu32;
    for &byte in b {
        crc ^= byte as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xedb8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// Rewrites `scene.safetensors` with tensor `key` replaced by `edit(dtype, shape, bytes)`
/// (`None` drops it), then fixes the checksums.
fn edit_tensor(
    dir: &Path,
    key: &str,
    edit: impl Fn(Dtype, &[usize], &[u8]) -> Option<(Dtype, Vec<usize>, Vec<u8>)>,
) {
    let p = dir.join(TENSORS);
    let f = StFile::open(&p).unwrap();
    let mut w = StWriter::new();
    for k in f.keys() {
        let (dt, shape, bytes) = f.tensor(&k).unwrap();
        if k == key {
            if let Some((dt, shape, bytes)) = edit(dt, shape, bytes) {
                w.raw(&k, dt, &shape, bytes);
            }
        } else {
            w.raw(&k, dt, shape, bytes.to_vec());
        }
    }
    std::fs::write(&p, w.finish(&p, None).unwrap()).unwrap();
    fix_checksums(dir);
}

fn err_of(dir: &Path) -> String {
    read_scene(dir).unwrap_err().to_string()
}

fn assert_names(e: &str, file: &str, key: &str) {
    assert!(e.contains(file), "error does not name file {file}: {e}");
    assert!(
        e.contains(&format!("[{key}]")),
        "error does not name key {key}: {e}"
    );
}

#[test]
fn roundtrip_is_lossless() {
    let (dir, scene) = written();
    let back = read_scene(dir.path()).unwrap();
    assert_eq!(back, scene);
    assert!(
        dir.path().join("images/000000.png").is_file()
            && dir.path().join("images/000001.png").is_file()
    );
    assert!(dir.path().join("matches/romav2-base.safetensors").is_file());
    // Bit-exactness including -0.0 / subnormals: compare bit patterns too.
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(
        bits(&back.ff.unwrap().points),
        bits(&scene.ff.unwrap().points)
    );
    // Optional parts absent.
    let mut s2 = full_scene(1, 2, 2);
    s2.gt = None;
    s2.sfm = None;
    s2.matches.clear();
    let d2 = tempfile::tempdir().unwrap();
    write_scene(d2.path(), &s2).unwrap();
    assert_eq!(read_scene(d2.path()).unwrap(), s2);
    let mut s3 = full_scene(2, 2, 3);
    s3.gt.as_mut().unwrap().depth = None;
    s3.ff = None;
    let d3 = tempfile::tempdir().unwrap();
    write_scene(d3.path(), &s3).unwrap();
    assert_eq!(read_scene(d3.path()).unwrap(), s3);
}

#[test]
fn writer_rejects_bad_matcher_name_and_invalid_scene() {
    let dir = tempfile::tempdir().unwrap();
    let mut s = full_scene(2, 3, 4);
    s.matches[0].matcher = "../evil".into();
    assert!(
        write_scene(dir.path(), &s)
            .unwrap_err()
            .to_string()
            .contains("matcher name")
    );
    let mut s = full_scene(2, 3, 4);
    s.images.pop();
    assert!(write_scene(dir.path(), &s).is_err());
}

#[test]
fn checksum_mismatch() {
    let (dir, _) = written();
    let p = dir.path().join(TENSORS);
    let mut b = std::fs::read(&p).unwrap();
    let last = b.len() - 1;
    b[last] ^= 0x55;
    std::fs::write(&p, b).unwrap();
    assert_names(&err_of(dir.path()), TENSORS, "crc32");
}

#[test]
fn truncated_file() {
    let (dir, _) = written();
    let p = dir.path().join("matches/synthetic_b.safetensors");
    let b = std::fs::read(&p).unwrap();
    std::fs::write(&p, &b[..b.len() - 10]).unwrap();
    assert_names(&err_of(dir.path()), "synthetic_b.safetensors", "bytes");
    // With a manifest that agrees, the safetensors layer itself must reject it.
    fix_checksums(dir.path());
    let e = err_of(dir.path());
    assert!(
        e.contains("synthetic_b.safetensors") && e.contains("truncated or corrupt"),
        "{e}"
    );
}

#[test]
fn wrong_dtype() {
    let (dir, _) = written();
    edit_tensor(dir.path(), "gt/K", |_, shape, bytes| {
        let v: Vec<u8> = bytes
            .chunks_exact(8)
            .flat_map(|c| (f64::from_le_bytes(c.try_into().unwrap()) as f32).to_le_bytes())
            .collect();
        Some((Dtype::F32, shape.to_vec(), v))
    });
    let e = err_of(dir.path());
    assert_names(&e, TENSORS, "gt/K");
    assert!(e.contains("dtype"), "{e}");
}

#[test]
fn wrong_shape() {
    let (dir, _) = written();
    edit_tensor(dir.path(), "ff/conf", |dt, _, bytes| {
        Some((dt, vec![2, 4, 3], bytes.to_vec()))
    });
    let e = err_of(dir.path());
    assert_names(&e, TENSORS, "ff/conf");
    assert!(e.contains("shape"), "{e}");
}

#[test]
fn nan_and_inf() {
    for (key, bad) in [
        ("ff/points", f32::NAN),
        ("ff/conf", f32::INFINITY),
        ("gt/points", f32::NEG_INFINITY),
        ("sfm/points", f32::NAN),
    ] {
        let (dir, _) = written();
        edit_tensor(dir.path(), key, |dt, shape, bytes| {
            let mut b = bytes.to_vec();
            b[4..8].copy_from_slice(&bad.to_le_bytes());
            Some((dt, shape.to_vec(), b))
        });
        let e = err_of(dir.path());
        assert_names(&e, TENSORS, key);
        assert!(e.contains("non-finite") && e.contains("index 1"), "{e}");
    }
    let (dir, _) = written();
    edit_tensor(dir.path(), "sfm/cam_from_world", |dt, shape, bytes| {
        let mut b = bytes.to_vec();
        b[0..8].copy_from_slice(&f64::NAN.to_le_bytes());
        Some((dt, shape.to_vec(), b))
    });
    assert_names(&err_of(dir.path()), TENSORS, "sfm/cam_from_world");
}

#[test]
fn missing_and_unexpected_key() {
    let (dir, _) = written();
    edit_tensor(dir.path(), "sfm/points_success", |_, _, _| None);
    let e = err_of(dir.path());
    assert_names(&e, TENSORS, "sfm/points_success");
    assert!(e.contains("missing"), "{e}");
    let (dir, _) = written();
    let mut m = read_manifest(dir.path()).unwrap();
    m.parts.gt_depth = false;
    std::fs::write(dir.path().join(MANIFEST), serde_json::to_vec(&m).unwrap()).unwrap();
    assert_names(&err_of(dir.path()), TENSORS, "gt/depth");
}

#[test]
fn bad_bool_byte() {
    let (dir, _) = written();
    edit_tensor(dir.path(), "gt/mask", |dt, shape, bytes| {
        let mut b = bytes.to_vec();
        b[3] = 7;
        Some((dt, shape.to_vec(), b))
    });
    assert_names(&err_of(dir.path()), TENSORS, "gt/mask");
}

#[test]
fn mismatched_dims_across_files() {
    let (dir, _) = written();
    // Replace one matcher file by one written for a different resolution.
    let other = full_scene(2, 4, 3);
    let p = dir.path().join("matches/romav2-base.safetensors");
    ggpt_core::io::matches::write_matches(&p, &other.matches[0], 2, 4, 3).unwrap();
    fix_checksums(dir.path());
    let e = err_of(dir.path());
    assert_names(&e, "romav2-base.safetensors", "pred_matches");
    // The manifest disagreeing with scene.safetensors (n) names the tensor file and key.
    let (dir, _) = written();
    let mut m = read_manifest(dir.path()).unwrap();
    m.n = 3;
    std::fs::write(dir.path().join(MANIFEST), serde_json::to_vec(&m).unwrap()).unwrap();
    let e = err_of(dir.path());
    assert_names(&e, TENSORS, "images");
}

#[test]
fn corrupt_manifest() {
    let (dir, _) = written();
    std::fs::write(
        dir.path().join(MANIFEST),
        b"{\"format\": \"ggpt-rs-scene\", ",
    )
    .unwrap();
    let e = err_of(dir.path());
    assert!(e.contains(MANIFEST) && e.contains("JSON"), "{e}");
    let (dir, _) = written();
    let mut m = read_manifest(dir.path()).unwrap();
    m.version = 99;
    std::fs::write(dir.path().join(MANIFEST), serde_json::to_vec(&m).unwrap()).unwrap();
    assert_names(&err_of(dir.path()), MANIFEST, "version");
    let e = ggpt_core::io::read_scene(&dir.path().join("images"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("not a scene directory"), "{e}");
}
