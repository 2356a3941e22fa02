//! Official pickles produced by a minimal torch-zip writer: strided views, dtype conversion and
//! every bad-input class (wrong dtype / shape, NaN, missing key, mismatched dims).
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

mod common;

use std::path::Path;

use common::torch::{Value, bool_tensor, f32_tensor, write_torch};
use common::{fixture, full_scene};
use ggpt_core::io::official::{read_ff_outputs_bin, read_sfm_dlt_outputs_bin};
use ggpt_core::io::read_scene;

const N: usize = 2;
const H: usize = 3;
const W: usize = 4;

fn row_major(m: &[nalgebra::Matrix3x4<f64>]) -> Vec<f32> {
    m.iter()
        .flat_map(|m| m.transpose().iter().map(|&x| x as f32).collect::<Vec<_>>())
        .collect()
}

fn k_row_major(m: &[nalgebra::Matrix3<f64>]) -> Vec<f32> {
    m.iter()
        .flat_map(|m| m.transpose().iter().map(|&x| x as f32).collect::<Vec<_>>())
        .collect()
}

/// ff_outputs entries of the synthetic scene, with `edit` applied to the named entry.
fn ff_entries(edit: Option<(&'static str, Value)>) -> Vec<(&'static str, Value)> {
    let s = full_scene(N, H, W);
    let ff = s.ff.unwrap();
    let mut e = vec![
        ("images_ff", f32_tensor(&s.images, &[N, H, W, 3])),
        (
            "extrinsics",
            f32_tensor(&row_major(&ff.cameras.cam_from_world), &[N, 3, 4]),
        ),
        (
            "intrinsics",
            f32_tensor(&k_row_major(&ff.cameras.intrinsics), &[N, 3, 3]),
        ),
        ("points", f32_tensor(&ff.points, &[N, H, W, 3])),
        ("points_conf", f32_tensor(&ff.conf, &[N, H, W])),
    ];
    if let Some((k, v)) = edit {
        e.retain(|(n, _)| *n != k);
        e.push((k, v));
    }
    e
}

fn err_ff(dir: &Path, edit: (&'static str, Value)) -> String {
    let p = dir.join("ff_outputs.bin");
    write_torch(&p, &ff_entries(Some(edit)));
    read_ff_outputs_bin(&p).unwrap_err().to_string()
}

#[test]
fn synthetic_pickle_reads_back() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("ff_outputs.bin");
    write_torch(&p, &ff_entries(None));
    let f = read_ff_outputs_bin(&p).unwrap();
    let s = full_scene(N, H, W);
    assert_eq!(f.points, s.ff.as_ref().unwrap().points);
    assert_eq!(f.images_ff, s.images);
}

#[test]
fn honours_strides_offsets_and_converts_f64() {
    let dir = tempfile::tempdir().unwrap();
    let s = full_scene(N, H, W);
    let pts = &s.ff.as_ref().unwrap().points;
    // Channel-first storage (N, 4, H, W) with a leading pad of 5 elements, viewed as (N, H, W, 3).
    let mut storage = vec![-9.0f32; 5 + N * 4 * H * W];
    for n in 0..N {
        for y in 0..H {
            for x in 0..W {
                for c in 0..3 {
                    storage[5 + ((n * 4 + c) * H + y) * W + x] = pts[((n * H + y) * W + x) * 3 + c];
                }
            }
        }
    }
    let view = Value::Tensor {
        storage: "FloatStorage",
        bytes: storage.iter().flat_map(|x| x.to_le_bytes()).collect(),
        numel: storage.len(),
        offset: 5,
        size: vec![N, H, W, 3],
        stride: vec![4 * H * W, W, 1, H * W],
    };
    let p = dir.path().join("ff_outputs.bin");
    write_torch(&p, &ff_entries(Some(("points", view))));
    assert_eq!(&read_ff_outputs_bin(&p).unwrap().points, pts);
    // f64 storage is converted like `.float()`.
    let conf = &s.ff.as_ref().unwrap().conf;
    let d = Value::Tensor {
        storage: "DoubleStorage",
        bytes: conf
            .iter()
            .flat_map(|&x| f64::from(x).to_le_bytes())
            .collect(),
        numel: conf.len(),
        offset: 0,
        size: vec![N, H, W],
        stride: vec![H * W, W, 1],
    };
    write_torch(&p, &ff_entries(Some(("points_conf", d))));
    assert_eq!(&read_ff_outputs_bin(&p).unwrap().points_conf, conf);
}

#[test]
fn wrong_dtype() {
    let dir = tempfile::tempdir().unwrap();
    let long = Value::Tensor {
        storage: "LongStorage",
        bytes: vec![0; 8 * N * H * W],
        numel: N * H * W,
        offset: 0,
        size: vec![N, H, W],
        stride: vec![H * W, W, 1],
    };
    let e = err_ff(dir.path(), ("points_conf", long));
    assert!(
        e.contains("ff_outputs.bin") && e.contains("[points_conf]") && e.contains("dtype"),
        "{e}"
    );
}

#[test]
fn wrong_shape() {
    let dir = tempfile::tempdir().unwrap();
    let e = err_ff(
        dir.path(),
        (
            "points_conf",
            f32_tensor(&[1.0; N * H * (W + 1)], &[N, H, W + 1]),
        ),
    );
    assert!(
        e.contains("ff_outputs.bin") && e.contains("[points_conf]") && e.contains("shape"),
        "{e}"
    );
    let e = err_ff(
        dir.path(),
        ("extrinsics", f32_tensor(&[0.0; 2 * 9], &[2, 3, 3])),
    );
    assert!(e.contains("[extrinsics]") && e.contains("shape"), "{e}");
}

#[test]
fn nan_and_inf() {
    let dir = tempfile::tempdir().unwrap();
    let mut v = full_scene(N, H, W).ff.unwrap().points;
    v[7] = f32::NAN;
    let e = err_ff(dir.path(), ("points", f32_tensor(&v, &[N, H, W, 3])));
    assert!(
        e.contains("[points]") && e.contains("non-finite") && e.contains("index 7"),
        "{e}"
    );
    let mut k = vec![0.0f32; N * 9];
    k[4] = f32::INFINITY;
    let e = err_ff(dir.path(), ("intrinsics", f32_tensor(&k, &[N, 3, 3])));
    assert!(
        e.contains("[intrinsics]") && e.contains("non-finite"),
        "{e}"
    );
}

#[test]
fn storage_shorter_than_view() {
    let dir = tempfile::tempdir().unwrap();
    let short = Value::Tensor {
        storage: "FloatStorage",
        bytes: vec![0; 4 * 10],
        numel: 10,
        offset: 0,
        size: vec![N, H, W],
        stride: vec![H * W, W, 1],
    };
    let e = err_ff(dir.path(), ("points_conf", short));
    assert!(e.contains("ff_outputs.bin"), "{e}");
}

#[test]
fn missing_python_bool_and_bad_mask() {
    let dir = tempfile::tempdir().unwrap();
    let s = full_scene(N, H, W);
    let sfm = s.sfm.unwrap();
    let p = dir.path().join("sfm_dlt_outputs.bin");
    let mut entries = vec![
        (
            "intrinsics",
            f32_tensor(&k_row_major(&sfm.cameras.intrinsics), &[N, 3, 3]),
        ),
        (
            "extrinsics",
            f32_tensor(&row_major(&sfm.cameras.cam_from_world), &[N, 3, 4]),
        ),
        ("camera_success", Value::Bool(true)),
        ("points", f32_tensor(&sfm.points, &[N, H, W, 3])),
        ("point_masks", bool_tensor(&sfm.mask, &[N, H, W])),
    ];
    write_torch(&p, &entries);
    let e = read_sfm_dlt_outputs_bin(&p).unwrap_err().to_string();
    assert!(
        e.contains("sfm_dlt_outputs.bin") && e.contains("[points_success]"),
        "{e}"
    );
    entries.push(("points_success", Value::Bool(false)));
    write_torch(&p, &entries);
    let r = read_sfm_dlt_outputs_bin(&p).unwrap();
    assert!(r.camera_success && !r.points_success);
    assert_eq!(r.point_masks, sfm.mask);
    entries[4] = ("point_masks", f32_tensor(&[0.0; N * H * W], &[N, H, W]));
    write_torch(&p, &entries);
    let e = read_sfm_dlt_outputs_bin(&p).unwrap_err().to_string();
    assert!(e.contains("[point_masks]") && e.contains("dtype"), "{e}");
}

#[test]
fn mismatched_dims_across_official_files() {
    let dir = tempfile::tempdir().unwrap();
    let seq = dir.path().join("seq");
    std::fs::create_dir(&seq).unwrap();
    write_torch(&seq.join("ff_outputs.bin"), &ff_entries(None));
    std::fs::copy(fixture("gt.bin"), seq.join("gt.bin")).unwrap();
    let e = read_scene(&seq).unwrap_err().to_string();
    assert!(
        e.contains("gt.bin")
            && e.contains("[points]")
            && e.contains("N=4 h=42 w=56")
            && e.contains("N=2 h=3 w=4"),
        "{e}"
    );
}

#[test]
fn corrupt_pickle_stream() {
    use std::io::Write;
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("ff_outputs.bin");
    for pkl in [
        &b"\x80\x02}q\x00(X\x05\x00\x00\x00pointsq"[..],
        b"\x80\x02\xff\xfe garbage opcode",
        b"",
    ] {
        let mut zw = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
        let opts = zip::write::SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Stored);
        zw.start_file("ff_outputs/data.pkl", opts).unwrap();
        zw.write_all(pkl).unwrap();
        zw.start_file("ff_outputs/version", opts).unwrap();
        zw.write_all(b"3\n").unwrap();
        std::fs::write(&p, zw.finish().unwrap().into_inner()).unwrap();
        let e = read_ff_outputs_bin(&p).unwrap_err().to_string();
        assert!(
            e.contains("ff_outputs.bin") && e.contains("torch pickle"),
            "{e}"
        );
    }
    // A valid pickle whose storage entry is missing from the archive.
    write_torch(&p, &ff_entries(None));
    let bytes = std::fs::read(&p).unwrap();
    let mut zr = zip::ZipArchive::new(std::io::Cursor::new(bytes)).unwrap();
    let mut zw = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    for i in 0..zr.len() {
        let mut f = zr.by_index(i).unwrap();
        let name = f.name().unwrap().into_owned();
        if name == "ff_outputs/data/3" {
            continue;
        }
        let mut buf = Vec::new();
        std::io::Read::read_to_end(&mut f, &mut buf).unwrap();
        zw.start_file(
            name,
            zip::write::SimpleFileOptions::default()
                .compression_method(zip::CompressionMethod::Stored),
        )
        .unwrap();
        zw.write_all(&buf).unwrap();
    }
    std::fs::write(&p, zw.finish().unwrap().into_inner()).unwrap();
    let e = read_ff_outputs_bin(&p).unwrap_err().to_string();
    assert!(e.contains("ff_outputs.bin"), "{e}");
}
