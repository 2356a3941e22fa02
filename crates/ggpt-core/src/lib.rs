//! Core data model of ggpt-rs.
//!
//! * [`scene`]: the in-memory scene (images, ground truth, feed-forward prediction, SfM result,
//!   dense matches), all dense arrays flat in *pixel order* `p = (n * h + y) * w + x`.
//! * [`camera`]: pinhole cameras, `cam_from_world` extrinsics (OpenCV axes).
//! * [`sim3`]: Umeyama and robust (LO-RANSAC) Sim(3) estimation.
//! * [`metrics`]: point / camera / depth accuracy (AUC@τ).
//! * [`io`]: every file format the project reads or writes.
//! * [`progress`]: progress reports of long calls (callbacks; binaries draw the bars).
//! * [`chunk_input`]: the per-pixel network input of one chunk (shared by planner, records and
//!   training chunks).
//! * [`resize`]: PyTorch-exact bilinear / nearest-exact resizing.
//! * [`color`]: the `[0, 1]` -> `u8` colour conversion of the exports.
//!
//! Conventions (frames, pixel centres, units) are in `docs/conventions.md`.

pub mod camera;
pub mod chunk_input;
pub mod chunking;
pub mod color;
pub mod error;
pub mod io;
pub mod metrics;
pub mod progress;
pub mod resize;
pub mod scene;
pub mod sim3;

pub use camera::Cameras;
pub use error::{CoreError, Result};
pub use progress::{Cancel, Progress};
pub use scene::{Dims, FeedForward, GroundTruth, MatchSet, Scene, SfmResult};
