//! GGPT_eval raw layout -> ff resolution, against the fixture's `gt.bin` content.
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

mod common;

use std::path::{Path, PathBuf};

use common::{fixture, fixture_dir};
use ggpt_core::io::ggpt_eval::{ff_size, prepare_ff_resolution, read_raw_sequence};
use ggpt_core::io::npy::{NpyArray, NpyData, read_npy, write_npy};
use ggpt_core::io::st::StFile;

/// JPEG decoders differ from libjpeg (OpenCV) by a few levels per channel (fixture README: "may
/// differ by +-1-2"; the `image` crate's decoder measured max 4 levels on this fixture, from
/// chroma upsampling / IDCT rounding); bilinear weights are convex, so the resized images differ
/// by at most the same amount / 255.
const JPEG_DECODER_TOL_U8: u8 = 4;

fn reference() -> StFile {
    StFile::open(&fixture("reference.safetensors")).unwrap()
}

fn max_abs(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

#[test]
fn ff_size_rule() {
    assert_eq!(ff_size(84, 112, 56), (42, 56));
    assert_eq!(ff_size(1080, 1920, 518), (294, 518)); // 518*1080/1920/14 = 20.8125 -> 21
    assert_eq!(ff_size(378, 518, 518), (378, 518)); // used as is
    assert_eq!(ff_size(7, 4, 8), (14, 8)); // 1.0 exactly
    assert_eq!(ff_size(35, 56, 56), (28, 56)); // 2.5 -> 2 (Python rounds half to even)
}

#[test]
fn raw_sequence_matches_reference() {
    let r = reference();
    let raw = read_raw_sequence(&fixture_dir()).unwrap();
    assert_eq!((raw.n, raw.height, raw.width), (4, 84, 112));
    assert_eq!(raw.name, "synth_room_s0");
    assert_eq!(raw.depths, r.f32("raw/depths", &[4, 84, 112]).unwrap());
    let e: Vec<f64> = raw
        .cam_from_world
        .iter()
        .flat_map(|m| m.transpose().iter().copied().collect::<Vec<_>>())
        .collect();
    let re = r.f64("raw/extrinsics", &[4, 4, 4]).unwrap();
    let re34: Vec<f64> = re.chunks_exact(16).flat_map(|m| m[..12].to_vec()).collect();
    assert_eq!(e, re34);
    let ru8 = r.u8("raw/images_u8_decoded", &[4, 84, 112, 3]).unwrap();
    let diff = raw
        .images
        .iter()
        .zip(&ru8)
        .map(|(a, b)| a.abs_diff(*b))
        .max()
        .unwrap();
    assert!(
        diff <= JPEG_DECODER_TOL_U8,
        "JPEG decode differs from libjpeg by {diff}"
    );
    let mean = raw
        .images
        .iter()
        .zip(&ru8)
        .map(|(a, b)| a.abs_diff(*b) as f64)
        .sum::<f64>()
        / ru8.len() as f64;
    eprintln!("JPEG decode vs libjpeg: max {diff} levels, mean {mean:.3}");
    assert!(mean < 1.0, "mean JPEG decode difference {mean}");
}

#[test]
fn prepare_matches_gt_bin() {
    let r = reference();
    let mut raw = read_raw_sequence(&fixture_dir()).unwrap();
    let ours = prepare_ff_resolution(&raw, 56).unwrap();
    // With the reference decoder's pixels the resize must agree to float rounding.
    raw.images = r.u8("raw/images_u8_decoded", &[4, 84, 112, 3]).unwrap();
    let s = prepare_ff_resolution(&raw, 56).unwrap();
    let (n, h, w) = (s.dims.n, s.dims.h, s.dims.w);
    assert_eq!((n, h, w), (4, 42, 56));
    let ref_images = r.f32("gt/images", &[n, h, w, 3]).unwrap();
    let d = max_abs(&s.images, &ref_images);
    eprintln!("bilinear resize (reference pixels) max |diff| = {d:e}");
    assert!(d <= 1e-6, "bilinear resize differs by {d}");
    let d = max_abs(&ours.images, &ref_images);
    eprintln!(
        "resize of our JPEG decode max |diff| = {d:e} ({:.2} u8 levels)",
        d * 255.0
    );
    assert!(
        d <= JPEG_DECODER_TOL_U8 as f32 / 255.0 + 1e-6,
        "resize of our JPEG decode differs by {d}"
    );
    let gt = s.gt.as_ref().unwrap();
    assert_eq!(gt.mask, r.bool("gt/point_masks", &[n, h, w]).unwrap());
    let k: Vec<f32> = gt
        .cameras
        .intrinsics
        .iter()
        .flat_map(|m| m.transpose().iter().map(|&x| x as f32).collect::<Vec<_>>())
        .collect();
    let rk = r.f32("gt/intrinsics", &[n, 3, 3]).unwrap();
    for (a, b) in k.iter().zip(&rk) {
        assert!((a - b).abs() <= 1e-6 * b.abs().max(1.0), "K {a} vs {b}");
    }
    let ext: Vec<f32> = gt
        .cameras
        .cam_from_world
        .iter()
        .flat_map(|m| m.transpose().iter().map(|&x| x as f32).collect::<Vec<_>>())
        .collect();
    let rext: Vec<f32> = r
        .f32("gt/extrinsics", &[n, 4, 4])
        .unwrap()
        .chunks_exact(16)
        .flat_map(|m| m[..12].to_vec())
        .collect();
    assert_eq!(ext, rext);
    // Points: the official unprojection runs in f32 (einsum), ours in f64; points are a few
    // metres from the origin, so f32 rounding of the chain is ~1e-6 m; allow 1e-5 m.
    let rp = r.f32("gt/points", &[n, h, w, 3]).unwrap();
    let d = max_abs(&gt.points, &rp);
    eprintln!("GT points max |diff| = {d:e} m");
    assert!(d <= 1e-5, "GT points differ by {d} m");
    assert!(rp.iter().any(|&x| x != 0.0));
    // Zeros exactly where the reference has zeros.
    for (p, (a, b)) in gt
        .points
        .chunks_exact(3)
        .zip(rp.chunks_exact(3))
        .enumerate()
    {
        assert_eq!(a == [0.0; 3], b == [0.0; 3], "pixel {p}");
    }
}

#[test]
fn rejects_bad_layouts() {
    let (_tmp, seq) = sequence_copy();
    // Gap in the names.
    std::fs::rename(seq.join("images/000003.jpg"), seq.join("images/000004.jpg")).unwrap();
    let e = read_raw_sequence(&seq).unwrap_err().to_string();
    assert!(e.contains("000004.jpg") && e.contains("000003.jpg"), "{e}");
    std::fs::rename(seq.join("images/000004.jpg"), seq.join("images/000003.jpg")).unwrap();
    // Missing depth.
    std::fs::remove_file(seq.join("depths/000002.npy")).unwrap();
    let e = read_raw_sequence(&seq).unwrap_err().to_string();
    assert!(e.contains("000002.npy"), "{e}");
    std::fs::copy(fixture("depths/000002.npy"), seq.join("depths/000002.npy")).unwrap();
    // Principal point not centred.
    let mut k = read_npy(&seq.join("intrinsics.npy")).unwrap();
    if let NpyData::F64(v) = &mut k.data {
        v[9 + 2] += 1.0; // view 1 cx
    }
    write_npy(&seq.join("intrinsics.npy"), &k).unwrap();
    let e = read_raw_sequence(&seq).unwrap_err().to_string();
    assert!(
        e.contains("intrinsics.npy") && e.contains("[view 1]") && e.contains("centred"),
        "{e}"
    );
    // Wrong pose count.
    let ext = read_npy(&fixture("extrinsics.npy")).unwrap();
    let short = NpyArray::new(
        vec![3, 4, 4],
        match ext.data {
            NpyData::F64(v) => NpyData::F64(v[..48].to_vec()),
            _ => unreachable!(),
        },
    )
    .unwrap();
    write_npy(&seq.join("extrinsics.npy"), &short).unwrap();
    let e = read_raw_sequence(&seq).unwrap_err().to_string();
    assert!(e.contains("extrinsics.npy") && e.contains("shape"), "{e}");
}

// ---------------------------------------------------------------------------------------------
// Bad inputs, one class per test: every error names the offending file (and the view where the
// file holds several) and the problem.

/// A writable copy of the fixture sequence (4 views of 112x84) in a temporary directory.
fn sequence_copy() -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let seq = dir.path().join("seq");
    std::fs::create_dir_all(seq.join("images")).unwrap();
    std::fs::create_dir_all(seq.join("depths")).unwrap();
    for f in ["extrinsics.npy", "intrinsics.npy"] {
        std::fs::copy(fixture(f), seq.join(f)).unwrap();
    }
    for i in 0..4 {
        std::fs::copy(
            fixture(&format!("images/{i:06}.jpg")),
            seq.join(format!("images/{i:06}.jpg")),
        )
        .unwrap();
        std::fs::copy(
            fixture(&format!("depths/{i:06}.npy")),
            seq.join(format!("depths/{i:06}.npy")),
        )
        .unwrap();
    }
    assert!(
        read_raw_sequence(&seq).is_ok(),
        "the unmodified copy must read"
    );
    (dir, seq)
}

