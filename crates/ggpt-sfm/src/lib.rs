//! GGPT SfM stage (`sfm.md`): dense-match filtering, BA track selection, bundle adjustment,
//! epipolar filter, batched DLT triangulation and scatter to pixels.
//!
//! Building blocks, one per module:
//! * [`matches`] / [`convert`]: the correspondence tensor (§2) and matcher-output conversion;
//! * [`cycle`]: forward-backward error (§3); [`ensemble`]: multi-matcher ensembling (§4);
//! * [`masks`]: BA / DLT masks and the threshold presets (§5);
//! * [`tracks`]: greedy BA track selection and the Shi–Tomasi ranking score (§6);
//! * [`ba`]: bundle adjustment (§7);
//! * [`epipolar`] (§8), [`dlt`] (§9), [`scatter`] (§10);
//! * [`pipeline`]: [`pipeline::run_sfm`], the whole stage; [`input`]: the file readers of the
//!   `ggpt-sfm` binary; [`output`]: the writers.
//!
//! Conventions: ff pixels with the pixel-centre convention (top-left pixel centre = `(0, 0)`),
//! cameras `cam_from_world` (OpenCV axes), geometry in f64.

pub mod ba;
pub mod convert;
pub mod cycle;
pub mod dlt;
pub mod ensemble;
pub mod epipolar;
pub mod error;
pub mod input;
pub mod masks;
pub mod matches;
pub mod output;
pub mod pipeline;
pub mod scatter;
pub mod tracks;

pub use error::{Result, SfmError};
