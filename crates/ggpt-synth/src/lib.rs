//! Procedural synthetic multi-view scenes with exact ground truth, a simulated feed-forward
//! prediction and simulated dense matches: everything the GGPT pipeline consumes.
//!
//! * [`world`]: room / object layouts, camera placement (GT world: metres, y down, OpenCV).
//! * [`geometry`]: analytic primitives, exact `f64` ray intersection.
//! * [`texture`]: solid 3D procedural textures (colour is a function of the 3D point).
//! * [`render`]: ray casting into GT depth / points / images.
//! * [`feedforward`]: VGGT-like prediction with a structured error model.
//! * [`matches`]: two simulated dense matchers in the `sfm.md` §2.1 layout.
//! * [`stats`]: diagnostics (AUC of the ff points, match pass rates).
//!
//! Entry point: [`generate`]. Deterministic given [`SynthConfig::seed`], independent of the
//! number of threads. The model is described in `docs/synthetic.md`.

pub mod error;
pub mod feedforward;
pub mod geometry;
pub mod matches;
pub mod regime;
pub mod render;
pub mod rng;
pub mod stats;
pub mod texture;
pub mod world;

use std::time::Instant;

use nalgebra::{Matrix3, Matrix3x4};

use ggpt_core::{Cameras, Dims, GroundTruth, Progress, Scene};

pub use error::SynthError;
pub use feedforward::FfErrorModel;
pub use matches::{FailureModes, MatcherModel, default_matchers, matchers_for};
pub use regime::Regime;
pub use world::SceneKind;

/// Minimum / maximum number of views.
pub const VIEWS_RANGE: (usize, usize) = (2, 64);
/// Image sides must be multiples of this (VGGT patch size, `README.md` "Feed-forward resolution").
pub const PATCH: usize = 14;

/// Multiplier of the feed-forward error magnitudes in object scenes [project]: they are small
/// and close (1.6-2.3 m), so the same relative error would give much smaller absolute (cm)
/// errors than in rooms; feed-forward models are also relatively less accurate on close-ups.
pub const OBJECT_FF_ERROR_FACTOR: f64 = 1.5;
/// The same multiplier in [`Regime::Benchmark`] [project, calibrated so that object scenes'
/// feed-forward AUC@5 matches the rooms', `docs/synthetic.md`].
pub const OBJECT_FF_ERROR_FACTOR_BENCHMARK: f64 = 1.8;

/// Generator configuration.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SynthConfig {
    /// Scene family.
    pub kind: SceneKind,
    /// Number of views `N`.
    pub views: usize,
    /// Feed-forward width (pixels, multiple of 14; default 518).
    pub width: usize,
    /// Feed-forward height (pixels, multiple of 14; default 392).
    pub height: usize,
    /// Seed of every random choice.
    pub seed: u64,
    /// Simulation regime of the world (how many low-texture surfaces); [`SynthConfig::for_regime`]
    /// also picks the regime's `ff_error` and `matchers`. A `synth.json` written before regimes
    /// existed reads as [`Regime::Easy`].
    #[serde(default = "Regime::before_regimes")]
    pub regime: Regime,
    /// Generate dense matches.
    pub matches: bool,
    /// Room ceiling: `None` = random (rooms only).
    pub ceiling: Option<bool>,
    /// Feed-forward error model.
    pub ff_error: FfErrorModel,
    /// Simulated matchers (one `MatchSet` each).
    pub matchers: Vec<MatcherModel>,
    /// Principal point of the simulated feed-forward intrinsics `K_ff` (the GT cameras keep the
    /// exact image centre).
    #[serde(default)]
    pub principal_point: PrincipalPoint,
}

/// Principal-point convention of the feed-forward intrinsics (`sfm.md` §1 inputs, §7.1: the BA
/// keeps whatever principal point the feed-forward model gives).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PrincipalPoint {
    /// VGGT's native output `(w/2, h/2)` (ff pixels, pixel-centre convention): half a pixel right
    /// of / below the true image centre. The default, because that is what real users feed.
    #[default]
    Vggt,
    /// The exact image centre `((w-1)/2, (h-1)/2)` (feed-forward models converted to OpenCV).
    Centre,
}

