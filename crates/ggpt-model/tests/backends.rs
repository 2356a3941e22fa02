//! Backend parity (ndarray = reference, flex, wgpu) on the tiny and small configurations:
//! forward <= 1e-4, gradients <= 1e-3, finite gradients for every parameter, and a few Adam
//! steps that reduce a simple loss. All wgpu work lives in this one test binary and is kept
//! small (the first kernel compilation on lavapipe is slow).
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

mod common;

use burn::module::{Module, ModuleVisitor, Param};
use burn::nn::LinearConfig;
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::{Device, Tensor};
use common::*;
use ggpt_model::infer::prepare_chunks;
use ggpt_model::plan::ChunkInput;
use ggpt_model::weights::{load_checkpoint, save_burnpack};
use ggpt_model::{Ggpt, GgptConfig, PreparedBatch};

#[allow(deprecated)]
fn ndarray() -> Device {
    Device::ndarray()
}

/// Deterministic surface-like chunk of `k` pixels, ~30 % guidance, a few duplicate voxels.
fn synthetic_chunk(k: usize, seed: u64) -> ChunkInput {
    let mut s = seed.wrapping_mul(0x9E3779B97F4A7C15).wrapping_add(1);
    let mut next = || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 11) as f32 / (1u64 << 53) as f32
    };
    let mut c = ChunkInput::default();
    let side = (k as f32).sqrt().ceil() as usize;
    for i in 0..k {
        let (u, v) = (
            (i % side) as f32 / side as f32,
            (i / side) as f32 / side as f32,
        );
        let p = [
            u * 1.6 - 0.8,
            v * 1.6 - 0.8,
            0.3 * (3.0 * u).sin() * (2.0 * v).cos() + 0.01 * next(),
        ];
        c.ff_pts.push(p);
        c.ff_conf.push(1.0 + 3.0 * next());
        let g = next() < 0.3;
        c.geo_msk.push(g);
        c.geo_pts.push(if g {
            [p[0] + 0.004 * next(), p[1], p[2] - 0.004 * next()]
        } else {
            [5.0 * next(); 3]
        });
    }
    c
}

/// Tiny model with random weights (last head layer randomised so gradients flow), copied to
/// every device through a burnpack file so all backends hold identical parameters.
fn models_on(cfg: &GgptConfig, devices: &[Device], fixture_weights: bool) -> Vec<Ggpt> {
    let reference = ndarray();
    let mut model = if fixture_weights {
        small_model(&reference)
    } else {
        Ggpt::new(cfg, &reference)
    };
    if !fixture_weights {
        model.head.fc3 = LinearConfig::new(cfg.head_width, 4).init(&reference);
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("m.bpk");
    save_burnpack(&model, &path).expect("save");
    devices
        .iter()
        .map(|d| load_checkpoint(Ggpt::new(cfg, d), &path).expect("load on device"))
        .collect()
}

fn forward_values(model: &Ggpt, batch: &PreparedBatch) -> Vec<f32> {
    let out = model.forward(batch);
    let mut v = values(&out.tokens_xyz);
    v.extend(values(&out.tokens_conf));
    v.extend(values(&out.pre_activation));
    v
}

/// Collects `(path, gradient values)` of every trainable float parameter from a
/// [`GradientsParams`] (plain autodiff through `GradientsParams::from_grads`, or the segment
/// recomputation).
struct GradCollector<'a> {
    grads: &'a GradientsParams,
    path: Vec<String>,
    out: Vec<(String, Option<Vec<f32>>)>,
}

impl ModuleVisitor for GradCollector<'_> {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.path.push(name.to_string());
    }
    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.path.pop();
    }
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        // BatchNorm running statistics are buffers, not trainable: no gradient expected.
        if matches!(
            self.path.last().map(String::as_str),
            Some("running_mean" | "running_var")
        ) {
            return;
        }
        let g = self.grads.get::<D>(param.id).map(|g| values(&g));
        self.out.push((self.path.join("."), g));
    }
}

/// `(path, gradient)` of every trainable parameter of `model`.
fn collect_gradients(model: &Ggpt, grads: &GradientsParams) -> Vec<(String, Option<Vec<f32>>)> {
    let mut c = GradCollector {
        grads,
        path: Vec::new(),
        out: Vec::new(),
    };
    model.visit(&mut c);
    c.out
}

