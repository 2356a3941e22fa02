//! Core data model of ggpt-rs.
//!
//! * [`scene`]: the in-memory scene (images, ground truth, feed-forward prediction, SfM result,
//!   dense matches), all dense arrays flat in *pixel order* `p = (n * h + y) * w + x`.
//! * [`camera`]: pinhole cameras, `cam_from_world` extrinsics (OpenCV axes).
//! * [`sim3`]: Umeyama and robust (LO-RANSAC) Sim(3) estimation.
//! * [`metrics`]: point / camera / depth accuracy (AUC@τ).
//! * [`io`]: every file format the project reads or writes.
//!
//! Conventions (frames, pixel centres, units) are in `docs/conventions.md`.

pub mod camera;
pub mod chunking;
pub mod error;
pub mod io;
pub mod metrics;
pub mod scene;
pub mod sim3;

pub use camera::Cameras;
pub use error::{CoreError, Result};
pub use scene::{Dims, FeedForward, GroundTruth, MatchSet, Scene, SfmResult};