impl PrincipalPoint {
    /// `(cx, cy)` of an `h x w` image in ff pixels (pixel-centre convention).
    pub fn of_image(self, h: usize, w: usize) -> (f64, f64) {
        match self {
            PrincipalPoint::Vggt => (w as f64 / 2.0, h as f64 / 2.0),
            PrincipalPoint::Centre => ggpt_core::camera::centred_principal_point(h, w),
        }
    }
}

impl Default for SynthConfig {
    /// 8 views of a room at 518 x 392, seed 42, [`Regime::Benchmark`].
    fn default() -> Self {
        Self::for_regime(Regime::default())
    }
}

impl SynthConfig {
    /// The default configuration of a regime: its world, feed-forward error model and matchers.
    pub fn for_regime(regime: Regime) -> Self {
        SynthConfig {
            kind: SceneKind::Room,
            views: 8,
            width: 518,
            height: 392,
            seed: 42,
            regime,
            matches: true,
            ceiling: None,
            ff_error: FfErrorModel::for_regime(regime),
            matchers: matchers_for(regime),
            principal_point: PrincipalPoint::default(),
        }
    }

    /// Checks the ranges of every parameter.
    pub fn validate(&self) -> Result<(), SynthError> {
        if self.views < VIEWS_RANGE.0 || self.views > VIEWS_RANGE.1 {
            return Err(SynthError::Config(format!(
                "views = {}, expected {}..={}",
                self.views, VIEWS_RANGE.0, VIEWS_RANGE.1
            )));
        }
        for (name, v) in [("width", self.width), ("height", self.height)] {
            if v == 0 || v % PATCH != 0 || v > 4096 {
                return Err(SynthError::Config(format!(
                    "{name} = {v}, expected a positive multiple of {PATCH} up to 4096"
                )));
            }
        }
        let mut names: Vec<&str> = self.matchers.iter().map(|m| m.name.as_str()).collect();
        names.sort_unstable();
        names.dedup();
        if names.len() != self.matchers.len() {
            return Err(SynthError::Config("matcher names must be unique".into()));
        }
        for m in &self.matchers {
            if !(0.0..=1.0).contains(&m.outlier_ratio) || m.noise_px < 0.0 || m.name.is_empty() {
                return Err(SynthError::Config(format!(
                    "matcher {:?}: outlier_ratio in [0,1], noise_px >= 0, non-empty name",
                    m.name
                )));
            }
        }
        Ok(())
    }

    /// Scene name `synth_<kind>_s<seed>`.
    pub fn scene_name(&self) -> String {
        format!("synth_{}_s{}", self.kind, self.seed)
    }
}

/// Progress stage of the ray casting (one unit per view).
pub const STAGE_RENDER: &str = "render";
/// Progress stage of the feed-forward simulation (one unit per view).
pub const STAGE_FEED_FORWARD: &str = "feed-forward";
/// Progress stage of the match simulation (one unit per matcher and view pair).
pub const STAGE_MATCHES: &str = "matches";

/// Everything [`generate`] produces.
#[derive(Debug, Clone)]
pub struct SynthOutput {
    /// The scene: images, GT, ff prediction, matches (no SfM result).
    pub scene: Scene,
    /// `S0 = [s0 R0 | s0 t0]`: GT world (metres) -> feed-forward frame.
    pub ff_from_world: Matrix3x4<f64>,
    /// GT cameras in the feed-forward frame (unperturbed).
    pub gt_cameras_ff: Cameras,
    /// `[N, h, w]` relative depth error of the ff prediction before the per-view similarity.
    pub ff_rel_depth_error: Vec<f32>,
    /// Wall-clock seconds per stage.
    pub timings: Vec<(String, f64)>,
}

/// Generates a scene. See [`generate_with_progress`].
pub fn generate(cfg: &SynthConfig) -> Result<SynthOutput, SynthError> {
    generate_with_progress(cfg, &|_| {})
}