/// Training-mode loss: squared distance of the outputs to a shifted target plus a confidence term.
fn loss_of(model: &Ggpt, batch: &PreparedBatch) -> Tensor<1> {
    loss_of_output(model.forward(batch), batch)
}

/// [`loss_of`] of outputs already computed.
fn loss_of_output(out: ggpt_model::GgptOutput, batch: &PreparedBatch) -> Tensor<1> {
    let target = batch.coord.clone().add_scalar(0.05);
    let d = out.tokens_xyz - target;
    (d.clone() * d)
        .mean()
        .add(out.tokens_conf.log().mean().mul_scalar(0.1))
}

fn gradients(
    model: &Ggpt,
    chunks: &[ChunkInput],
    cfg: &GgptConfig,
    device: &Device,
) -> Vec<(String, Option<Vec<f32>>)> {
    let batch = prepare_chunks(cfg, chunks, device).expect("plan");
    let loss = loss_of(model, &batch);
    collect_gradients(model, &GradientsParams::from_grads(loss.backward(), model))
}

/// `(path, gradient)` of every trainable parameter from the segment recomputation
/// (`ggpt_model::recompute`: on a GPU device the attention parts take the grouped backward).
#[cfg(feature = "wgpu")]
fn recomputed_gradient_values(
    model: &Ggpt,
    chunks: &[ChunkInput],
    cfg: &GgptConfig,
    device: &Device,
) -> Vec<(String, Option<Vec<f32>>)> {
    let batch = prepare_chunks(cfg, chunks, device).expect("plan");
    let (grads, ()) = ggpt_model::recompute::recomputed_gradients(model, &batch, |out| {
        Ok::<_, String>((loss_of_output(out, &batch), ()))
    })
    .unwrap();
    collect_gradients(model, &grads)
}

fn tiny_cfg() -> GgptConfig {
    let mut cfg = GgptConfig::tiny();
    cfg.drop_path = 0.0; // deterministic training forward for cross-backend comparison
    cfg
}

fn compare_forward(
    cfg: &GgptConfig,
    chunks: &[ChunkInput],
    devices: &[Device],
    names: &[&str],
    fixture: bool,
) -> Vec<String> {
    let models = models_on(cfg, devices, fixture);
    let mut results = Vec::new();
    for (m, d) in models.iter().zip(devices) {
        let batch = prepare_chunks(cfg, chunks, d).expect("plan");
        results.push(forward_values(m, &batch));
    }
    let mut failures = Vec::new();
    for i in 1..results.len() {
        let (diff, at) = max_abs_diff(&results[0], &results[i]);
        eprintln!(
            "forward {} vs ndarray: max |Δ| = {diff:.2e} at {at}",
            names[i]
        );
        if diff > 1e-4 {
            failures.push(format!(
                "forward {} vs ndarray: max |Δ| = {diff:e} at {at}",
                names[i]
            ));
        }
    }
    failures
}

fn compare_gradients(
    cfg: &GgptConfig,
    chunks: &[ChunkInput],
    devices: &[Device],
    names: &[&str],
) -> Vec<String> {
    let ad: Vec<Device> = devices.iter().map(|d| d.clone().autodiff()).collect();
    let models = models_on(cfg, &ad, false);
    let grads: Vec<_> = models
        .iter()
        .zip(&ad)
        .map(|(m, d)| gradients(m, chunks, cfg, d))
        .collect();
    let mut failures = Vec::new();
    for (path, g) in &grads[0] {
        match g {
            None => failures.push(format!("{path}: no gradient on ndarray")),
            Some(g) if g.iter().any(|x| !x.is_finite()) => {
                failures.push(format!("{path}: non-finite gradient"))
            }
            _ => {}
        }
    }
    for i in 1..grads.len() {
        let mut worst = 0.0f32;
        for ((path, a), (_, b)) in grads[0].iter().zip(&grads[i]) {
            if let (Some(a), Some(b)) = (a, b) {
                let (d, at) = max_abs_diff(a, b);
                worst = worst.max(d);
                if d > 1e-3 {
                    failures.push(format!(
                        "grad {path} {} vs ndarray: max |Δ| = {d:e} at {at}",
                        names[i]
                    ));
                }
            } else {
                failures.push(format!("grad {path}: missing on {}", names[i]));
            }
        }
        eprintln!("gradients {} vs ndarray: max |Δ| = {worst:.2e}", names[i]);
    }
    failures
}

