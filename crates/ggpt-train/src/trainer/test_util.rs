//! Helpers shared by the tests of the trainer modules: the CPU device, the lock of the backend
//! RNG, a toy chunk set, small run options and models.

use std::path::Path;

use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::{Device, Tensor};
use ggpt_model::{Ggpt, GgptConfig};

use super::{LrSchedule, Recompute, TrainOptions};
use crate::chunkset::tests::toy_chunk;
use crate::chunkset::{ChunkSet, ChunkSetWriter, SceneEntry, Split, TrainChunk};

#[allow(deprecated)]
pub(super) fn cpu() -> Device {
    Device::ndarray()
}

/// The backend RNG (initialisation, drop path) is one per backend and process: tests that
/// seed it and depend on its sequence must not interleave.
pub(super) static BACKEND_RNG: std::sync::Mutex<()> = std::sync::Mutex::new(());

pub(super) fn rng_lock() -> std::sync::MutexGuard<'static, ()> {
    BACKEND_RNG.lock().unwrap_or_else(|e| e.into_inner())
}

pub(super) fn toy_set(dir: &Path) -> ChunkSet {
    let mut w = ChunkSetWriter::new(dir, 4, serde_json::json!({"test": true})).unwrap();
    for s in 0..3 {
        let idx = w.add_scene(SceneEntry {
            name: format!("train{s}"),
            split: Split::Train,
            views: 2,
            height: 14,
            width: 14,
            metres_per_unit: 1.0,
            source: "test".into(),
        });
        for k in 0..3 {
            w.add_chunk(toy_chunk(idx, 60 + 7 * k, (s * 3 + k) as u32))
                .unwrap();
        }
    }
    let v = w.add_scene(SceneEntry {
        name: "val".into(),
        split: Split::Val,
        views: 2,
        height: 14,
        width: 14,
        metres_per_unit: 1.0,
        source: "test".into(),
    });
    w.add_chunk(toy_chunk(v, 50, 99)).unwrap();
    w.finish().unwrap();
    ChunkSet::open(dir).unwrap()
}

pub(super) fn options(steps: u64) -> TrainOptions {
    TrainOptions {
        model: GgptConfig::tiny(),
        steps,
        batch_size: 2,
        lr: 1e-3,
        lr_schedule: LrSchedule::Cosine,
        warmup_steps: 2,
        clip_grad_norm: Some(1.0),
        seed: 7,
        save_every: 2,
        val_every: 0,
        val_chunks: 4,
        val_max_tokens: 100_000,
        keep_checkpoints: 10,
        grad_accum: 1,
        devices: Vec::new(),
        recompute: Recompute::default(),
    }
}

pub(super) fn fresh(o: &TrainOptions, device: &Device) -> Ggpt {
    let plain = device.clone().without_autodiff();
    plain.seed(o.seed);
    Ggpt::new(&o.model, &plain).fork(device).train()
}

/// Every float parameter and buffer of the model, flattened in visiting order.
pub(super) fn weights(model: &Ggpt) -> Vec<f32> {
    struct Collect(Vec<f32>);
    impl ModuleVisitor for Collect {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            self.0.extend(
                param
                    .val()
                    .into_data()
                    .convert::<f32>()
                    .try_to_vec::<f32>()
                    .unwrap(),
            );
        }
    }
    let mut c = Collect(Vec::new());
    model.valid().visit(&mut c);
    c.0
}

pub(super) fn rel_to_max(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    let max = a.iter().fold(0.0f32, |m, x| m.max(x.abs())).max(1e-30);
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max)
        / max
}

pub(super) fn toy_batch(n: usize) -> Vec<TrainChunk> {
    (0..n)
        .map(|i| toy_chunk(i % 3, 40 + 7 * i, i as u32 + 1))
        .collect()
}
