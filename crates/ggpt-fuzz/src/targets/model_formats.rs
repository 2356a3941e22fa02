//! Targets of `ggpt-model`'s and `ggpt-infer`'s readers: chunk records, checkpoints in the three
//! weight formats (official-key safetensors, official-key `.pth`, burnpack), `model_config.json`
//! and `inference.json`.

use std::hash::{DefaultHasher, Hash, Hasher};
use std::path::Path;
use std::sync::Mutex;

use burn_store::ModuleSnapshot;
use ggpt_core::io::st::StWriter;
use ggpt_core::io::torch_zip::{TorchValue, contiguous_strides, torch_zip_bytes};
use ggpt_model::{Ggpt, GgptConfig};

use super::{err_text, seed_from_writer};
use crate::harness::{SeedFile, Target, fingerprint_debug};
use crate::{FuzzError, Result};

fn seed_err(target: &str, message: impl std::fmt::Display) -> FuzzError {
    FuzzError::Seed {
        target: target.to_string(),
        message: message.to_string(),
    }
}

/// The CPU device the model targets load onto.
fn cpu_device() -> std::result::Result<burn::tensor::Device, String> {
    ggpt_model::device::device_from_name("ndarray").map_err(|e| e.to_string())
}

/// Fingerprint of every tensor (name, shape, bytes) of `model`.
pub fn model_fingerprint(model: &Ggpt) -> std::result::Result<u64, String> {
    let mut h = DefaultHasher::new();
    for t in model.collect(None, None, false) {
        t.name.hash(&mut h);
        t.shape.iter().copied().collect::<Vec<usize>>().hash(&mut h);
        t.to_bytes()
            .map_err(|e| format!("tensor {}: {e:?}", t.name))?
            .hash(&mut h);
    }
    Ok(h.finish())
}

/// Chunk-input records (`ggpt-infer chunk --input`; `read_chunk_inputs`).
pub struct ChunkRecord;

impl Target for ChunkRecord {
    fn name(&self) -> &'static str {
        "chunk-record"
    }
    fn describe(&self) -> &'static str {
        "chunk-input safetensors (`ggpt-infer chunk`)"
    }
    fn seed(&self) -> Result<Vec<SeedFile>> {
        let path = Path::new("chunks.safetensors");
        let mut w = StWriter::new();
        for (c, k) in [(0usize, 12usize), (1, 7)] {
            let pts: Vec<f32> = (0..3 * k).map(|i| (i as f32 * 0.37).sin()).collect();
            w.f32(&format!("chunk{c}/ff_pts"), &[k, 3], &pts);
            w.f32(
                &format!("chunk{c}/ff_pts_conf"),
                &[k],
                &(0..k).map(|i| 1.0 + i as f32).collect::<Vec<_>>(),
            );
            w.f32(
                &format!("chunk{c}/geo_pts"),
                &[k, 3],
                &pts.iter().map(|x| x * 0.9).collect::<Vec<_>>(),
            );
            w.bool(
                &format!("chunk{c}/geo_msks"),
                &[k],
                &(0..k).map(|i| i % 2 == 0).collect::<Vec<_>>(),
            );
        }
        let bytes = w.finish(path, None).map_err(|e| seed_err(self.name(), e))?;
        Ok(vec![SeedFile::new(path, bytes)])
    }
    fn read(&self, dir: &Path) -> std::result::Result<u64, String> {
        ggpt_model::chunk_io::read_chunk_inputs(&dir.join("chunks.safetensors"))
            .map(|c| fingerprint_debug(&c))
            .map_err(|e| err_text(&e))
    }
}

/// The weight formats `ggpt_model::weights::load_checkpoint` reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WeightsFormat {
    /// Official-key safetensors.
    Safetensors,
    /// Official-key torch zip pickle.
    Pth,
    /// This crate's burnpack.
    Burnpack,
}

/// A random-init tiny network saved in one weight format, loaded strictly into a fresh one.
pub struct Weights {
    format: WeightsFormat,
    /// The network the seed is made of and every case loads into (cloned per case).
    template: Mutex<Option<Ggpt>>,
}

impl Weights {
    /// The target of `format`.
    pub fn new(format: WeightsFormat) -> Self {
        Self {
            format,
            template: Mutex::new(None),
        }
    }

    fn file_name(&self) -> &'static str {
        match self.format {
            WeightsFormat::Safetensors => "model.safetensors",
            WeightsFormat::Pth => "model.pth",
            WeightsFormat::Burnpack => "model.bpk",
        }
    }

    fn template(&self) -> std::result::Result<Ggpt, String> {
        let mut t = self
            .template
            .lock()
            .map_err(|_| "template lock poisoned".to_string())?;
        if t.is_none() {
            let device = cpu_device()?;
            device.seed(3);
            *t = Some(Ggpt::new(&GgptConfig::tiny(), &device));
        }
        t.clone().ok_or_else(|| "no template".to_string())
    }
}

