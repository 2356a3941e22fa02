//! File formats (`formats.md`). Every reader rejects malformed input with a [`crate::CoreError`]
//! naming the file, the key and the problem; every writer is atomic (temp file + rename).

pub mod arrays;
pub mod atomic;
pub mod colmap;
pub mod feedforward;
pub mod ggpt_eval;
pub mod infer_folder;
pub mod matches;
pub mod npy;
pub mod official;
pub mod ply;
pub mod png;
pub mod scene_dir;
pub mod st;
pub mod torch_zip;
