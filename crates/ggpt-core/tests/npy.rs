//! npy / npz reading and writing, including the fixture's NumPy-written files.
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

mod common;

use common::fixture;
use ggpt_core::io::npy::{
    NpyArray, NpyData, encode_npy, parse_npy, read_npy, read_npz, write_npy, write_npz,
};
use ggpt_core::io::st::StFile;
use std::path::Path;

fn all_dtypes() -> Vec<(&'static str, NpyArray)> {
    vec![
        (
            "f4",
            NpyArray::new(
                vec![2, 3],
                NpyData::F32(vec![1.0, -2.5, f32::MIN_POSITIVE, 0.0, -0.0, 7.0]),
            )
            .unwrap(),
        ),
        (
            "f8",
            NpyArray::new(
                vec![3],
                NpyData::F64(vec![1e-300, std::f64::consts::PI, -1.0]),
            )
            .unwrap(),
        ),
        (
            "i4",
            NpyArray::new(vec![1, 2, 2], NpyData::I32(vec![i32::MIN, -1, 0, i32::MAX])).unwrap(),
        ),
        (
            "i8",
            NpyArray::new(vec![2], NpyData::I64(vec![i64::MIN, i64::MAX])).unwrap(),
        ),
        (
            "u1",
            NpyArray::new(vec![4], NpyData::U8(vec![0, 1, 254, 255])).unwrap(),
        ),
        (
            "u2",
            NpyArray::new(vec![2, 1], NpyData::U16(vec![0, 65535])).unwrap(),
        ),
        (
            "b1",
            NpyArray::new(vec![], NpyData::Bool(vec![true])).unwrap(),
        ),
        (
            "empty",
            NpyArray::new(vec![0, 3], NpyData::F32(vec![])).unwrap(),
        ),
    ]
}

#[test]
fn npy_roundtrip_every_dtype() {
    let dir = tempfile::tempdir().unwrap();
    for (name, a) in all_dtypes() {
        let p = dir.path().join(format!("{name}.npy"));
        write_npy(&p, &a).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        assert_eq!(&bytes[..8], b"\x93NUMPY\x01\x00");
        let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        assert_eq!((10 + hlen) % 64, 0, "data not 64-aligned");
        assert_eq!(bytes[9 + hlen], b'\n');
        assert_eq!(read_npy(&p).unwrap(), a, "{name}");
    }
}

#[test]
fn npz_roundtrip_stored_and_deflated() {
    let dir = tempfile::tempdir().unwrap();
    let arrays = all_dtypes();
    let refs: Vec<(&str, &NpyArray)> = arrays.iter().map(|(k, a)| (*k, a)).collect();
    for store in [false, true] {
        let p = dir.path().join("a.npz");
        write_npz(&p, &refs, store).unwrap();
        let back = read_npz(&p).unwrap();
        assert_eq!(back.len(), arrays.len());
        for (k, a) in &arrays {
            assert_eq!(&back[*k], a, "{k}");
        }
    }
}

#[test]
fn reads_numpy_written_fixture_files() {
    // The fixture's depths / poses were written by NumPy; compare with reference.safetensors.
    let r = StFile::open(&fixture("reference.safetensors")).unwrap();
    let e = read_npy(&fixture("extrinsics.npy")).unwrap();
    assert_eq!(e.shape, vec![4, 4, 4]);
    assert_eq!(
        e.data,
        NpyData::F64(r.f64("raw/extrinsics", &[4, 4, 4]).unwrap())
    );
    let k = read_npy(&fixture("intrinsics.npy")).unwrap();
    assert_eq!(
        k.data,
        NpyData::F64(r.f64("raw/intrinsics", &[4, 3, 3]).unwrap())
    );
    let depths = r.f32("raw/depths", &[4, 84, 112]).unwrap();
    for i in 0..4 {
        let d = read_npy(&fixture(&format!("depths/{i:06}.npy"))).unwrap();
        assert_eq!(d.shape, vec![84, 112]);
        assert_eq!(
            d.data,
            NpyData::F32(depths[i * 84 * 112..(i + 1) * 84 * 112].to_vec())
        );
    }
}