/// The error of reading `seq`, checked to name `file` (full path as displayed).
fn error_naming(seq: &Path, file: &Path) -> String {
    let e = read_raw_sequence(seq)
        .expect_err("bad input must be rejected")
        .to_string();
    assert!(
        e.contains(&file.display().to_string()),
        "error does not name {}: {e}",
        file.display()
    );
    e
}

fn depth_path(seq: &Path, i: usize) -> PathBuf {
    seq.join("depths").join(format!("{i:06}.npy"))
}

/// Rewrites a float `.npy` of the copy with `edit` applied to its values (kept in its dtype).
fn edit_floats(path: &Path, edit: impl FnOnce(&mut Vec<f64>)) {
    let a = read_npy(path).unwrap();
    let mut v = a.to_f64().unwrap();
    edit(&mut v);
    let data = match a.data {
        NpyData::F32(_) => NpyData::F32(v.iter().map(|&x| x as f32).collect()),
        NpyData::F64(_) => NpyData::F64(v),
        d => panic!("fixture {} is {}", path.display(), d.descr()),
    };
    write_npy(path, &NpyArray::new(a.shape, data).unwrap()).unwrap();
}

/// `.npy` bytes with an arbitrary descriptor (for dtypes `write_npy` cannot produce).
fn raw_npy(descr: &str, shape: &[usize], payload: &[u8]) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let mut header = format!(
        "{{'descr': '{descr}', 'fortran_order': False, 'shape': ({}), }}",
        dims.join(", ")
    );
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(payload);
    out
}

