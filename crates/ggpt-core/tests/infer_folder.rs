//! formats.md §5.1 scene folder (ff.npz / sfm.npz / matches/ / official .bin mix-ins).
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

mod common;

use common::{fixture, full_scene};
use ggpt_core::io::infer_folder::write_infer_folder;
use ggpt_core::io::matches::{MatchFile, apply_diagonal};
use ggpt_core::io::npy::{NpyData, read_npz, write_npz};
use ggpt_core::io::read_scene;

fn expected(mut s: ggpt_core::Scene) -> ggpt_core::Scene {
    let d = s.dims;
    s.gt = None;
    s.name = "scn".into();
    for m in &mut s.matches {
        let mut f = MatchFile {
            set: m.clone(),
            n: d.n,
            h: d.h,
            w: d.w,
        };
        apply_diagonal(&mut f);
        *m = f.set;
    }
    s
}

#[test]
fn roundtrip_through_npz_folder() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("scn");
    let s = full_scene(3, 2, 5);
    write_infer_folder(&p, &s).unwrap();
    assert_eq!(read_scene(&p).unwrap(), expected(s.clone()));
    // Without images in ff.npz the PNG files of images/ are used (u8 quantised).
    let z = read_npz(&p.join("ff.npz")).unwrap();
    let keep: Vec<(&str, &ggpt_core::io::npy::NpyArray)> = z
        .iter()
        .filter(|(k, _)| *k != "images")
        .map(|(k, a)| (k.as_str(), a))
        .collect();
    write_npz(&p.join("ff.npz"), &keep, true).unwrap();
    let back = read_scene(&p).unwrap();
    let d = back
        .images
        .iter()
        .zip(&s.images)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(d <= 0.5 / 255.0 + 1e-6, "{d}");
}

#[test]
fn requires_matches_or_sfm_and_checks_principal_point() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("scn");
    let mut s = full_scene(2, 3, 4);
    s.sfm = None;
    s.matches.truncate(1);
    write_infer_folder(&p, &s).unwrap();
    std::fs::remove_file(p.join("matches/romav2-base.safetensors")).unwrap();
    let e = read_scene(&p).unwrap_err().to_string();
    assert!(e.contains("[matches]"), "{e}");
    let mut s = full_scene(2, 3, 4);
    s.ff.as_mut().unwrap().cameras.intrinsics[1][(0, 2)] += 0.01;
    write_infer_folder(&p, &s).unwrap();
    let e = read_scene(&p).unwrap_err().to_string();
    assert!(
        e.contains("ff.npz") && e.contains("[K]") && e.contains("view 1"),
        "{e}"
    );
}

#[test]
fn mismatched_dims_across_files() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("scn");
    write_infer_folder(&p, &full_scene(2, 3, 4)).unwrap();
    // The official gt.bin of the fixture is 4 x 42 x 56.
    std::fs::copy(fixture("gt.bin"), p.join("gt.bin")).unwrap();
    let e = read_scene(&p).unwrap_err().to_string();
    assert!(
        e.contains("gt.bin") && e.contains("[points]") && e.contains("N=4 h=42 w=56"),
        "{e}"
    );
    std::fs::remove_file(p.join("gt.bin")).unwrap();
    // sfm.npz of another resolution.
    write_infer_folder(&dir.path().join("other"), &full_scene(2, 4, 3)).unwrap();
    std::fs::copy(dir.path().join("other/sfm.npz"), p.join("sfm.npz")).unwrap();
    let e = read_scene(&p).unwrap_err().to_string();
    assert!(e.contains("sfm.npz") && e.contains("[points]"), "{e}");
    // Matches of another resolution.
    std::fs::copy(
        dir.path().join("other/matches/romav2-base.safetensors"),
        p.join("matches/romav2-base.safetensors"),
    )
    .unwrap();
    std::fs::remove_file(p.join("sfm.npz")).unwrap();
    let e = read_scene(&p).unwrap_err().to_string();
    assert!(
        e.contains("romav2-base.safetensors") && e.contains("[pred_matches]"),
        "{e}"
    );
}

#[test]
fn wrong_dtype_and_nan_in_npz() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("scn");
    write_infer_folder(&p, &full_scene(2, 3, 4)).unwrap();
    // float64 points and confidences are read (rounded to f32), integers are not
    let before = read_scene(&p).unwrap();
    let mut z = read_npz(&p.join("ff.npz")).unwrap();
    for key in ["conf", "points"] {
        if let Some(a) = z.get_mut(key)
            && let NpyData::F32(v) = &a.data
        {
            a.data = NpyData::F64(v.iter().map(|&x| x as f64).collect());
        }
    }
    let arrays: Vec<_> = z.iter().map(|(k, a)| (k.as_str(), a)).collect();
    write_npz(&p.join("ff.npz"), &arrays, false).unwrap();
    assert_eq!(read_scene(&p).unwrap().ff, before.ff);
    let mut z = read_npz(&p.join("ff.npz")).unwrap();
    if let Some(a) = z.get_mut("conf") {
        a.data = NpyData::I32(vec![1; 24]);
    }
    let arrays: Vec<_> = z.iter().map(|(k, a)| (k.as_str(), a)).collect();
    write_npz(&p.join("ff.npz"), &arrays, false).unwrap();
    let e = read_scene(&p).unwrap_err().to_string();
    assert!(
        e.contains("ff.npz") && e.contains("[conf]") && e.contains("dtype"),
        "{e}"
    );
    let mut z = read_npz(&p.join("ff.npz")).unwrap();
    if let Some(a) = z.get_mut("conf") {
        a.data = NpyData::F32(vec![f32::NAN; 24]);
    }
    let arrays: Vec<_> = z.iter().map(|(k, a)| (k.as_str(), a)).collect();
    write_npz(&p.join("ff.npz"), &arrays, false).unwrap();
    let e = read_scene(&p).unwrap_err().to_string();
    assert!(
        e.contains("ff.npz") && e.contains("[conf]") && e.contains("non-finite"),
        "{e}"
    );
    let mut z = read_npz(&p.join("ff.npz")).unwrap();
    z.remove("conf");
    let arrays: Vec<_> = z.iter().map(|(k, a)| (k.as_str(), a)).collect();
    write_npz(&p.join("ff.npz"), &arrays, false).unwrap();
    let e = read_scene(&p).unwrap_err().to_string();
    assert!(
        e.contains("ff.npz") && e.contains("[conf]") && e.contains("missing"),
        "{e}"
    );
}

#[test]
fn official_bins_inside_a_folder() {
    // ff_outputs.bin + sfm_dlt_outputs.bin + an (empty-diagonal) matches dir.
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("scn");
    std::fs::create_dir_all(p.join("matches")).unwrap();
    for f in ["ff_outputs.bin", "sfm_dlt_outputs.bin", "gt.bin"] {
        std::fs::copy(fixture(f), p.join(f)).unwrap();
    }
    let s = read_scene(&p).unwrap();
    assert!(s.ff.is_some() && s.sfm.is_some() && s.gt.is_some() && s.matches.is_empty());
    assert_eq!(s.name, "scn");
}
