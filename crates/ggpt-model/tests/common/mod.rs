//! Shared helpers of the integration tests: fixture paths, tensor reading, comparisons.
#![allow(dead_code)]

use std::path::PathBuf;

use burn::tensor::{Device, Tensor};
use ggpt_model::chunk_io::read_f32;
use ggpt_model::plan::ChunkInput;
use ggpt_model::readback::read_f32 as data_f32;
use ggpt_model::{Ggpt, GgptConfig};
use safetensors::SafeTensors;

/// `$GGPT_FIXTURES/ggpt_small`, by default `<workspace>/../shared/fixtures/ggpt_small`
/// (`GGPT_FIXTURES` lets a prebuilt test binary run on another machine: scripts/gpu_bench.sh).
pub fn small_dir() -> PathBuf {
    match std::env::var_os("GGPT_FIXTURES") {
        Some(root) => PathBuf::from(root).join("ggpt_small"),
        None => PathBuf::from(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../../shared/fixtures/ggpt_small"
        )),
    }
}

/// Reads a fixture file (panics with the path when missing: tests must fail, not skip).
pub fn read_fixture(name: &str) -> Vec<u8> {
    let path = small_dir().join(name);
    std::fs::read(&path).unwrap_or_else(|e| panic!("cannot read fixture {}: {e}", path.display()))
}

/// The two fixture chunks.
pub fn fixture_chunks() -> Vec<ChunkInput> {
    let path = small_dir().join("inputs.safetensors");
    ggpt_model::chunk_io::read_chunk_inputs(&path).unwrap_or_else(|e| panic!("{e}"))
}

/// The small model with the fixture weights (safetensors) on `device`.
pub fn small_model(device: &Device) -> Ggpt {
    let model = Ggpt::new(&GgptConfig::small(), device);
    ggpt_model::weights::load_checkpoint(model, &small_dir().join("weights.safetensors"))
        .unwrap_or_else(|e| panic!("{e}"))
}

/// Tensor values as f32.
pub fn values<const D: usize>(t: &Tensor<D>) -> Vec<f32> {
    data_f32(&t.to_data(), "tensor").unwrap_or_else(|e| panic!("{e}"))
}

/// Max |a - b| with its flat index; NaN/inf anywhere counts as infinite.
pub fn max_abs_diff(a: &[f32], b: &[f32]) -> (f32, usize) {
    let mut worst = (0.0f32, 0usize);
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        let d = if x.is_finite() && y.is_finite() {
            (x - y).abs()
        } else {
            f32::INFINITY
        };
        if d > worst.0 {
            worst = (d, i);
        }
    }
    worst
}

/// Compares `ours` with `reference` (shape `shape`); returns a failure line or None.
pub fn compare(
    name: &str,
    ours: &[f32],
    reference: &[f32],
    shape: &[usize],
    tol: f32,
) -> Option<String> {
    if ours.len() != reference.len() {
        return Some(format!(
            "{name}: {} values, reference {} (shape {shape:?})",
            ours.len(),
            reference.len()
        ));
    }
    let (d, i) = max_abs_diff(ours, reference);
    let cols = shape
        .get(1..)
        .map(|s| s.iter().product::<usize>())
        .unwrap_or(1)
        .max(1);
    let at = if shape.len() > 1 {
        format!("[{}, {}]", i / cols, i % cols)
    } else {
        format!("[{i}]")
    };
    let line = format!(
        "{name}: max |Δ| = {d:.3e} at {at} (ours {}, ref {})",
        ours.get(i).copied().unwrap_or(f32::NAN),
        reference.get(i).copied().unwrap_or(f32::NAN)
    );
    if d <= tol { None } else { Some(line) }
}

/// Reads `name` from a fixture safetensors.
pub fn fixture_f32(st: &SafeTensors<'_>, name: &str) -> (Vec<usize>, Vec<f32>) {
    read_f32(st, name, &small_dir()).unwrap_or_else(|e| panic!("{e}"))
}
