//! The in-memory scene: everything the pipeline knows about one multi-view sequence.
//!
//! All dense arrays are flat `Vec`s in **pixel order** `p = (n * h + y) * w + x` (see
//! `docs/conventions.md`); per-pixel vectors are interleaved (`[N, h, w, 3]` → `3 * p + a`).

use crate::{Cameras, CoreError, Result};

/// Feed-forward resolution of a scene: `n` views of `h x w` pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Dims {
    /// Views.
    pub n: usize,
    /// Height in pixels.
    pub h: usize,
    /// Width in pixels.
    pub w: usize,
}

impl Dims {
    /// Pixels per view, `h * w`.
    pub fn hw(&self) -> usize {
        self.h * self.w
    }
    /// Pixels of all views, `n * h * w`.
    pub fn pixels(&self) -> usize {
        self.n * self.h * self.w
    }
    /// Flat pixel index of view `n`, row `y`, column `x`.
    pub fn index(&self, n: usize, y: usize, x: usize) -> usize {
        (n * self.h + y) * self.w + x
    }
}

/// Ground truth at feed-forward resolution (metric, metres, GT world frame).
#[derive(Debug, Clone, PartialEq)]
pub struct GroundTruth {
    /// `[N, h, w, 3]` GT world points, 0 where `mask` is false.
    pub points: Vec<f32>,
    /// `[N, h, w]` valid GT (depth > 1e-5).
    pub mask: Vec<bool>,
    /// `[N, h, w]` GT z-depth in metres, 0 where invalid (absent in the official `gt.bin`).
    pub depth: Option<Vec<f32>>,
    /// GT cameras (`cam_from_world` in the GT world frame, K at ff resolution).
    pub cameras: Cameras,
}

/// Dense feed-forward prediction `X_d` (feed-forward frame, scene units).
#[derive(Debug, Clone, PartialEq)]
pub struct FeedForward {
    /// `[N, h, w, 3]` dense points.
    pub points: Vec<f32>,
    /// `[N, h, w]` raw confidence (VGGT `1 + exp` scale, ≥ 1).
    pub conf: Vec<f32>,
    /// Feed-forward cameras (ff pixels, pixel-centre convention; principal point as the
    /// feed-forward model gives it, e.g. VGGT's `(w/2, h/2)` or the centre `((w-1)/2, (h-1)/2)`).
    pub cameras: Cameras,
}

/// Output of the SfM stage (SfM frame, scene units).
#[derive(Debug, Clone, PartialEq)]
pub struct SfmResult {
    /// `[N, h, w, 3]` DLT point map `X_s`, 0 where `mask` is false.
    pub points: Vec<f32>,
    /// `[N, h, w]` `M_s`: the pixel has a DLT point.
    pub mask: Vec<bool>,
    /// Bundle-adjusted cameras.
    pub cameras: Cameras,
    /// BA ran successfully.
    pub camera_success: bool,
    /// At least one DLT pixel exists.
    pub points_success: bool,
}

/// Dense matches of one matcher for every ordered view pair (layout of `sfm.md` §2.1).
#[derive(Debug, Clone, PartialEq)]
pub struct MatchSet {
    /// Matcher name (e.g. `romav2-base`, `synthetic-a`).
    pub matcher: String,
    /// `[N, N, h*w, 2]`: `[t, s, k]` = location `(x, y)` in view `t` (ff pixels) of pixel `k` of view `s`.
    pub pred_matches: Vec<f32>,
    /// `[N, N, h*w]` matcher confidence.
    pub pred_scores: Vec<f32>,
    /// `[N, N, h*w]` cycle error (ff pixels), computed by the SfM stage when absent.
    pub pred_cycle_error: Option<Vec<f32>>,
    /// `[N, h*w]` optional ranking score for BA track selection (e.g. SuperPoint).
    pub rank_scores: Option<Vec<f32>>,
}

