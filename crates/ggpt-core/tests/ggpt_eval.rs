//! GGPT_eval raw layout -> ff resolution, against the fixture's `gt.bin` content.

mod common;

use common::{fixture, fixture_dir};
use ggpt_core::io::ggpt_eval::{ff_size, prepare_ff_resolution, read_raw_sequence};
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
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
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
    let e: Vec<f64> = raw.cam_from_world.iter().flat_map(|m| m.transpose().iter().copied().collect::<Vec<_>>()).collect();
    let re = r.f64("raw/extrinsics", &[4, 4, 4]).unwrap();
    let re34: Vec<f64> = re.chunks_exact(16).flat_map(|m| m[..12].to_vec()).collect();
    assert_eq!(e, re34);
    let ru8 = r.u8("raw/images_u8_decoded", &[4, 84, 112, 3]).unwrap();
    let diff = raw.images.iter().zip(&ru8).map(|(a, b)| a.abs_diff(*b)).max().unwrap();
    assert!(diff <= JPEG_DECODER_TOL_U8, "JPEG decode differs from libjpeg by {diff}");
    let mean = raw.images.iter().zip(&ru8).map(|(a, b)| a.abs_diff(*b) as f64).sum::<f64>() / ru8.len() as f64;
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
    eprintln!("resize of our JPEG decode max |diff| = {d:e} ({:.2} u8 levels)", d * 255.0);
    assert!(d <= JPEG_DECODER_TOL_U8 as f32 / 255.0 + 1e-6, "resize of our JPEG decode differs by {d}");
    let gt = s.gt.as_ref().unwrap();
    assert_eq!(gt.mask, r.bool("gt/point_masks", &[n, h, w]).unwrap());
    let k: Vec<f32> = gt.cameras.intrinsics.iter().flat_map(|m| m.transpose().iter().map(|&x| x as f32).collect::<Vec<_>>()).collect();
    let rk = r.f32("gt/intrinsics", &[n, 3, 3]).unwrap();
    for (a, b) in k.iter().zip(&rk) {
        assert!((a - b).abs() <= 1e-6 * b.abs().max(1.0), "K {a} vs {b}");
    }
    let ext: Vec<f32> = gt.cameras.cam_from_world.iter().flat_map(|m| m.transpose().iter().map(|&x| x as f32).collect::<Vec<_>>()).collect();
    let rext: Vec<f32> = r.f32("gt/extrinsics", &[n, 4, 4]).unwrap().chunks_exact(16).flat_map(|m| m[..12].to_vec()).collect();
    assert_eq!(ext, rext);
    // Points: the official unprojection runs in f32 (einsum), ours in f64; points are a few
    // metres from the origin, so f32 rounding of the chain is ~1e-6 m; allow 1e-5 m.
    let rp = r.f32("gt/points", &[n, h, w, 3]).unwrap();
    let d = max_abs(&gt.points, &rp);
    eprintln!("GT points max |diff| = {d:e} m");
    assert!(d <= 1e-5, "GT points differ by {d} m");
    assert!(rp.iter().any(|&x| x != 0.0));
    // Zeros exactly where the reference has zeros.
    for (p, (a, b)) in gt.points.chunks_exact(3).zip(rp.chunks_exact(3)).enumerate() {
        assert_eq!(a == [0.0; 3], b == [0.0; 3], "pixel {p}");
    }
}

#[test]
fn rejects_bad_layouts() {
    let dir = tempfile::tempdir().unwrap();
    let seq = dir.path().join("seq");
    std::fs::create_dir_all(seq.join("images")).unwrap();
    std::fs::create_dir_all(seq.join("depths")).unwrap();
    for f in ["extrinsics.npy", "intrinsics.npy"] {
        std::fs::copy(fixture(f), seq.join(f)).unwrap();
    }
    for i in 0..4 {
        std::fs::copy(fixture(&format!("images/{i:06}.jpg")), seq.join(format!("images/{i:06}.jpg"))).unwrap();
        std::fs::copy(fixture(&format!("depths/{i:06}.npy")), seq.join(format!("depths/{i:06}.npy"))).unwrap();
    }
    assert!(read_raw_sequence(&seq).is_ok());
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
    let mut k = ggpt_core::io::npy::read_npy(&seq.join("intrinsics.npy")).unwrap();
    if let ggpt_core::io::npy::NpyData::F64(v) = &mut k.data {
        v[9 + 2] += 1.0; // view 1 cx
    }
    ggpt_core::io::npy::write_npy(&seq.join("intrinsics.npy"), &k).unwrap();
    let e = read_raw_sequence(&seq).unwrap_err().to_string();
    assert!(e.contains("intrinsics.npy") && e.contains("[view 1]") && e.contains("centred"), "{e}");
    // Wrong pose count.
    let ext = ggpt_core::io::npy::read_npy(&fixture("extrinsics.npy")).unwrap();
    let short = ggpt_core::io::npy::NpyArray::new(vec![3, 4, 4], match ext.data {
        ggpt_core::io::npy::NpyData::F64(v) => ggpt_core::io::npy::NpyData::F64(v[..48].to_vec()),
        _ => unreachable!(),
    })
    .unwrap();
    ggpt_core::io::npy::write_npy(&seq.join("extrinsics.npy"), &short).unwrap();
    let e = read_raw_sequence(&seq).unwrap_err().to_string();
    assert!(e.contains("extrinsics.npy") && e.contains("shape"), "{e}");
}