/// The official state dict of `model` as torch-zip entries (i64 `num_batches_tracked` as
/// `LongStorage`).
fn pth_bytes(model: &Ggpt) -> std::result::Result<Vec<u8>, String> {
    let dict = ggpt_train::export::official_state_dict(model, 5).map_err(|e| e.to_string())?;
    let entries: Vec<(&str, TorchValue)> = dict
        .iter()
        .map(|(name, dtype, shape, bytes)| {
            let (storage, size) = if *dtype == safetensors::Dtype::I64 {
                ("LongStorage", 8)
            } else {
                ("FloatStorage", 4)
            };
            let value = TorchValue::Tensor {
                storage,
                bytes: bytes.clone(),
                numel: bytes.len() / size,
                offset: 0,
                size: shape.clone(),
                stride: contiguous_strides(shape),
            };
            (name.as_str(), value)
        })
        .collect();
    torch_zip_bytes("model", &entries).map_err(|e| e.to_string())
}

impl Target for Weights {
    fn name(&self) -> &'static str {
        match self.format {
            WeightsFormat::Safetensors => "weights-safetensors",
            WeightsFormat::Pth => "weights-pth",
            WeightsFormat::Burnpack => "weights-burnpack",
        }
    }
    fn describe(&self) -> &'static str {
        match self.format {
            WeightsFormat::Safetensors => "official-key safetensors checkpoint (tiny network)",
            WeightsFormat::Pth => "official-key `.pth` checkpoint (tiny network)",
            WeightsFormat::Burnpack => "burnpack checkpoint (tiny network)",
        }
    }
    fn seed(&self) -> Result<Vec<SeedFile>> {
        let model = self.template().map_err(|m| seed_err(self.name(), m))?;
        let (format, file) = (self.format, self.file_name());
        seed_from_writer(self.name(), |dir| {
            let path = dir.join(file);
            match format {
                WeightsFormat::Safetensors => {
                    ggpt_train::export::save_official_safetensors(&model, 5, &path)
                        .map_err(|e| e.to_string())
                }
                WeightsFormat::Pth => {
                    std::fs::write(&path, pth_bytes(&model)?).map_err(|e| e.to_string())
                }
                WeightsFormat::Burnpack => {
                    ggpt_model::weights::save_burnpack(&model, &path).map_err(|e| e.to_string())
                }
            }
        })
    }
    fn read(&self, dir: &Path) -> std::result::Result<u64, String> {
        let model = self.template()?;
        let loaded = ggpt_model::weights::load_checkpoint(model, &dir.join(self.file_name()))
            .map_err(|e| err_text(&e))?;
        model_fingerprint(&loaded)
    }
}

/// `model_config.json` as `ggpt-train export` writes it (`GgptConfig::from_json_file`).
pub struct ModelConfigJson;

impl Target for ModelConfigJson {
    fn name(&self) -> &'static str {
        "model-config-json"
    }
    fn describe(&self) -> &'static str {
        "`model_config.json`"
    }
    fn seed(&self) -> Result<Vec<SeedFile>> {
        seed_from_writer(self.name(), |dir| {
            ggpt_train::export::save_model_config(
                &GgptConfig::small(),
                &dir.join("model_config.json"),
            )
            .map_err(|e| e.to_string())
        })
    }
    fn read(&self, dir: &Path) -> std::result::Result<u64, String> {
        GgptConfig::from_json_file(&dir.join("model_config.json"))
            .map(|c| fingerprint_debug(&c))
            .map_err(|e| err_text(&e))
    }
}

/// A model folder's `inference.json` (`read_inference_settings`).
pub struct InferenceJson;

impl Target for InferenceJson {
    fn name(&self) -> &'static str {
        "inference-json"
    }
    fn describe(&self) -> &'static str {
        "`inference.json`"
    }
    fn seed(&self) -> Result<Vec<SeedFile>> {
        let settings = ggpt_model::model_dir::InferenceSettings {
            chunking: Some(ggpt_core::chunking::ChunkingSettings {
                chunk_size: Some(0.25),
                max_pixels: Some(40_000),
                min_dlt: Some(50),
                min_pixels: Some(2_000),
            }),
        };
        let text = serde_json::to_string_pretty(&settings).map_err(|e| seed_err(self.name(), e))?;
        Ok(vec![SeedFile::new("inference.json", text.into_bytes())])
    }
    fn read(&self, dir: &Path) -> std::result::Result<u64, String> {
        ggpt_model::model_dir::read_inference_settings(&dir.join("inference.json"))
            .map(|s| fingerprint_debug(&s))
            .map_err(|e| err_text(&e))
    }
}