/// Generates a scene, reporting progress by stage ([`STAGE_RENDER`], [`STAGE_FEED_FORWARD`],
/// [`STAGE_MATCHES`]); the match stage reports from several threads, hence `Sync`.
/// GT: metres, GT world frame; feed-forward: ff frame (see [`feedforward`]); matches: ff pixels.
pub fn generate_with_progress(
    cfg: &SynthConfig,
    progress: &(dyn Fn(Progress) + Sync),
) -> Result<SynthOutput, SynthError> {
    cfg.validate()?;
    let dims = Dims {
        n: cfg.views,
        h: cfg.height,
        w: cfg.width,
    };
    let mut timings = Vec::new();
    let t0 = Instant::now();
    let world = match cfg.kind {
        SceneKind::Room => world::build_room(cfg.seed, cfg.ceiling, cfg.regime),
        SceneKind::Object => world::build_object(cfg.seed, cfg.regime),
    };
    let (cam_from_world, focal) = world::place_cameras(&world, cfg.seed, cfg.views, cfg.width);
    let (cx, cy) = ggpt_core::camera::centred_principal_point(dims.h, dims.w);
    let k = Matrix3::new(focal, 0.0, cx, 0.0, focal, cy, 0.0, 0.0, 1.0);
    let gt_cams = Cameras {
        cam_from_world,
        intrinsics: vec![k; cfg.views],
    };
    let views = dims.n as u64;
    progress(Progress::new(STAGE_RENDER, 0, views));
    let render = render::render(&world, &gt_cams, dims);
    let images = render::camera_images(&render, cfg.seed);
    progress(Progress::new(STAGE_RENDER, views, views));
    timings.push(("render".to_string(), t0.elapsed().as_secs_f64()));

    let t1 = Instant::now();
    progress(Progress::new(STAGE_FEED_FORWARD, 0, views));
    let model = match cfg.kind {
        SceneKind::Room => cfg.ff_error.clone(),
        SceneKind::Object => cfg.ff_error.scaled(match cfg.regime {
            Regime::Easy => OBJECT_FF_ERROR_FACTOR,
            Regime::Benchmark => OBJECT_FF_ERROR_FACTOR_BENCHMARK,
        }),
    };
    let mut sim = feedforward::simulate_ff(&render, &gt_cams, &model, cfg.seed);
    let (ff_cx, ff_cy) = cfg.principal_point.of_image(dims.h, dims.w);
    for k in &mut sim.ff.cameras.intrinsics {
        k[(0, 2)] = ff_cx;
        k[(1, 2)] = ff_cy;
    }
    progress(Progress::new(STAGE_FEED_FORWARD, views, views));
    timings.push(("feedforward".to_string(), t1.elapsed().as_secs_f64()));

    let mut gt_points = Vec::with_capacity(3 * dims.pixels());
    for (p, q) in render.points.iter().zip(&render.prim) {
        let valid = *q != render::SKY;
        for a in 0..3 {
            gt_points.push(if valid { p[a] as f32 } else { 0.0 });
        }
    }
    let gt = GroundTruth {
        points: gt_points,
        mask: render.prim.iter().map(|q| *q != render::SKY).collect(),
        depth: Some(render.depth.iter().map(|d| *d as f32).collect()),
        cameras: gt_cams.clone(),
    };

    let t2 = Instant::now();
    let mut match_sets = Vec::new();
    if cfg.matches && !cfg.matchers.is_empty() {
        let total = (cfg.matchers.len() * dims.n * dims.n) as u64;
        progress(Progress::new(STAGE_MATCHES, 0, total));
        let ranks = matches::rank_scores(&images, dims, cfg.seed);
        let maps = cfg
            .matchers
            .iter()
            .any(matches::SceneMaps::needed_by)
            .then(|| matches::SceneMaps::new(&render, &images, |q| world.texture_period_m(q)));
        let done = std::sync::atomic::AtomicU64::new(0);
        let tick = || {
            let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            progress(Progress::new(STAGE_MATCHES, d, total));
        };
        for (i, m) in cfg.matchers.iter().enumerate() {
            match_sets.push(matches::generate_matches(
                &render,
                &gt_cams,
                m,
                i,
                cfg.seed,
                Some(ranks.clone()),
                maps.as_ref(),
                &tick,
            ));
        }
    }
    timings.push(("matches".to_string(), t2.elapsed().as_secs_f64()));

    let scene = Scene {
        name: cfg.scene_name(),
        dims,
        images,
        gt: Some(gt),
        ff: Some(sim.ff),
        sfm: None,
        matches: match_sets,
    };
    scene.validate()?;
    timings.push(("total".to_string(), t0.elapsed().as_secs_f64()));
    Ok(SynthOutput {
        scene,
        ff_from_world: sim.ff_from_world,
        gt_cameras_ff: sim.gt_cameras_ff,
        ff_rel_depth_error: sim.rel_depth_error,
        timings,
    })
}