/// One multi-view scene.
#[derive(Debug, Clone, PartialEq)]
pub struct Scene {
    /// Sequence name (seeds the chunk sampler, `pipeline.md` §5).
    pub name: String,
    /// Feed-forward resolution.
    pub dims: Dims,
    /// `[N, h, w, 3]` RGB in `[0, 1]` at ff resolution.
    pub images: Vec<f32>,
    /// Ground truth, when known.
    pub gt: Option<GroundTruth>,
    /// Feed-forward prediction.
    pub ff: Option<FeedForward>,
    /// SfM result.
    pub sfm: Option<SfmResult>,
    /// Dense matches, one entry per matcher.
    pub matches: Vec<MatchSet>,
}

impl Scene {
    /// Checks that every array has the size `dims` implies, that camera counts equal `N`, and
    /// that points, confidences and cameras are finite. Errors name the offending field and
    /// the first bad index.
    pub fn validate(&self) -> Result<()> {
        let d = self.dims;
        let px = d.pixels();
        let check_len = |what: &str, len: usize, want: usize| -> Result<()> {
            if len != want {
                return Err(CoreError::Invalid(format!(
                    "{what}: {len} values, expected {want} for N={} h={} w={}",
                    d.n, d.h, d.w
                )));
            }
            Ok(())
        };
        let check_finite = |what: &str, v: &[f32]| -> Result<()> {
            crate::io::st::check_finite_f32(std::path::Path::new(&self.name), what, v)
        };
        let check_cams = |what: &str, c: &Cameras| -> Result<()> {
            if c.cam_from_world.len() != d.n || c.intrinsics.len() != d.n {
                return Err(CoreError::Invalid(format!(
                    "{what}: {} extrinsics / {} intrinsics for {} views",
                    c.cam_from_world.len(),
                    c.intrinsics.len(),
                    d.n
                )));
            }
            if !c.is_finite() {
                return Err(CoreError::Invalid(format!(
                    "{what}: non-finite camera entry"
                )));
            }
            Ok(())
        };
        check_len("images", self.images.len(), 3 * px)?;
        if let Some(gt) = &self.gt {
            check_len("gt.points", gt.points.len(), 3 * px)?;
            check_len("gt.mask", gt.mask.len(), px)?;
            if let Some(depth) = &gt.depth {
                check_len("gt.depth", depth.len(), px)?;
                check_finite("gt.depth", depth)?;
            }
            check_finite("gt.points", &gt.points)?;
            check_cams("gt.cameras", &gt.cameras)?;
        }
        if let Some(ff) = &self.ff {
            check_len("ff.points", ff.points.len(), 3 * px)?;
            check_len("ff.conf", ff.conf.len(), px)?;
            check_finite("ff.points", &ff.points)?;
            check_finite("ff.conf", &ff.conf)?;
            check_cams("ff.cameras", &ff.cameras)?;
        }
        if let Some(sfm) = &self.sfm {
            check_len("sfm.points", sfm.points.len(), 3 * px)?;
            check_len("sfm.mask", sfm.mask.len(), px)?;
            check_finite("sfm.points", &sfm.points)?;
            check_cams("sfm.cameras", &sfm.cameras)?;
        }
        let pairs = d.n * d.n * d.hw();
        for m in &self.matches {
            let name = format!("matches[{}]", m.matcher);
            check_len(
                &format!("{name}.pred_matches"),
                m.pred_matches.len(),
                2 * pairs,
            )?;
            check_len(&format!("{name}.pred_scores"), m.pred_scores.len(), pairs)?;
            check_finite(&format!("{name}.pred_scores"), &m.pred_scores)?;
            if let Some(c) = &m.pred_cycle_error {
                check_len(&format!("{name}.pred_cycle_error"), c.len(), pairs)?;
            }
            if let Some(r) = &m.rank_scores {
                check_len(&format!("{name}.rank_scores"), r.len(), d.n * d.hw())?;
            }
        }
        Ok(())
    }
}