#[test]
fn rejects_non_finite_depth() {
    let (_tmp, seq) = sequence_copy();
    let p = depth_path(&seq, 2);
    edit_floats(&p, |v| v[3 * 112 + 5] = f64::NAN);
    let e = error_naming(&seq, &p);
    assert!(e.contains("non-finite depth NaN at row 3, column 5"), "{e}");
    std::fs::copy(fixture("depths/000002.npy"), &p).unwrap();
    let p = depth_path(&seq, 0);
    edit_floats(&p, |v| v[83 * 112 + 111] = f64::NEG_INFINITY);
    let e = error_naming(&seq, &p);
    assert!(
        e.contains("non-finite depth -inf at row 83, column 111"),
        "{e}"
    );
}

#[test]
fn rejects_non_finite_cameras() {
    let (_tmp, seq) = sequence_copy();
    // Extrinsics: view 2, row 1, column 3 (t_y) = +inf.
    let p = seq.join("extrinsics.npy");
    edit_floats(&p, |v| v[2 * 16 + 4 + 3] = f64::INFINITY);
    let e = error_naming(&seq, &p);
    assert!(
        e.contains("[view 2]") && e.contains("non-finite value inf at row 1, column 3"),
        "{e}"
    );
    std::fs::copy(fixture("extrinsics.npy"), &p).unwrap();
    // NaN in the last row is reported as non-finite too (not as a bad homogeneous row).
    edit_floats(&p, |v| v[15] = f64::NAN);
    let e = error_naming(&seq, &p);
    assert!(
        e.contains("[view 0]") && e.contains("non-finite value NaN at row 3, column 3"),
        "{e}"
    );
    std::fs::copy(fixture("extrinsics.npy"), &p).unwrap();
    // Intrinsics: view 3, fx = NaN; view 1, cy = -inf.
    let p = seq.join("intrinsics.npy");
    edit_floats(&p, |v| v[3 * 9] = f64::NAN);
    let e = error_naming(&seq, &p);
    assert!(
        e.contains("[view 3]") && e.contains("non-finite value NaN at row 0, column 0"),
        "{e}"
    );
    std::fs::copy(fixture("intrinsics.npy"), &p).unwrap();
    edit_floats(&p, |v| v[9 + 5] = f64::NEG_INFINITY);
    let e = error_naming(&seq, &p);
    assert!(
        e.contains("[view 1]") && e.contains("non-finite value -inf at row 1, column 2"),
        "{e}"
    );
}

