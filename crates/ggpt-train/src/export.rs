//! Export of a trained network in the official formats: a `.safetensors` state dict with the
//! official key names and PyTorch layouts (`network.md` §12.2; loads strictly with
//! `ggpt_model::weights::load_checkpoint`) and the official `model_config` JSON.

use std::path::Path;

use burn::module::Module;
use burn_store::ModuleSnapshot;
use ggpt_core::chunking::ChunkingSettings;
use ggpt_core::io::st::{Dtype, StWriter};
use ggpt_model::model_dir::{
    INFERENCE_SETTINGS_FILE, InferenceSettings, MODEL_CONFIG_FILE, MODEL_WEIGHTS_FILE,
};
use ggpt_model::weights::official_key;
use ggpt_model::{Ggpt, GgptConfig};

use crate::error::{Result, TrainError};

/// One tensor of an official state dict: key, dtype, shape, little-endian bytes.
pub type StateDictEntry = (String, Dtype, Vec<usize>, Vec<u8>);

/// Official key and PyTorch-layout f32 values of every model tensor (Linear weights transposed
/// back to `[out, in]`), plus a `num_batches_tracked` (i64, 0-d) per BatchNorm set to `steps`.
pub fn official_state_dict(model: &Ggpt, steps: u64) -> Result<Vec<StateDictEntry>> {
    let model = model.valid();
    let mut out = Vec::new();
    for t in model.collect(None, None, false) {
        let name = t.name.clone();
        let shape: Vec<usize> = t.shape.iter().copied().collect();
        let bytes = t
            .to_bytes()
            .map_err(|e| TrainError::Invalid(format!("tensor {name}: {e:?}")))?;
        if bytes.len() != 4 * shape.iter().product::<usize>() {
            return Err(TrainError::Invalid(format!(
                "tensor {name}: {} bytes for shape {shape:?} (expected f32)",
                bytes.len()
            )));
        }
        let key = official_key(&name);
        let (shape, bytes) = if shape.len() == 2 {
            // Burn Linear weight [in, out] -> PyTorch [out, in]
            let (r, c) = (shape[0], shape[1]);
            let mut tb = vec![0u8; bytes.len()];
            for i in 0..r {
                for j in 0..c {
                    let (s, d) = (4 * (i * c + j), 4 * (j * r + i));
                    tb[d..d + 4].copy_from_slice(&bytes[s..s + 4]);
                }
            }
            (vec![c, r], tb)
        } else {
            (shape, bytes.to_vec())
        };
        if let Some(prefix) = key.strip_suffix(".running_mean") {
            out.push((
                format!("{prefix}.num_batches_tracked"),
                Dtype::I64,
                vec![],
                (steps as i64).to_le_bytes().to_vec(),
            ));
        }
        out.push((key, Dtype::F32, shape, bytes));
    }
    out.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(out)
}

/// Writes `model` as an official `.safetensors` state dict (atomically).
pub fn save_official_safetensors(model: &Ggpt, steps: u64, path: &Path) -> Result<()> {
    let mut w = StWriter::new();
    for (name, dtype, shape, bytes) in official_state_dict(model, steps)? {
        w.raw(&name, dtype, &shape, bytes);
    }
    let bytes = w.finish(path, None)?;
    ggpt_core::io::atomic::write_atomic(path, |w| w.write_all(&bytes))?;
    Ok(())
}

/// The official `model_config` JSON object of `cfg` (the fields `GgptConfig` reads plus the
/// official descriptive ones: `enc_dim`, `output_dim`, `enable_flash`, `embedding_type`, ...).
pub fn official_model_config(cfg: &GgptConfig) -> Result<serde_json::Value> {
    let mut v =
        serde_json::to_value(cfg).map_err(|e| TrainError::Invalid(format!("model config: {e}")))?;
    if let Some(obj) = v.as_object_mut() {
        obj.insert(
            "enc_dim".into(),
            cfg.enc_channels.first().copied().unwrap_or(0).into(),
        );
        obj.insert(
            "output_dim".into(),
            cfg.dec_channels.first().copied().unwrap_or(0).into(),
        );
        obj.insert("enable_flash".into(), true.into());
        obj.insert("embedding_type".into(), "MLP".into());
        obj.insert("predict_residual".into(), true.into());
        obj.insert("zero_init".into(), true.into());
        obj.insert("turn_off_bn".into(), false.into());
    }
    Ok(v)
}

/// Writes `model_config.json` (atomically).
pub fn save_model_config(cfg: &GgptConfig, path: &Path) -> Result<()> {
    let text = serde_json::to_string_pretty(&official_model_config(cfg)?)
        .map_err(|e| TrainError::Invalid(e.to_string()))?;
    ggpt_core::io::atomic::write_atomic(path, |w| w.write_all(text.as_bytes()))?;
    Ok(())
}

/// Sampler settings recorded by `prepare` in a chunk set's manifest (`provenance.params.chunking`),
/// as the `chunking` section of a model's `inference.json`: a model trained on such chunks is run
/// on chunks of the same size.
pub fn training_chunking(provenance: &serde_json::Value) -> Option<ChunkingSettings> {
    let c = provenance.get("params")?.get("chunking")?;
    Some(ChunkingSettings {
        chunk_size: c.get("chunk_size").and_then(|v| v.as_f64()),
        max_pixels: c
            .get("max_pixels")
            .and_then(|v| v.as_u64())
            .map(|v| v as usize),
        min_dlt: c
            .get("min_dlt")
            .and_then(|v| v.as_u64())
            .map(|v| v as usize),
        min_pixels: c
            .get("min_pixels")
            .and_then(|v| v.as_u64())
            .map(|v| v as usize),
    })
}

/// Writes a model folder that `ggpt-infer` loads directly: `model.safetensors` (official keys),
/// `model_config.json` and, when the training chunk sampler is known, `inference.json` with it.
/// Every file is written atomically.
pub fn export_model_dir(
    model: &Ggpt,
    steps: u64,
    cfg: &GgptConfig,
    chunking: Option<ChunkingSettings>,
    dir: &Path,
) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(crate::error::io_err(dir))?;
    save_official_safetensors(model, steps, &dir.join(MODEL_WEIGHTS_FILE))?;
    save_model_config(cfg, &dir.join(MODEL_CONFIG_FILE))?;
    let path = dir.join(INFERENCE_SETTINGS_FILE);
    match chunking {
        Some(chunking) => {
            let settings = InferenceSettings {
                chunking: Some(chunking),
            };
            let text = serde_json::to_string_pretty(&settings)
                .map_err(|e| TrainError::Invalid(e.to_string()))?;
            ggpt_core::io::atomic::write_atomic(&path, |w| w.write_all(text.as_bytes()))?;
        }
        None if path.exists() => {
            std::fs::remove_file(&path).map_err(crate::error::io_err(&path))?
        }
        None => {}
    }
    Ok(())
}