fn npy_with_header(dict: &str, major: u8, data: &[u8]) -> Vec<u8> {
    let mut h = dict.to_string();
    let pre = if major == 1 { 10 } else { 12 };
    while !(pre + h.len() + 1).is_multiple_of(64) {
        h.push(' ');
    }
    h.push('\n');
    let mut out = b"\x93NUMPY".to_vec();
    out.extend_from_slice(&[major, 0]);
    if major == 1 {
        out.extend_from_slice(&(h.len() as u16).to_le_bytes());
    } else {
        out.extend_from_slice(&(h.len() as u32).to_le_bytes());
    }
    out.extend_from_slice(h.as_bytes());
    out.extend_from_slice(data);
    out
}

#[test]
fn versions_2_3_and_fortran_order() {
    let p = Path::new("x.npy");
    let data: Vec<u8> = [0i32, 3, 1, 4, 2, 5]
        .iter()
        .flat_map(|x| x.to_le_bytes())
        .collect();
    for major in [1u8, 2, 3] {
        let b = npy_with_header(
            "{'descr': '<i4', 'fortran_order': True, 'shape': (2, 3), }",
            major,
            &data,
        );
        let a = parse_npy(p, "", &b).unwrap();
        assert_eq!(a.shape, vec![2, 3]);
        assert_eq!(a.data, NpyData::I32(vec![0, 1, 2, 3, 4, 5]), "v{major}");
    }
    // 3-D Fortran: element (i,j,k) at i + 2j + 4k for shape (2,2,2).
    let f: Vec<u8> = (0..8u8).collect();
    let b = npy_with_header(
        "{'descr': '|u1', 'fortran_order': True, 'shape': (2, 2, 2), }",
        1,
        &f,
    );
    let a = parse_npy(p, "", &b).unwrap();
    assert_eq!(a.data, NpyData::U8(vec![0, 4, 2, 6, 1, 5, 3, 7]));
}

#[test]
fn rejects_bad_npy() {
    let p = Path::new("bad.npy");
    let good = encode_npy(&NpyArray::new(vec![4], NpyData::F32(vec![1.0; 4])).unwrap()).unwrap();
    let e = parse_npy(p, "k", &good[..good.len() - 1])
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("bad.npy") && e.contains("[k]") && e.contains("truncated"),
        "{e}"
    );
    let e = parse_npy(p, "", &good[..20]).unwrap_err().to_string();
    assert!(e.contains("truncated"), "{e}");
    let b = npy_with_header(
        "{'descr': '>f4', 'fortran_order': False, 'shape': (1,), }",
        1,
        &[0; 4],
    );
    assert!(
        parse_npy(p, "", &b)
            .unwrap_err()
            .to_string()
            .contains("'>f4'")
    );
    let b = npy_with_header(
        "{'descr': '<c8', 'fortran_order': False, 'shape': (1,), }",
        1,
        &[0; 8],
    );
    assert!(
        parse_npy(p, "", &b)
            .unwrap_err()
            .to_string()
            .contains("unsupported dtype")
    );
    let b = npy_with_header(
        "{'descr': '|b1', 'fortran_order': False, 'shape': (2,), }",
        1,
        &[1, 2],
    );
    assert!(
        parse_npy(p, "", &b)
            .unwrap_err()
            .to_string()
            .contains("bool byte 2")
    );
    let b = npy_with_header("{'descr': '<f4', 'fortran_order': False, }", 1, &[]);
    assert!(
        parse_npy(p, "", &b)
            .unwrap_err()
            .to_string()
            .contains("missing 'shape'")
    );
    assert!(
        parse_npy(p, "", b"not numpy at all")
            .unwrap_err()
            .to_string()
            .contains("magic")
    );
}

#[test]
fn rejects_corrupt_npz() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("c.npz");
    let a = NpyArray::new(vec![64], NpyData::F64(vec![0.5; 64])).unwrap();
    write_npz(&p, &[("points", &a)], true).unwrap();
    let b = std::fs::read(&p).unwrap();
    std::fs::write(&p, &b[..b.len() / 2]).unwrap();
    let e = read_npz(&p).unwrap_err().to_string();
    assert!(e.contains("c.npz") && e.contains("npz"), "{e}");
    // Corrupt payload of a stored member -> CRC error or npy error naming the member.
    let mut b2 = b.clone();
    b2[120] ^= 0xff;
    std::fs::write(&p, &b2).unwrap();
    let e = read_npz(&p).unwrap_err().to_string();
    assert!(e.contains("c.npz") && e.contains("[points]"), "{e}");
}