#[test]
fn rejects_wrong_dtypes() {
    let (_tmp, seq) = sequence_copy();
    // Depth saved as int32 (e.g. millimetres).
    let p = depth_path(&seq, 1);
    let d = read_npy(&p).unwrap();
    let mm: Vec<i32> = d
        .to_f32()
        .unwrap()
        .iter()
        .map(|&z| (z * 1000.0) as i32)
        .collect();
    write_npy(
        &p,
        &NpyArray::new(d.shape.clone(), NpyData::I32(mm)).unwrap(),
    )
    .unwrap();
    let e = error_naming(&seq, &p);
    assert!(e.contains("wrong dtype <i4") && e.contains("<f4"), "{e}");
    // Depth saved as float64 is accepted (values rounded to f32 are the fixture's exactly).
    let f64s: Vec<f64> = d.to_f64().unwrap();
    write_npy(
        &p,
        &NpyArray::new(d.shape.clone(), NpyData::F64(f64s)).unwrap(),
    )
    .unwrap();
    let raw = read_raw_sequence(&seq).unwrap();
    assert_eq!(raw.depths[84 * 112..2 * 84 * 112], d.to_f32().unwrap()[..]);
    std::fs::copy(fixture("depths/000001.npy"), &p).unwrap();
    // Extrinsics as float16: the descriptor itself is unsupported.
    let p = seq.join("extrinsics.npy");
    std::fs::write(&p, raw_npy("<f2", &[4, 4, 4], &[0u8; 4 * 16 * 2])).unwrap();
    let e = error_naming(&seq, &p);
    assert!(e.contains("unsupported dtype descriptor '<f2'"), "{e}");
    // Extrinsics as int32: a readable dtype, but not a float one.
    write_npy(
        &p,
        &NpyArray::new(vec![4, 4, 4], NpyData::I32(vec![0; 64])).unwrap(),
    )
    .unwrap();
    let e = error_naming(&seq, &p);
    assert!(e.contains("wrong dtype <i4, expected <f4 or <f8"), "{e}");
    std::fs::copy(fixture("extrinsics.npy"), &p).unwrap();
    // Intrinsics as uint8.
    let p = seq.join("intrinsics.npy");
    write_npy(
        &p,
        &NpyArray::new(vec![4, 3, 3], NpyData::U8(vec![1; 36])).unwrap(),
    )
    .unwrap();
    let e = error_naming(&seq, &p);
    assert!(e.contains("wrong dtype |u1, expected <f4 or <f8"), "{e}");
}

