//! Training of the GGPT network (`pipeline.md` §11, `docs/training.md`).
//!
//! * [`chunkset`]: the sharded, checksummed on-disk format of curated training chunks.
//! * [`prepare`]: training chunks from synthetic scenes (`ggpt-synth` + `ggpt-sfm`) or official
//!   per-sequence directories, with GT Sim(3)-aligned into the SfM frame.
//! * [`loss`]: `L = L_conf + λ_id L_id` (§11.3).
//! * [`trainer`]: the hand-written Burn autodiff loop: Adam, schedules, clipping, checkpoints,
//!   exact resume.
//! * [`evaluate`]: chunk-level validation and whole-scene evaluation through
//!   `ggpt_scene::refine_scene`.
//! * [`export`]: official `.safetensors` + `model_config.json`.
//! * [`plot`]: the training-curve PNG.
//! * [`scene_source`]: where a chunk-set scene came from, and how to rebuild it.
//! * [`model_source`]: a model from any form the commands accept (model folder, run or
//!   checkpoint directory, weight file).

pub mod chunkset;
pub mod error;
pub mod evaluate;
pub mod export;
pub mod grads;
pub mod loss;
pub mod model_source;
pub mod plot;
pub mod prepare;
pub mod scene_source;
pub mod trainer;

pub use error::{Result, TrainError};
