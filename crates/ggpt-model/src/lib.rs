//! GGPT network (Point Transformer V3 backbone + guidance encoding + residual head) in
//! Burn 0.22, bit-faithful to the official PyTorch model (`docs/network.md`,
//! `shared/spec/network.md`).
//!
//! Flow: [`plan::plan_batch`] (host integer planning) -> [`PreparedBatch::new`] (upload index
//! tables) -> [`Ggpt::forward`] -> [`GgptOutput::to_chunks`].

#![warn(missing_docs)]

pub mod attention;
pub mod bench;
pub mod block;
pub mod chunk_io;
pub mod config;
pub mod conv_layout;
pub mod device;
pub mod device_stats;
pub mod drop_path;
pub mod error;
pub mod grads;
pub mod head;
pub mod host_attention;
pub mod host_attention_grad;
pub mod host_conv_grad;
mod host_dense;
pub mod infer;
pub mod kernels;
pub mod linear_bn;
pub mod model;
pub mod model_dir;
pub mod norm;
pub mod ops;
pub mod plan;
pub mod pooling;
pub mod prepared;
pub mod profile;
pub mod readback;
pub mod recompute;
pub mod recorder;
pub mod segments;
pub mod sparse_conv;
pub mod unpooling;
pub mod weights;

pub use config::GgptConfig;
pub use error::{ModelError, Result};
pub use model::{ChunkOutput, Ggpt, GgptOutput};
pub use prepared::PreparedBatch;
pub use recorder::Recorder;
