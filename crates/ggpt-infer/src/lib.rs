//! `ggpt-infer` library: whole-scene GGPT inference with the Burn network.
//!
//! * [`refiner`]: [`refiner::BurnRefiner`], the network as a `ggpt_scene::ChunkRefiner`
//!   (several chunks per forward within a token budget, eval mode, one forward alive at a time);
//! * the model folder (weights, configuration, `inference.json`, the shipped model):
//!   [`ggpt_model::model_dir`];
//! * [`pipeline`]: [`pipeline::run_scene`] — SfM when needed, refinement, export, evaluation;
//! * before / after metrics: [`ggpt_eval::refinement`]; per-view error maps:
//!   [`ggpt_eval::error_maps`];
//! * [`run_output`]: [`run_output::RunOutput`], the one writer of the run folder, and its file
//!   names;
//! * [`demo`]: the synthetic end-to-end demo; [`rss`]: per-stage wall time and peak memory.
//!
//! Frames and units: refined points in the SfM frame (scene units); evaluation in the GT frame
//! (metres, errors in cm); pixels in ff resolution with the pixel-centre convention.

pub mod demo;
pub mod engine;
pub mod error;
pub mod inputs;
pub mod pipeline;
pub mod refiner;
pub mod rss;
pub mod run_output;

pub use engine::Refiner;
pub use error::{InferError, Result};
