//! Shared helpers of the SfM fixture tests (`sfm_small`, `sfm_native_seed3`; fixtures are read
//! in place and must exist).
#![allow(dead_code)]

pub mod synth;

use std::path::PathBuf;

use ggpt_core::io::st::StFile;
use ggpt_core::{Cameras, Dims};
use ggpt_sfm::input::cameras_from_flat;
use ggpt_sfm::matches::Correspondences;

/// The default SfM fixture (principal point at the image centre).
pub const SFM_SMALL: &str = "sfm_small";
/// The SfM fixture with VGGT's native principal point `(w/2, h/2)`.
pub const SFM_NATIVE: &str = "sfm_native_seed3";

/// A file of the `sfm_small` fixture.
pub fn fixture(name: &str) -> PathBuf {
    fixture_in(SFM_SMALL, name)
}

/// A file of the fixture folder `set` (`SFM_SMALL`, `SFM_NATIVE`).
pub fn fixture_in(set: &str, name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/fixtures")
        .join(set)
        .join(name)
}

pub struct Fx {
    pub inputs: StFile,
    pub steps: StFile,
    pub dims: Dims,
}

/// The `sfm_small` fixture.
pub fn open() -> Fx {
    open_set(SFM_SMALL)
}

/// The fixture folder `set`.
pub fn open_set(set: &str) -> Fx {
    let inputs = StFile::open(&fixture_in(set, "inputs.safetensors"))
        .unwrap_or_else(|e| panic!("fixture missing: {e}"));
    let steps = StFile::open(&fixture_in(set, "steps.safetensors"))
        .unwrap_or_else(|e| panic!("fixture missing: {e}"));
    let p = inputs.f32_tensor("ff/points").unwrap();
    let dims = Dims {
        n: p.shape[0],
        h: p.shape[1],
        w: p.shape[2],
    };
    Fx {
        inputs,
        steps,
        dims,
    }
}

impl Fx {
    /// The file holding `key`: the inputs (`ff/`, `match/`, `gt/`, `config/`) or the steps.
    fn file(&self, key: &str) -> &StFile {
        if ["ff/", "match/", "gt/", "config/"]
            .iter()
            .any(|p| key.starts_with(p))
        {
            &self.inputs
        } else {
            &self.steps
        }
    }
    pub fn f32(&self, key: &str) -> Vec<f32> {
        self.file(key)
            .f32_tensor(key)
            .unwrap_or_else(|e| panic!("{e}"))
            .data
    }
    pub fn f64(&self, key: &str) -> Vec<f64> {
        self.file(key)
            .f64_tensor(key)
            .unwrap_or_else(|e| panic!("{e}"))
            .data
    }
    pub fn i64(&self, key: &str) -> Vec<i64> {
        self.steps
            .i64_tensor(key)
            .unwrap_or_else(|e| panic!("{e}"))
            .data
    }
    pub fn bool(&self, key: &str) -> Vec<bool> {
        self.steps
            .bool_tensor(key)
            .unwrap_or_else(|e| panic!("{e}"))
            .data
    }

    /// `cycle/m{m}/*` converted to the target-major layout.
    pub fn cycle_set(&self, m: usize) -> Correspondences {
        let (n, hw) = (self.dims.n, self.dims.hw());
        let pm = self.f32(&format!("cycle/m{m}/pred_matches_lr"));
        let ps = self.f32(&format!("cycle/m{m}/pred_scores"));
        let pc = self.f32(&format!("cycle/m{m}/pred_cycle_error"));
        Correspondences {
            dims: self.dims,
            matches: Correspondences::transpose_pairs(&pm, n, hw, 2).unwrap(),
            scores: Correspondences::transpose_pairs(&ps, n, hw, 1).unwrap(),
            cycle: Correspondences::transpose_pairs(&pc, n, hw, 1).unwrap(),
        }
    }

    /// The ensembled correspondences exactly as recorded (gather by `ensemble/selected_idx`).
    pub fn ensembled(&self) -> Correspondences {
        let (n, hw) = (self.dims.n, self.dims.hw());
        let sets = [self.cycle_set(0), self.cycle_set(1)];
        let sel =
            Correspondences::transpose_pairs(&self.i64("ensemble/selected_idx"), n, hw, 1).unwrap();
        let mut out = sets[0].clone();
        for i in 0..out.entries() {
            let s = &sets[sel[i] as usize];
            out.matches[2 * i] = s.matches[2 * i];
            out.matches[2 * i + 1] = s.matches[2 * i + 1];
        }
        out.scores = self.f32("ensemble/pred_scores");
        out.cycle = self.f32("ensemble/pred_cycle_error");
        out
    }

