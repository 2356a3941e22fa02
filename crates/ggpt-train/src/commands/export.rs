//! `ggpt-train export`: a checkpoint as an official model folder.

use anyhow::{Context, Result};
use ggpt_model::Ggpt;
use ggpt_model::model_dir::MODEL_WEIGHTS_FILE;
use ggpt_train::chunkset::{ChunkSet, Split};
use ggpt_train::model_source::require_checkpoint;
use ggpt_train::trainer;

use crate::cli::ExportArgs;

/// Runs `export`.
pub fn run(a: &ExportArgs) -> Result<()> {
    let device = ggpt_model::device::device_from_name("cpu")?;
    let dir = require_checkpoint(&a.checkpoint)?;
    let (mut model, _, st) = trainer::load_checkpoint(&dir, &device)?;
    let set = ChunkSet::open(&st.data);
    if a.bn_recalibrate_batches > 0 {
        let set = set.as_ref().map_err(|e| {
            anyhow::anyhow!(
                "--bn-recalibrate-batches needs the training chunk set {}: {e}",
                st.data.display()
            )
        })?;
        let chunks = set.load_split(Split::Train)?;
        let batch = a.bn_recalibrate_batch_size.unwrap_or(st.options.batch_size);
        tracing::info!(
            "re-estimating BatchNorm statistics over {} batches of {batch} training chunks",
            a.bn_recalibrate_batches
        );
        model = trainer::recalibrate_batch_norm(
            model,
            &st.options.model,
            &chunks,
            batch,
            a.bn_recalibrate_batches,
            st.options.seed,
            &device.clone().autodiff(),
        )?;
    }
    let chunking = match &set {
        Ok(set) => ggpt_train::export::training_chunking(&set.manifest.provenance),
        Err(e) => {
            tracing::warn!(
                "training chunk set {} unreadable ({e}): no inference.json written",
                st.data.display()
            );
            None
        }
    };
    ggpt_train::export::export_model_dir(&model, st.step, &st.options.model, chunking, &a.out_dir)?;
    // strict reload check
    ggpt_model::weights::load_checkpoint(
        Ggpt::new(&st.options.model, &device),
        &a.out_dir.join(MODEL_WEIGHTS_FILE),
    )
    .context("strict reload of the export")?;
    println!(
        "exported step {} to {} (strict reload ok)",
        st.step,
        a.out_dir.display()
    );
    Ok(())
}
