//! [`ChunkRefiner`] adapter for the Burn GGPT network (`pipeline.md` §7).
//!
//! The scene driver (`ggpt_scene::driver`) groups chunk records into forwards by a token budget
//! and builds only one group of records at a time; this adapter plans the group
//! (`ggpt_model::plan`), uploads it, runs one batched forward and reads the dense outputs back.
//! Several chunks in one forward give the same results as one forward per chunk
//! (`network.md` §4.1). Activations of a forward are dropped before the next one, so memory is
//! bounded by the token budget, not by the number of views or chunks.
//!
//! Eval mode: the model must live on a plain (non-autodiff) device; BatchNorm then uses its
//! running statistics and drop path is the identity. An autodiff device is rejected.

use std::time::{Duration, Instant};

use burn::tensor::Device;
use ggpt_model::infer::prepare_chunks;
use ggpt_model::{Ggpt, GgptConfig};
use ggpt_scene::driver::RefinedChunk;
use ggpt_scene::{ChunkRecord, ChunkRefiner, SceneError};

use crate::rss::{peak_rss_bytes, reset_peak_rss};

/// Statistics gathered by a [`BurnRefiner`] (for the per-stage timing of `meta.json`).
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct RefinerStats {
    /// Forwards run.
    pub forwards: usize,
    /// Chunks refined.
    pub chunks: usize,
    /// Tokens over all forwards (dense + DLT).
    pub tokens: usize,
    /// Host planning + upload time (seconds).
    pub plan_seconds: f64,
    /// Network forward + read-back time (seconds).
    pub forward_seconds: f64,
    /// Largest forward (tokens).
    pub max_tokens_per_forward: usize,
    /// Peak resident memory of the process before the first forward (bytes; Linux only).
    pub peak_rss_before_first_forward: Option<u64>,
    #[serde(skip)]
    first_call: Option<Instant>,
}

impl RefinerStats {
    /// When the first forward started (the chunk sampling ends there).
    pub fn first_call(&self) -> Option<Instant> {
        self.first_call
    }
    /// Planning + forward seconds.
    pub fn network_seconds(&self) -> f64 {
        self.plan_seconds + self.forward_seconds
    }
}

/// The GGPT network as a [`ChunkRefiner`].
pub struct BurnRefiner {
    model: Ggpt,
    cfg: GgptConfig,
    device: Device,
    stats: RefinerStats,
    /// Reset the process's peak-RSS counter at the first forward (per-stage memory figures).
    measure_rss: bool,
}

impl BurnRefiner {
    /// Wraps a loaded model. Fails on an autodiff device (inference runs in eval mode).
    pub fn new(model: Ggpt, cfg: GgptConfig, device: Device) -> crate::Result<Self> {
        if device.is_autodiff() {
            return Err(crate::InferError::Invalid(
                "the refiner needs a plain (non-autodiff) device: inference runs in eval mode"
                    .into(),
            ));
        }
        Ok(BurnRefiner {
            model,
            cfg,
            device,
            stats: RefinerStats::default(),
            measure_rss: false,
        })
    }

    /// Resets the process's peak resident memory at the first forward, so that
    /// [`RefinerStats::peak_rss_before_first_forward`] and the peak read after the run separate
    /// the chunking stage from the network stage.
    pub fn with_rss_stages(mut self, on: bool) -> Self {
        self.measure_rss = on;
        self
    }

    /// Statistics so far.
    pub fn stats(&self) -> &RefinerStats {
        &self.stats
    }

    /// Returns the statistics gathered so far and resets them.
    pub fn take_stats(&mut self) -> RefinerStats {
        std::mem::take(&mut self.stats)
    }

    /// The model configuration.
    pub fn config(&self) -> &GgptConfig {
        &self.cfg
    }

    /// The network.
    pub fn model(&self) -> &Ggpt {
        &self.model
    }

    /// The device the network lives on.
    pub fn device(&self) -> &Device {
        &self.device
    }
}

impl ChunkRefiner for BurnRefiner {
    fn refine(&mut self, chunks: &[ChunkRecord]) -> Result<Vec<RefinedChunk>, SceneError> {
        if chunks.is_empty() {
            return Ok(Vec::new());
        }
        if self.stats.first_call.is_none() {
            self.stats.first_call = Some(Instant::now());
            if self.measure_rss {
                self.stats.peak_rss_before_first_forward = peak_rss_bytes();
                reset_peak_rss();
            }
        }
        let first = chunks.first().map_or(0, |c| c.index);
        let t0 = Instant::now();
        // The records lend their network input to the planner (no copy of the arrays).
        let batch = prepare_chunks(&self.cfg, chunks, &self.device).map_err(|e| {
            SceneError::Refiner(format!(
                "planning chunks {first}..{}: {e}",
                first + chunks.len()
            ))
        })?;
        let t1 = Instant::now();
        let out = self.model.forward(&batch).to_chunks(&batch).map_err(|e| {
            SceneError::Refiner(format!(
                "forward of chunks {first}..{}: {e}",
                first + chunks.len()
            ))
        })?;
        let t2 = Instant::now();
        let tokens = batch.num_tokens;
        drop(batch);
        self.stats.forwards += 1;
        self.stats.chunks += chunks.len();
        self.stats.tokens += tokens;
        self.stats.max_tokens_per_forward = self.stats.max_tokens_per_forward.max(tokens);
        self.stats.plan_seconds += secs(t1 - t0);
        self.stats.forward_seconds += secs(t2 - t1);
        tracing::debug!(
            "forward {}: chunks {first}..{} ({tokens} tokens), plan {:.3} s, network {:.3} s",
            self.stats.forwards,
            first + chunks.len(),
            secs(t1 - t0),
            secs(t2 - t1)
        );
        let mut results = Vec::with_capacity(out.len());
        for (rec, o) in chunks.iter().zip(out) {
            if let Some(i) = o
                .ff_pts_out
                .iter()
                .flatten()
                .chain(&o.ff_pts_conf_out)
                .position(|v| !v.is_finite())
            {
                return Err(SceneError::Refiner(format!(
                    "chunk {}: the network produced a non-finite output (value {i})",
                    rec.index
                )));
            }
            results.push(RefinedChunk {
                points: o.ff_pts_out,
                conf: o.ff_pts_conf_out,
            });
        }
        Ok(results)
    }
}

fn secs(d: Duration) -> f64 {
    d.as_secs_f64()
}