    /// The recorded official BA output cameras `ba/out_*`.
    pub fn ba_out_cameras(&self) -> Cameras {
        let e = self.f32("ba/out_extrinsics");
        let k = self.f32("ba/out_intrinsics");
        cameras_from_flat(std::path::Path::new("steps"), self.dims.n, &e, 3, &k).unwrap()
    }
}

/// Our DLT point map (`mask [N hw]`, `points [N hw 3]`, our gauge) against the fixture's
/// `scatter/*`: the number of mask differences and, over the pixels both have, the distances
/// after a least-squares similarity (the BAs fix the gauge differently), sorted ascending.
pub fn dlt_difference(fx: &Fx, mask: &[bool], points: &[f32]) -> (usize, Vec<f64>) {
    let want_mask = fx.bool("scatter/point_masks");
    let want_pts = fx.f32("scatter/points");
    let diff = mask.iter().zip(&want_mask).filter(|(a, b)| a != b).count();
    let pt = |v: &[f32], p: usize| {
        nalgebra::Point3::new(v[3 * p] as f64, v[3 * p + 1] as f64, v[3 * p + 2] as f64)
    };
    let common: Vec<usize> = (0..want_mask.len())
        .filter(|&p| mask[p] && want_mask[p])
        .collect();
    let src: Vec<_> = common.iter().map(|&p| pt(points, p)).collect();
    let tgt: Vec<_> = common.iter().map(|&p| pt(&want_pts, p)).collect();
    let sim = ggpt_core::sim3::umeyama(&src, &tgt).unwrap();
    let mut errs: Vec<f64> = src
        .iter()
        .zip(&tgt)
        .map(|(a, b)| (sim.apply(a) - b).norm())
        .collect();
    errs.sort_by(f64::total_cmp);
    (diff, errs)
}

/// Max abs difference with its index.
pub fn max_abs_diff(a: &[f32], b: &[f32]) -> (f32, usize) {
    assert_eq!(a.len(), b.len(), "length mismatch");
    let mut best = (0f32, 0usize);
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        let d = (x - y).abs();
        if d > best.0 || d.is_nan() {
            best = (d, i);
        }
    }
    best
}

/// What [`check_colmap_model`] found in a `sparse/0/` model.
#[derive(Debug, Clone)]
pub struct ColmapCheck {
    pub model: ggpt_core::io::colmap::ColmapModel,
    pub points: usize,
    /// Observations with a `POINT3D_ID` (= sum of the track lengths).
    pub observations: usize,
    /// Reprojection error of every observation (pixels), in point order then track order.
    pub errors: Vec<f64>,
    pub max_error: f64,
    pub mean_error: f64,
}

