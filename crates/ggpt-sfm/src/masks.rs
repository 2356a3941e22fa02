//! BA and DLT masks and the threshold presets (`sfm.md` §5).
//!
//! `M_BA[t,s,k] = score > τ_BA_score && cycle < τ_BA_cycle`, `M_DLT` likewise with the DLT
//! thresholds; strict comparisons in **f32** (the thresholds are rounded to f32 first, as the
//! official f32-tensor-vs-Python-float comparison does); diagonal entries are always true.

use crate::error::{Result, SfmError};
use crate::matches::Correspondences;

/// Named threshold presets of `sfm.md` §5.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Preset {
    /// `benchmark_sfm.yaml` (default of the evaluation commands).
    Benchmark,
    /// `demo.yaml` (default of the user-facing inference command).
    Demo,
    /// The official README recipe for more than 50 views.
    ManyViews,
}

impl Preset {
    /// Parses `benchmark`, `demo` or `many-views`.
    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "benchmark" => Ok(Preset::Benchmark),
            "demo" => Ok(Preset::Demo),
            "many-views" => Ok(Preset::ManyViews),
            other => Err(SfmError::Invalid(format!(
                "unknown preset {other:?} (benchmark, demo, many-views)"
            ))),
        }
    }

    /// The preset's name.
    pub fn name(self) -> &'static str {
        match self {
            Preset::Benchmark => "benchmark",
            Preset::Demo => "demo",
            Preset::ManyViews => "many-views",
        }
    }
}

/// Thresholds of the filtering stages (`sfm.md` §5 table). Scores are matcher confidences,
/// cycle / epipolar / reprojection errors in ff pixels, angles in degrees.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Thresholds {
    /// `τ_BA_score`: BA correspondences need `score > this`.
    pub ba_score: f64,
    /// `τ_BA_cycle` (px): BA correspondences need `cycle < this`.
    pub ba_cycle: f64,
    /// BA tracks per view (`mintrack_per_view`, §6.1).
    pub mintrack_per_view: usize,
    /// `τ_DLT_score`.
    pub dlt_score: f64,
    /// `τ_DLT_cycle` (px).
    pub dlt_cycle: f64,
    /// Max epipolar error (px, §8).
    pub max_epipolar_error: f64,
    /// Min triangulation angle (degrees, §9.3).
    pub min_tri_angle_deg: f64,
    /// Max mean reprojection error (px, §9.3).
    pub max_reproj_error: f64,
}

impl Thresholds {
    /// The values of a preset (`sfm.md` §5; values in parentheses there are inherited from demo).
    pub fn preset(p: Preset) -> Self {
        match p {
            Preset::Benchmark => Thresholds {
                ba_score: 0.6,
                ba_cycle: 2.0,
                mintrack_per_view: 2048,
                dlt_score: 0.1,
                dlt_cycle: 4.0,
                max_epipolar_error: 4.0,
                min_tri_angle_deg: 3.0,
                max_reproj_error: 4.0,
            },
            Preset::Demo => Thresholds {
                ba_score: 0.6,
                ba_cycle: 2.0,
                mintrack_per_view: 2048,
                dlt_score: 0.4,
                dlt_cycle: 2.0,
                max_epipolar_error: 2.0,
                min_tri_angle_deg: 5.0,
                max_reproj_error: 2.0,
            },
            Preset::ManyViews => Thresholds {
                ba_score: 0.8,
                ba_cycle: 1.0,
                mintrack_per_view: 512,
                dlt_score: 0.4,
                dlt_cycle: 1.0,
                max_epipolar_error: 2.0,
                min_tri_angle_deg: 7.0,
                max_reproj_error: 1.0,
            },
        }
    }

