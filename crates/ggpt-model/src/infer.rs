//! Convenience: plan, upload and run chunks in one call.

use burn::tensor::Device;

use crate::config::{GgptConfig, NUM_LEVELS};
use crate::error::{ModelError, Result};
use crate::model::{ChunkOutput, Ggpt};
use crate::plan::{AsChunkView, PlanConfig, plan_batch};
use crate::prepared::PreparedBatch;

/// Planning parameters of a model configuration (grid 384, one patch size for all levels).
pub fn plan_config(cfg: &GgptConfig) -> PlanConfig {
    PlanConfig {
        grid_resolution: cfg.grid_resolution,
        patch_size: vec![cfg.patch_size; NUM_LEVELS],
        num_levels: NUM_LEVELS,
    }
}

/// Plans `chunks` as one batch and uploads the tables to `device`. The chunks are borrowed
/// ([`AsChunkView`]): a forward over chunk records or training chunks copies none of their
/// arrays.
pub fn prepare_chunks<C: AsChunkView>(
    cfg: &GgptConfig,
    chunks: &[C],
    device: &Device,
) -> Result<PreparedBatch> {
    let plan =
        plan_batch(chunks, &plan_config(cfg)).map_err(|e| ModelError::Planning(e.to_string()))?;
    PreparedBatch::new(&plan, cfg, device)
}

/// Runs `chunks` as one batched forward and returns the per-chunk outputs (network.md §10).
pub fn infer_chunks<C: AsChunkView>(
    model: &Ggpt,
    cfg: &GgptConfig,
    chunks: &[C],
    device: &Device,
) -> Result<Vec<ChunkOutput>> {
    let batch = prepare_chunks(cfg, chunks, device)?;
    model.forward(&batch).to_chunks(&batch)
}