/// Reads the COLMAP model in `dir` and checks its consistency: point ids unique, every
/// `POINT3D_ID` of `images.bin` names an existing point whose track holds that
/// `(image_id, point2D_idx)`, every track element names an existing image / `POINTS2D` entry that
/// points back, every track has ≥ 2 elements in distinct images; then reprojects every point with
/// the written cameras (pixel-centre K from `to_cameras`, independently of the writer) and
/// measures the distance to each of its observations (`colmap_to_pixel`). Also checks that each
/// point's stored `ERROR` is the mean of its observations' errors (1e-6 px) and, unless
/// `allow_behind` (the DLT export has no cheirality test), that every point lies in front of
/// every camera observing it.
pub fn check_colmap_model(dir: &std::path::Path, allow_behind: bool) -> ColmapCheck {
    use ggpt_core::io::colmap::{colmap_to_pixel, read_colmap};
    use std::collections::{HashMap, HashSet};
    let model = read_colmap(dir).unwrap_or_else(|e| panic!("reading {}: {e}", dir.display()));
    let (cams, _) = model.to_cameras(dir).unwrap_or_else(|e| panic!("{e}"));
    let img_index: HashMap<u32, usize> = model
        .images
        .iter()
        .enumerate()
        .map(|(i, im)| (im.id, i))
        .collect();
    assert_eq!(img_index.len(), model.images.len(), "duplicate image ids");
    let pt_index: HashMap<u64, usize> = model
        .points3d
        .iter()
        .enumerate()
        .map(|(i, p)| (p.id, i))
        .collect();
    assert_eq!(pt_index.len(), model.points3d.len(), "duplicate point ids");
    let mut observations = 0;
    for im in &model.images {
        for (idx, p2) in im.points2d.iter().enumerate() {
            if let Some(pid) = p2.point3d_id {
                observations += 1;
                let &pi = pt_index.get(&pid).unwrap_or_else(|| {
                    panic!(
                        "image {} POINTS2D[{idx}] names point {pid}, which does not exist",
                        im.id
                    )
                });
                assert!(
                    model.points3d[pi].track.contains(&(im.id, idx as u32)),
                    "point {pid}'s track lacks (image {}, {idx})",
                    im.id
                );
            }
        }
    }
    let mut errors = Vec::new();
    for p in &model.points3d {
        assert!(
            p.track.len() >= 2,
            "point {}: track of length {}",
            p.id,
            p.track.len()
        );
        let distinct: HashSet<u32> = p.track.iter().map(|t| t.0).collect();
        assert_eq!(
            distinct.len(),
            p.track.len(),
            "point {}: two observations in one image",
            p.id
        );
        let x = nalgebra::Vector3::from(p.xyz);
        assert!(
            x.iter().all(|c| c.is_finite()),
            "point {}: non-finite",
            p.id
        );
        let mut sum = 0.0;
        for &(iid, idx) in &p.track {
            let &v = img_index
                .get(&iid)
                .unwrap_or_else(|| panic!("point {}: unknown image {iid}", p.id));
            let p2 = model.images[v]
                .points2d
                .get(idx as usize)
                .unwrap_or_else(|| panic!("point {}: image {iid} has no POINTS2D[{idx}]", p.id));
            assert_eq!(
                p2.point3d_id,
                Some(p.id),
                "point {}: image {iid} POINTS2D[{idx}] points elsewhere",
                p.id
            );
            let c = cams.rotation(v) * x + cams.translation(v);
            assert!(
                allow_behind || c.z > 0.0,
                "point {} behind camera of image {iid}",
                p.id
            );
            let k = &cams.intrinsics[v];
            let uv = [
                k[(0, 0)] * c.x / c.z + k[(0, 2)],
                k[(1, 1)] * c.y / c.z + k[(1, 2)],
            ];
            let obs = colmap_to_pixel(p2.xy);
            let e = ((uv[0] - obs[0]).powi(2) + (uv[1] - obs[1]).powi(2)).sqrt();
            sum += e;
            errors.push(e);
        }
        let mean = sum / p.track.len() as f64;
        assert!(
            (p.error - mean).abs() < 1e-6,
            "point {}: stored error {} vs recomputed {mean}",
            p.id,
            p.error
        );
    }
    let track_sum: usize = model.points3d.iter().map(|p| p.track.len()).sum();
    assert_eq!(
        observations, track_sum,
        "POINTS2D with an id vs track elements"
    );
    let max_error = errors.iter().copied().fold(0.0, f64::max);
    let mean_error = if errors.is_empty() {
        f64::NAN
    } else {
        errors.iter().sum::<f64>() / errors.len() as f64
    };
    ColmapCheck {
        points: model.points3d.len(),
        observations,
        errors,
        max_error,
        mean_error,
        model,
    }
}