    /// Rejects NaN thresholds.
    pub fn validate(&self) -> Result<()> {
        let vals = [
            ("ba_score", self.ba_score),
            ("ba_cycle", self.ba_cycle),
            ("dlt_score", self.dlt_score),
            ("dlt_cycle", self.dlt_cycle),
            ("max_epipolar_error", self.max_epipolar_error),
            ("min_tri_angle_deg", self.min_tri_angle_deg),
            ("max_reproj_error", self.max_reproj_error),
        ];
        for (name, v) in vals {
            if v.is_nan() {
                return Err(SfmError::Invalid(format!("threshold {name} is NaN")));
            }
        }
        Ok(())
    }
}

/// `score > score_thr && cycle < cycle_thr` with both thresholds rounded to f32 (strict).
#[inline]
pub fn passes(score: f32, cycle: f32, score_thr: f32, cycle_thr: f32) -> bool {
    score > score_thr && cycle < cycle_thr
}

/// The BA and DLT masks (`[t, s, k]`, target-major like `corr`), diagonal forced true.
pub fn compute_masks(corr: &Correspondences, thr: &Thresholds) -> Result<(Vec<bool>, Vec<bool>)> {
    corr.validate()?;
    thr.validate()?;
    let (bs, bc) = (thr.ba_score as f32, thr.ba_cycle as f32);
    let (ds, dc) = (thr.dlt_score as f32, thr.dlt_cycle as f32);
    let mut m_ba: Vec<bool> = corr
        .scores
        .iter()
        .zip(&corr.cycle)
        .map(|(&s, &c)| passes(s, c, bs, bc))
        .collect();
    let mut m_dlt: Vec<bool> = corr
        .scores
        .iter()
        .zip(&corr.cycle)
        .map(|(&s, &c)| passes(s, c, ds, dc))
        .collect();
    let hw = corr.dims.hw();
    for s in 0..corr.dims.n {
        let b = corr.idx(s, s, 0);
        m_ba[b..b + hw].iter_mut().for_each(|v| *v = true);
        m_dlt[b..b + hw].iter_mut().for_each(|v| *v = true);
    }
    Ok((m_ba, m_dlt))
}

#[cfg(test)]
mod tests {
    use super::*;
    use ggpt_core::Dims;

    #[test]
    fn f32_strict_comparison() {
        // a score of exactly f32(0.6) fails `> 0.6` in f32 (it would pass in f64)
        assert!(!passes(0.6f32, 0.0, 0.6f64 as f32, 2.0));
        assert!((0.6f32 as f64) > 0.6);
        assert!(passes(0.6000001f32, 1.9999, 0.6, 2.0));
        assert!(!passes(0.9, 2.0, 0.6, 2.0));
        assert!(!passes(f32::NAN, 0.0, 0.6, 2.0));
    }

    #[test]
    fn diagonal_always_true_and_presets() {
        let dims = Dims { n: 2, h: 1, w: 2 };
        let e = 8;
        let corr = Correspondences {
            dims,
            matches: vec![0.0; 2 * e],
            scores: vec![0.0; e],
            cycle: vec![1e6; e],
        };
        let (ba, dlt) = compute_masks(&corr, &Thresholds::preset(Preset::Benchmark)).unwrap();
        let diag: Vec<bool> = (0..e).map(|i| ba[i] && dlt[i]).collect();
        assert_eq!(
            diag,
            vec![true, true, false, false, false, false, true, true]
        );
        let mv = Thresholds::preset(Preset::ManyViews);
        assert_eq!(
            (
                mv.ba_score,
                mv.ba_cycle,
                mv.mintrack_per_view,
                mv.min_tri_angle_deg
            ),
            (0.8, 1.0, 512, 7.0)
        );
        let demo = Thresholds::preset(Preset::Demo);
        assert_eq!(
            (demo.dlt_score, demo.dlt_cycle, demo.max_reproj_error),
            (0.4, 2.0, 2.0)
        );
        assert_eq!(Preset::parse("many-views").unwrap(), Preset::ManyViews);
        assert!(Preset::parse("fast").is_err());
    }
}
