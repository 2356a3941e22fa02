//! `ggpt-infer chunk` reproduces the official fixture outputs (shared/fixtures/ggpt_small).

use std::path::PathBuf;
use std::process::Command;

use safetensors::{Dtype, SafeTensors};

fn small_dir() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../../../shared/fixtures/ggpt_small"))
}

fn f32s(st: &SafeTensors<'_>, name: &str) -> Vec<f32> {
    let v = st.tensor(name).unwrap_or_else(|e| panic!("{name}: {e}"));
    assert_eq!(v.dtype(), Dtype::F32, "{name}");
    v.data().chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
}

#[test]
fn chunk_subcommand_reproduces_fixture_outputs() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("out.safetensors");
    let status = Command::new(env!("CARGO_BIN_EXE_ggpt-infer"))
        .args(["chunk", "--model-config"])
        .arg(small_dir().join("manifest.json"))
        .arg("--weights")
        .arg(small_dir().join("weights.pth"))
        .arg("--input")
        .arg(small_dir().join("inputs.safetensors"))
        .arg("--output")
        .arg(&out)
        .args(["--device", "ndarray", "--threads", "1"])
        .status()
        .expect("runs");
    assert!(status.success(), "ggpt-infer chunk failed: {status}");
    let ours_bytes = std::fs::read(&out).expect("output written");
    let ours = SafeTensors::deserialize(&ours_bytes).expect("valid output");
    let ref_path = small_dir().join("outputs.safetensors");
    let ref_bytes = std::fs::read(&ref_path).unwrap_or_else(|e| panic!("{}: {e}", ref_path.display()));
    let reference = SafeTensors::deserialize(&ref_bytes).expect("valid reference");
    let mut names = reference.names();
    names.sort();
    assert_eq!(names.len(), 12);
    for name in names {
        let (a, b) = (f32s(&ours, name), f32s(&reference, name));
        assert_eq!(a.len(), b.len(), "{name}");
        let worst = a.iter().zip(&b).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
        assert!(worst <= 1e-4 && a.iter().all(|x| x.is_finite()), "{name}: max |Δ| = {worst:e}");
    }
}