/// Compares a model written from our BA (all BA tracks are candidates; the written points are
/// numbered `1, 2, ...` in BA point order, skipping the ones left out) with Ceres' run recorded
/// under `prefix` (`ba` or `ba_upstream`): every written observation's reprojection error equals
/// that of Ceres' final state under the exported cameras (`out_intrinsics`) to 5e-3 px;
/// exactly the observations Ceres leaves above 4 px or behind their camera are missing, and
/// exactly the points left with fewer than 2 observations; the written points equal
/// `final_points3D` to 1e-3 relative after a similarity (the free gauge drifts slightly
/// differently). Returns (max |Δ error| px, max relative point difference).
pub fn compare_with_ceres(fx: &Fx, chk: &ColmapCheck, prefix: &str) -> (f64, f64) {
    let want = fx.f64(&format!("{prefix}/final_points3D"));
    let cams = fx.f64(&format!("{prefix}/final_cam_from_world"));
    let k_out = fx.f32(&format!("{prefix}/out_intrinsics"));
    let (obs_pid, obs_img) = (
        fx.i64(&format!("{prefix}/obs_point3D_id")),
        fx.i64(&format!("{prefix}/obs_image_id")),
    );
    let obs_xy = fx.f64(&format!("{prefix}/obs_xy"));
    let np = want.len() / 3;
    // Ceres' final state in camera `v` of observation `o`.
    let in_cam = |o: usize| {
        let (v, p) = ((obs_img[o] - 1) as usize, (obs_pid[o] - 1) as usize);
        let m = &cams[12 * v..12 * v + 12];
        let x = &want[3 * p..3 * p + 3];
        let row =
            |r: usize| m[4 * r] * x[0] + m[4 * r + 1] * x[1] + m[4 * r + 2] * x[2] + m[4 * r + 3];
        (v, [row(0), row(1), row(2)])
    };
    let in_front = |o: usize| in_cam(o).1[2] > 0.0;
    // Its reprojection error with the exported cameras (`out_intrinsics`, the official K_sfm:
    // principal point at the image centre whatever the BA used, sfm.md §7.1), as in the model.
    let want_err: Vec<f64> = (0..obs_pid.len())
        .map(|o| {
            let (v, c) = in_cam(o);
            let k = &k_out[9 * v..9 * v + 9];
            let u = f64::from(k[0]) * c[0] / c[2] + f64::from(k[2]);
            let w = f64::from(k[4]) * c[1] / c[2] + f64::from(k[5]);
            ((u - (obs_xy[2 * o] - 0.5)).powi(2) + (w - (obs_xy[2 * o + 1] - 0.5)).powi(2)).sqrt()
        })
        .collect();
    let kept = |o: usize| want_err[o] <= 4.0 && in_front(o);
    let mut kept_per_point = vec![0usize; np + 1];
    for o in 0..want_err.len() {
        if kept(o) {
            kept_per_point[obs_pid[o] as usize] += 1;
        }
    }
    let written: Vec<usize> = (1..=np).filter(|&p| kept_per_point[p] >= 2).collect();
    let ids: Vec<usize> = chk.model.points3d.iter().map(|p| p.id as usize).collect();
    assert_eq!(
        ids,
        (1..=written.len()).collect::<Vec<_>>(),
        "written point ids (Ceres' points with 2 usable observations: {written:?})"
    );
    let mut ours = std::collections::HashMap::new();
    let mut k = 0;
    for p in &chk.model.points3d {
        let ceres_id = written[p.id as usize - 1] as i64;
        for &(iid, _) in &p.track {
            ours.insert((ceres_id, iid as i64), chk.errors[k]);
            k += 1;
        }
    }
    let mut de = 0f64;
    let mut dropped = 0;
    for o in 0..want_err.len() {
        let expected = kept(o) && kept_per_point[obs_pid[o] as usize] >= 2;
        match ours.get(&(obs_pid[o], obs_img[o])) {
            Some(e) => {
                assert!(
                    expected,
                    "observation (point {}, image {}) written, Ceres error {} (in front: {})",
                    obs_pid[o],
                    obs_img[o],
                    want_err[o],
                    in_front(o)
                );
                de = de.max((e - want_err[o]).abs());
            }
            None => {
                assert!(
                    !expected,
                    "observation (point {}, image {}) missing, Ceres error {}",
                    obs_pid[o], obs_img[o], want_err[o]
                );
                dropped += 1;
            }
        }
    }
    assert_eq!(chk.observations + dropped, want_err.len());
    let want: Vec<f64> = written
        .iter()
        .flat_map(|&p| want[3 * (p - 1)..3 * p].to_vec())
        .collect();
    let np = written.len();
    let src: Vec<_> = chk
        .model
        .points3d
        .iter()
        .map(|p| nalgebra::Point3::from(p.xyz))
        .collect();
    let tgt: Vec<_> = (0..np)
        .map(|i| nalgebra::Point3::new(want[3 * i], want[3 * i + 1], want[3 * i + 2]))
        .collect();
    let sim = ggpt_core::sim3::umeyama(&src, &tgt).unwrap();
    let scale = tgt.iter().map(|p| p.coords.norm()).sum::<f64>() / np as f64;
    let dp = src
        .iter()
        .zip(&tgt)
        .map(|(a, b)| (sim.apply(a) - b).norm())
        .fold(0.0, f64::max)
        / scale;
    assert!(
        de < 5e-3,
        "observation errors differ from Ceres' by up to {de} px"
    );
    assert!(
        dp < 1e-3,
        "BA points differ from Ceres' by up to {dp} (relative, after Sim(3))"
    );
    (de, dp)
}

/// A 3-view 56 x 42 `ggpt-synth` scene (default regime, two matchers, seed 9).
pub fn small_synthetic_scene() -> ggpt_core::Scene {
    let cfg = ggpt_synth::SynthConfig {
        views: 3,
        width: 56,
        height: 42,
        seed: 9,
        ..Default::default()
    };
    ggpt_synth::generate(&cfg).expect("synthetic scene").scene
}
