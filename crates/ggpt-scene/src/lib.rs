//! GGPT scene pipeline around the network (`pipeline.md` §3-§9), free of any Burn dependency:
//!
//! * [`prealign`]: Sim(3) pre-alignment of the dense feed-forward points into the SfM frame (§3),
//!   and the GT alignment used by training / evaluation (§11.1).
//! * [`radius`]: the scene radius `R` (§4).
//! * [`chunker`]: the random overlapping-cube chunk sampler (§5), with an injectable draw source.
//! * [`record`]: per-chunk records normalised to the chunk frame (§6).
//! * [`roi`]: evaluation regions of interest (T&T box, 4D-DRESS mask).
//! * [`fusion`]: streaming per-pixel fusion of refined chunks (§8).
//! * [`driver`]: [`driver::refine_scene`], the whole refinement against a [`driver::ChunkRefiner`]
//!   (the network is supplied by the caller), batched by a token budget (§7).
//! * [`export`]: PLY / npy / npz / COLMAP export (§9).
//!
//! Frames: the refined outputs live in the SfM frame (scene units); chunk records in the chunk
//! frame `x' = (x - c) / r`. Arrays are flat in pixel order `p = (n * h + y) * w + x`.

pub mod chunk_settings;
pub mod chunker;
pub mod driver;
pub mod error;
pub mod export;
pub mod fusion;
pub mod prealign;
pub mod radius;
pub mod record;
pub mod roi;
pub mod splat;

#[cfg(test)]
pub(crate) mod test_util;

pub use chunker::{Chunk, ChunkParams, ChunkSampler, DrawSource, PcgDraws};
pub use driver::{ChunkRefiner, RefineOptions, RefinedChunk, RefinedScene, refine_scene};

pub use error::SceneError;
pub use record::ChunkRecord;
