//! Shared helpers of the `sfm_small` fixture tests (fixtures are read in place and must exist).
#![allow(dead_code)]

pub mod synth;

use std::path::PathBuf;

use ggpt_core::{Cameras, Dims};
use ggpt_sfm::input::cameras_from_flat;
use ggpt_sfm::matches::Correspondences;
use ggpt_sfm::st::StFile;

pub fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/fixtures/sfm_small").join(name)
}

pub struct Fx {
    pub inputs: StFile,
    pub steps: StFile,
    pub dims: Dims,
}

pub fn open() -> Fx {
    let inputs = StFile::open(&fixture("inputs.safetensors")).unwrap_or_else(|e| panic!("fixture missing: {e}"));
    let steps = StFile::open(&fixture("steps.safetensors")).unwrap_or_else(|e| panic!("fixture missing: {e}"));
    let p = inputs.f32("ff/points").unwrap();
    let dims = Dims { n: p.shape[0], h: p.shape[1], w: p.shape[2] };
    Fx { inputs, steps, dims }
}

impl Fx {
    pub fn f32(&self, key: &str) -> Vec<f32> {
        let f = if key.starts_with("ff/") || key.starts_with("match/") || key.starts_with("gt/") || key.starts_with("config/") { &self.inputs } else { &self.steps };
        f.f32(key).unwrap_or_else(|e| panic!("{e}")).data
    }
    pub fn f64(&self, key: &str) -> Vec<f64> {
        self.steps.f64(key).unwrap_or_else(|e| panic!("{e}")).data
    }
    pub fn i64(&self, key: &str) -> Vec<i64> {
        self.steps.i64(key).unwrap_or_else(|e| panic!("{e}")).data
    }
    pub fn bool(&self, key: &str) -> Vec<bool> {
        self.steps.bool(key).unwrap_or_else(|e| panic!("{e}")).data
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
        let sel = Correspondences::transpose_pairs(&self.i64("ensemble/selected_idx"), n, hw, 1).unwrap();
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