fn cpu_devices() -> (Vec<Device>, Vec<&'static str>) {
    (vec![ndarray(), Device::flex()], vec!["ndarray", "flex"])
}

#[test]
fn cpu_backends_agree_forward_and_gradients() {
    let (devices, names) = cpu_devices();
    let chunks = [synthetic_chunk(400, 1), synthetic_chunk(150, 2)];
    let mut failures = compare_forward(&tiny_cfg(), &chunks, &devices, &names, false);
    failures.extend(compare_gradients(&tiny_cfg(), &chunks, &devices, &names));
    // small config with the fixture weights on fixture chunk 1
    let fixture = fixture_chunks();
    failures.extend(compare_forward(
        &GgptConfig::small(),
        &fixture[1..],
        &devices,
        &names,
        true,
    ));
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn adam_steps_reduce_the_loss() {
    let device = ndarray().autodiff();
    let cfg = tiny_cfg();
    let mut model = models_on(&cfg, std::slice::from_ref(&device), false).remove(0);
    let batch = prepare_chunks(&cfg, &[synthetic_chunk(300, 5)], &device).expect("plan");
    let mut optim = AdamConfig::new().with_epsilon(1e-8).init();
    let mut losses = Vec::new();
    for _ in 0..4 {
        let loss = loss_of(&model, &batch);
        losses.push(values(&loss)[0]);
        let grads = GradientsParams::from_grads(loss.backward(), &model);
        model = optim.step(1e-3, model, grads);
    }
    let last = values(&loss_of(&model, &batch))[0];
    assert!(losses.iter().all(|l| l.is_finite()));
    assert!(
        last < losses[0],
        "loss did not decrease: {losses:?} -> {last}"
    );
}

#[cfg(feature = "wgpu")]
#[test]
fn wgpu_agrees_with_ndarray() {
    use burn::tensor::DeviceKind;
    let devices = vec![ndarray(), Device::wgpu(DeviceKind::DefaultDevice)];
    let names = ["ndarray", "wgpu"];
    let chunks = [synthetic_chunk(200, 3)];
    let mut failures = compare_forward(&tiny_cfg(), &chunks, &devices, &names, false);
    failures.extend(compare_gradients(&tiny_cfg(), &chunks, &devices, &names));
    // the training path of GPU devices: segment recomputation with the grouped attention
    // backward on wgpu, against plain autodiff on ndarray (both in training mode)
    let cfg = tiny_cfg();
    let ad: Vec<Device> = devices.iter().map(|d| d.clone().autodiff()).collect();
    let models: Vec<Ggpt> = models_on(&cfg, &ad, false)
        .into_iter()
        .map(Ggpt::train)
        .collect();
    let want = gradients(&models[0], &chunks, &cfg, &ad[0]);
    let got = recomputed_gradient_values(&models[1], &chunks, &cfg, &ad[1]);
    let mut worst = 0.0f32;
    for ((path, a), (_, b)) in want.iter().zip(&got) {
        match (a, b) {
            (Some(a), Some(b)) => {
                let (d, at) = max_abs_diff(a, b);
                worst = worst.max(d);
                if d > 1e-3 {
                    failures.push(format!(
                        "recomputed grad {path} wgpu: max |Δ| = {d:e} at {at}"
                    ));
                }
            }
            (Some(_), None) => failures.push(format!("recomputed grad {path}: missing on wgpu")),
            _ => {}
        }
    }
    eprintln!("recomputed gradients wgpu vs plain autodiff ndarray: max |Δ| = {worst:.2e}");
    let fixture = fixture_chunks();
    failures.extend(compare_forward(
        &GgptConfig::small(),
        &fixture[1..],
        &devices,
        &names,
        true,
    ));
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
