//! Parity with the official PyTorch fixtures (`shared/fixtures/ggpt_small`) on ndarray:
//! every recorded intermediate and every output to 1e-4, each chunk alone and both batched.
//! `GGPT_TEST_DEVICE=wgpu` (or `flex`, `cuda`) runs the same checks on that device
//! (scripts/gpu_bench.sh does, on a GPU).
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

mod common;

use burn::tensor::Device;
use common::*;
use ggpt_model::infer::prepare_chunks;
use ggpt_model::{GgptConfig, Recorder};
use safetensors::{Dtype, SafeTensors};

/// Fixture tolerance for every f32 feature and output (fixtures/README.md).
const TOL: f32 = 1e-4;
/// Tolerance of `input.feat` / `input.coord` (ULP differences of sin/cos/pow).
const TOL_INPUT: f32 = 1e-5;

/// ndarray, or the device named by `GGPT_TEST_DEVICE` (`ggpt_model::device::device_from_name`).
#[allow(deprecated)]
fn device() -> Device {
    match std::env::var("GGPT_TEST_DEVICE") {
        Ok(name) => ggpt_model::device::device_from_name(&name)
            .unwrap_or_else(|e| panic!("GGPT_TEST_DEVICE={name}: {e}")),
        Err(_) => Device::ndarray(),
    }
}

/// Output names of the fixture `outputs.safetensors`, with the values from a `ChunkOutput`.
fn output_values(o: &ggpt_model::ChunkOutput) -> Vec<(&'static str, Vec<f32>)> {
    let flat = |v: &[[f32; 3]]| {
        v.iter()
            .flat_map(|p| p.iter().copied())
            .collect::<Vec<f32>>()
    };
    vec![
        ("ff_pts_out", flat(&o.ff_pts_out)),
        ("ff_pts_conf_out", o.ff_pts_conf_out.clone()),
        ("geo_pts_out", flat(&o.geo_pts_out)),
        ("geo_pts_conf_out", o.geo_pts_conf_out.clone()),
        ("tokens_xyz_out", flat(&o.tokens_xyz_out)),
        ("tokens_conf_out", o.tokens_conf_out.clone()),
    ]
}

#[test]
fn every_intermediate_and_output_matches_each_chunk_alone() {
    let device = device();
    let cfg = GgptConfig::small();
    let model = small_model(&device);
    let inter_bytes = read_fixture("intermediates.safetensors");
    let inter = SafeTensors::deserialize(&inter_bytes).expect("valid intermediates");
    let out_bytes = read_fixture("outputs.safetensors");
    let outs = SafeTensors::deserialize(&out_bytes).expect("valid outputs");
    let chunks = fixture_chunks();
    assert_eq!(chunks.len(), 2);
    let mut failures = Vec::new();
    let mut report = Vec::new();
    for (c, chunk) in chunks.iter().enumerate() {
        let batch = prepare_chunks(&cfg, std::slice::from_ref(chunk), &device).expect("plan");
        let mut rec = Recorder::enabled();
        let output = model.forward_recorded(&batch, &mut rec);
        let prefix = format!("chunk{c}/");
        let mut compared = 0;
        for (name, view) in inter.tensors() {
            let Some(short) = name.strip_prefix(&prefix) else {
                continue;
            };
            if view.dtype() != Dtype::F32 {
                continue;
            }
            let (shape, reference) = fixture_f32(&inter, &name);
            let Some(ours) = rec.tensors.get(short) else {
                failures.push(format!("{name}: not produced by the port"));
                continue;
            };
            let tol = if short.starts_with("input.") {
                TOL_INPUT
            } else {
                TOL
            };
            let ours = values(ours);
            let (d, _) = max_abs_diff(&ours, &reference);
            report.push(format!("{name}: {d:.2e}"));
            if let Some(f) = compare(&name, &ours, &reference, &shape, tol) {
                failures.push(f);
            }
            compared += 1;
        }
        assert!(
            compared >= 58,
            "chunk{c}: only {compared} intermediates compared"
        );
        let per_chunk = output.to_chunks(&batch).expect("outputs");
        for (name, ours) in output_values(&per_chunk[0]) {
            let full = format!("{prefix}{name}");
            let (shape, reference) = fixture_f32(&outs, &full);
            report.push(format!("{full}: {:.2e}", max_abs_diff(&ours, &reference).0));
            if let Some(f) = compare(&full, &ours, &reference, &shape, TOL) {
                failures.push(f);
            }
        }
    }
    eprintln!("{}", report.join("\n"));
    assert!(
        failures.is_empty(),
        "{} mismatches:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

#[test]
fn batched_forward_matches_single_chunk_forwards() {
    let device = device();
    let cfg = GgptConfig::small();
    let model = small_model(&device);
    let chunks = fixture_chunks();
    let out_bytes = read_fixture("outputs.safetensors");
    let outs = SafeTensors::deserialize(&out_bytes).expect("valid outputs");
    let batch = prepare_chunks(&cfg, &chunks, &device).expect("plan");
    let batched = model.forward(&batch).to_chunks(&batch).expect("outputs");
    assert_eq!(batched.len(), 2);
    let mut failures = Vec::new();
    for (c, chunk) in chunks.iter().enumerate() {
        let single_batch =
            prepare_chunks(&cfg, std::slice::from_ref(chunk), &device).expect("plan");
        let single = model
            .forward(&single_batch)
            .to_chunks(&single_batch)
            .expect("outputs");
        for ((name, b), (_, s)) in output_values(&batched[c])
            .into_iter()
            .zip(output_values(&single[0]))
        {
            let full = format!("chunk{c}/{name}");
            let (shape, reference) = fixture_f32(&outs, &full);
            if let Some(f) = compare(
                &format!("{full} (batched vs fixture)"),
                &b,
                &reference,
                &shape,
                TOL,
            ) {
                failures.push(f);
            }
            if let Some(f) = compare(&format!("{full} (batched vs single)"), &b, &s, &shape, 1e-5) {
                failures.push(f);
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
