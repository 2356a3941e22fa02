//! Targets of `ggpt-train`'s readers: chunk-set folders (manifest + shards, with their size and
//! CRC checks), shard bytes behind those checks (`parse_shard`), and training checkpoints
//! (`model.bpk`, `optim.bpk`, `state.json`).

use std::path::Path;

use burn::module::Module;
use ggpt_model::{Ggpt, GgptConfig};
use ggpt_train::chunkset::{
    ChunkSet, ChunkSetWriter, SceneEntry, Split, TrainChunk, parse_shard, shard_bytes,
};
use ggpt_train::trainer::{
    LrSchedule, TrainOptions, TrainState, adam, load_checkpoint, save_checkpoint, train_step,
};

use super::model_formats::model_fingerprint;
use super::{err_text, seed_from_writer};
use crate::Result;
use crate::harness::{SeedFile, Target, fingerprint_debug};

fn chunk(scene: usize, k: usize, salt: u32) -> TrainChunk {
    TrainChunk::deterministic(scene, k, salt)
}

fn scene(name: &str, split: Split) -> SceneEntry {
    SceneEntry {
        name: name.into(),
        split,
        views: 2,
        height: 12,
        width: 16,
        metres_per_unit: 2.0,
        source: "ggpt-fuzz".into(),
    }
}

/// A chunk-set folder: manifest and three shards (`ChunkSet::open` + `load_split`).
pub struct ChunkSetDir;

impl Target for ChunkSetDir {
    fn name(&self) -> &'static str {
        "chunkset"
    }
    fn describe(&self) -> &'static str {
        "chunk-set folder (manifest, shards)"
    }
    fn seed(&self) -> Result<Vec<SeedFile>> {
        seed_from_writer(self.name(), |dir| {
            let e = |e: ggpt_train::TrainError| e.to_string();
            let mut w = ChunkSetWriter::new(dir, 2, serde_json::json!({"made_by": "ggpt-fuzz"}))
                .map_err(e)?;
            let a = w.add_scene(scene("a", Split::Train));
            let v = w.add_scene(scene("v", Split::Val));
            for k in 0..3 {
                w.add_chunk(chunk(a, 9 + k, k as u32)).map_err(e)?;
            }
            w.add_chunk(chunk(v, 6, 7)).map_err(e)?;
            w.finish().map(|_| ()).map_err(e)
        })
    }
    fn read(&self, dir: &Path) -> std::result::Result<u64, String> {
        let set = ChunkSet::open(dir).map_err(|e| err_text(&e))?;
        let train = set.load_split(Split::Train).map_err(|e| err_text(&e))?;
        let val = set.load_split(Split::Val).map_err(|e| err_text(&e))?;
        Ok(fingerprint_debug(&(set.manifest, train, val)))
    }
}

/// Shard bytes parsed directly (`parse_shard`), i.e. behind the manifest's size and CRC checks,
/// which would reject almost every mutation before the parser sees it.
pub struct Shard;

impl Target for Shard {
    fn name(&self) -> &'static str {
        "chunkset-shard"
    }
    fn describe(&self) -> &'static str {
        "chunk-set shard safetensors, parsed without its CRC check"
    }
    fn seed(&self) -> Result<Vec<SeedFile>> {
        let bytes =
            shard_bytes(&[chunk(0, 9, 1), chunk(1, 5, 2)]).map_err(|e| crate::FuzzError::Seed {
                target: self.name().into(),
                message: e.to_string(),
            })?;
        Ok(vec![SeedFile::new("shard.safetensors", bytes)])
    }
    fn read(&self, dir: &Path) -> std::result::Result<u64, String> {
        let path = dir.join("shard.safetensors");
        let bytes = std::fs::read(&path).map_err(|e| format!("{}: {e}", path.display()))?;
        parse_shard(&bytes, &path, 2)
            .map(|c| fingerprint_debug(&c))
            .map_err(|e| err_text(&e))
    }
}

/// A training checkpoint of the tiny network after one Adam step (`load_checkpoint`).
pub struct Checkpoint;

impl Checkpoint {
    /// The target.
    pub fn new() -> Self {
        Self
    }
}

impl Default for Checkpoint {
    fn default() -> Self {
        Self::new()
    }
}

fn options() -> TrainOptions {
    TrainOptions {
        model: GgptConfig::tiny(),
        steps: 4,
        batch_size: 1,
        lr: 1e-3,
        lr_schedule: LrSchedule::Constant,
        warmup_steps: 0,
        clip_grad_norm: Some(1.0),
        seed: 42,
        save_every: 1,
        val_every: 0,
        val_chunks: 1,
        val_max_tokens: 10_000,
        keep_checkpoints: 1,
        grad_accum: 1,
        devices: Vec::new(),
        recompute: ggpt_train::trainer::Recompute::default(),
    }
}

fn autodiff_cpu() -> std::result::Result<burn::tensor::Device, String> {
    Ok(ggpt_model::device::device_from_name("ndarray")
        .map_err(|e| e.to_string())?
        .autodiff())
}

impl Target for Checkpoint {
    fn name(&self) -> &'static str {
        "train-checkpoint"
    }
    fn describe(&self) -> &'static str {
        "training checkpoint (`model.bpk`, `optim.bpk`, `state.json`)"
    }
    fn seed(&self) -> Result<Vec<SeedFile>> {
        let tmp = tempfile::tempdir().map_err(|e| crate::FuzzError::Io {
            path: std::env::temp_dir(),
            source: e,
        })?;
        let dir = (|| -> std::result::Result<std::path::PathBuf, String> {
            let o = options();
            let device = autodiff_cpu()?;
            let plain = device.clone().without_autodiff();
            plain.seed(o.seed);
            let model = Ggpt::new(&o.model, &plain).fork(&device).train();
            let mut optim = adam();
            let c = chunk(0, 40, 3);
            let (model, _) = train_step(
                model,
                &mut optim,
                &o.model,
                &[&c],
                o.lr,
                o.clip_grad_norm,
                &device,
            )
            .map_err(|e| e.to_string())?;
            let state = TrainState {
                step: 1,
                options: o,
                rng: "per-step seeds".into(),
                data: "chunks".into(),
                last_validation: None,
            };
            save_checkpoint(tmp.path(), &model, &optim, &state).map_err(|e| e.to_string())
        })()
        .map_err(|message| crate::FuzzError::Seed {
            target: self.name().into(),
            message,
        })?;
        super::seed_files_of(&dir)
    }
    fn read(&self, dir: &Path) -> std::result::Result<u64, String> {
        let device = autodiff_cpu()?;
        let (model, _optim, state) = load_checkpoint(dir, &device).map_err(|e| err_text(&e))?;
        Ok(fingerprint_debug(&(
            model_fingerprint(&model.valid())?,
            state,
        )))
    }
}