#[test]
fn rejects_depth_of_another_size() {
    let (_tmp, seq) = sequence_copy();
    let p = depth_path(&seq, 3);
    for shape in [vec![84, 111], vec![112, 84], vec![1, 84, 112]] {
        let numel = shape.iter().product();
        write_npy(
            &p,
            &NpyArray::new(shape.clone(), NpyData::F32(vec![1.0; numel])).unwrap(),
        )
        .unwrap();
        let e = error_naming(&seq, &p);
        assert!(
            e.contains(&format!(
                "depth shape {shape:?} differs from the image size [84, 112]"
            )),
            "{e}"
        );
    }
}

#[test]
fn rejects_images_of_different_sizes() {
    let (_tmp, seq) = sequence_copy();
    let p = seq.join("images/000002.jpg");
    let img = image::open(&p)
        .unwrap()
        .resize_exact(56, 42, image::imageops::FilterType::Triangle)
        .to_rgb8();
    img.save(&p).unwrap();
    assert_eq!(
        image::open(&p).unwrap().width(),
        56,
        "the smaller JPEG must have been written"
    );
    let e = error_naming(&seq, &p);
    assert!(
        e.contains("image is 56x42, view 0 is 112x84") && e.contains("one size"),
        "{e}"
    );
}

#[test]
fn rejects_truncated_npy() {
    let (_tmp, seq) = sequence_copy();
    for (file, fixture_name) in [
        (depth_path(&seq, 1), "depths/000001.npy"),
        (seq.join("extrinsics.npy"), "extrinsics.npy"),
        (seq.join("intrinsics.npy"), "intrinsics.npy"),
    ] {
        let full = std::fs::read(fixture(fixture_name)).unwrap();
        // Data cut short by one value's worth of bytes (the header is intact).
        std::fs::write(&file, &full[..full.len() - 4]).unwrap();
        let e = error_naming(&seq, &file);
        assert!(
            e.contains("truncated: data has") && e.contains("needs"),
            "{e}"
        );
        // Cut inside the header dict.
        std::fs::write(&file, &full[..40]).unwrap();
        let e = error_naming(&seq, &file);
        assert!(e.contains("truncated header"), "{e}");
        // Cut inside the magic / version bytes; an empty file.
        for len in [7, 0] {
            std::fs::write(&file, &full[..len]).unwrap();
            let e = error_naming(&seq, &file);
            assert!(e.contains("not a .npy file"), "{e}");
        }
        std::fs::write(&file, &full).unwrap();
    }
    assert!(read_raw_sequence(&seq).is_ok());
}

#[test]
fn rejects_skewed_intrinsics() {
    let (_tmp, seq) = sequence_copy();
    let p = seq.join("intrinsics.npy");
    for (j, value) in [(1, 0.5), (6, 1e-3), (8, 2.0)] {
        edit_floats(&p, |v| v[9 + j] = value); // view 1: skew, K[2,0], K[2,2]
        let e = error_naming(&seq, &p);
        assert!(
            e.contains("[view 1]") && e.contains("not a pinhole K"),
            "{e}"
        );
        std::fs::copy(fixture("intrinsics.npy"), &p).unwrap();
    }
}

#[test]
fn prepare_rejects_inconsistent_raw_sequence() {
    let raw = read_raw_sequence(&fixture_dir()).unwrap();
    let mut short = raw.clone();
    short.depths.pop();
    let e = prepare_ff_resolution(&short, 56).unwrap_err().to_string();
    assert!(
        e.contains("synth_room_s0") && e.contains("depths has 37631 entries, expected 37632"),
        "{e}"
    );
    let mut short = raw.clone();
    short.intrinsics.pop();
    let e = prepare_ff_resolution(&short, 56).unwrap_err().to_string();
    assert!(e.contains("intrinsics has 3 entries, expected 4"), "{e}");
    let mut short = raw;
    short.images.truncate(10);
    let e = prepare_ff_resolution(&short, 56).unwrap_err().to_string();
    assert!(e.contains("images has 10 entries"), "{e}");
}
