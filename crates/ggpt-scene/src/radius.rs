//! Scene radius `R` (`pipeline.md` §4): the length unit of the chunk size.
//!
//! Computed on the **aligned** dense points (SfM frame, scene units). Two rules:
//!
//! * [`RadiusRule::AcrossViews`] (official, default): `R = 3 · mean_{y,x,a} std_n(X_d[n,y,x,a])`,
//!   the unbiased standard deviation **across views** of each pixel location and axis.
//! * [`RadiusRule::Pooled`]: `R = 3 · mean_a std_p(X_d[p,a])` over all pixels `p` (or those of a
//!   region-of-interest mask `F`), unbiased. The official code uses it whenever a mask `F`
//!   exists (Tanks and Temples, 4D-DRESS evaluation).
//!
//! With `N = 1` the across-view std is undefined (the official code gets NaN and refines
//! nothing); the project then uses the pooled rule (**[project]**).
//! Statistics are accumulated in `f64` and rounded to `f32` where the official torch code holds
//! `f32` tensors (per-element std, their mean), which reproduces the official `R` bit-exactly.

use ggpt_core::Dims;

use crate::error::{SceneError, check_len};

/// Factor applied to the mean standard deviation (`pipeline.md` §4).
pub const RADIUS_STD_FACTOR: f64 = 3.0;

/// Which rule defines the scene radius (`chunking.radius_rule`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RadiusRule {
    /// Official rule: std across views per pixel and axis, averaged.
    #[default]
    AcrossViews,
    /// Per-axis std over all (masked) points, averaged.
    Pooled,
}

/// The radius and the rule that actually produced it.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct SceneRadius {
    /// `R` in scene units (SfM frame).
    pub radius: f64,
    /// Rule used (may differ from the requested one: a mask forces [`RadiusRule::Pooled`], as does `N = 1`).
    pub rule: RadiusRule,
}

/// Computes the scene radius of the aligned dense points `points` (`[N, h, w, 3]` flat, pixel
/// order, SfM frame). `roi` is the optional region-of-interest mask `F` (`[N, h, w]`); when given,
/// the pooled rule over the masked points is used (official behaviour). With `N = 1` and the
/// across-view rule, the pooled rule over all pixels (or `F`) is used instead.
///
/// Errors: array sizes not matching `dims`, fewer than 2 points for a pooled std, a non-finite
/// or negative result.
pub fn scene_radius(
    points: &[f32],
    dims: Dims,
    rule: RadiusRule,
    roi: Option<&[bool]>,
) -> Result<SceneRadius, SceneError> {
    let px = dims.pixels();
    check_len("radius: points", points.len(), 3 * px)?;
    if let Some(f) = roi {
        check_len("radius: region-of-interest mask", f.len(), px)?;
    }
    let effective = if roi.is_some() || dims.n < 2 {
        RadiusRule::Pooled
    } else {
        rule
    };
    let radius = match effective {
        RadiusRule::AcrossViews => across_views(points, dims),
        RadiusRule::Pooled => pooled(points, roi)?,
    };
    if !radius.is_finite() || radius < 0.0 {
        return Err(SceneError::Numeric(format!(
            "scene radius is {radius} ({effective:?} rule)"
        )));
    }
    Ok(SceneRadius {
        radius,
        rule: effective,
    })
}

/// `3 · mean_{y,x,a} std_n` (unbiased, `N ≥ 2`), emulating the official torch arithmetic on an
/// `f32` tensor: each std accumulated in `f64` and stored as `f32`, their mean rounded to `f32`
/// (accumulated here in `f64`), then `× 3` in `f64`.
fn across_views(points: &[f32], dims: Dims) -> f64 {
    let hw3 = 3 * dims.hw();
    let n = dims.n as f64;
    let mut total = 0.0f64;
    for i in 0..hw3 {
        let vals = (0..dims.n).filter_map(|v| points.get(v * hw3 + i).map(|&x| f64::from(x)));
        let mean = vals.clone().sum::<f64>() / n;
        let ss: f64 = vals.map(|x| (x - mean) * (x - mean)).sum();
        total += f64::from((ss / (n - 1.0)).sqrt() as f32);
    }
    RADIUS_STD_FACTOR * f64::from((total / hw3 as f64) as f32)
}

/// `3 · mean_a std_p` over the (masked) points, unbiased (torch arithmetic, see below).
fn pooled(points: &[f32], roi: Option<&[bool]>) -> Result<f64, SceneError> {
    let keep = |p: usize| roi.is_none_or(|f| f.get(p).copied().unwrap_or(false));
    let mut count = 0usize;
    let mut sum = [0.0f64; 3];
    for (p, x) in points.chunks_exact(3).enumerate() {
        if keep(p) {
            count += 1;
            for a in 0..3 {
                sum[a] += f64::from(x[a]);
            }
        }
    }
    if count < 2 {
        return Err(SceneError::Numeric(format!(
            "scene radius: {count} point(s) in the region of interest, need at least 2"
        )));
    }
    let mean = sum.map(|s| s / count as f64);
    let mut ss = [0.0f64; 3];
    for (p, x) in points.chunks_exact(3).enumerate() {
        if keep(p) {
            for a in 0..3 {
                let d = f64::from(x[a]) - mean[a];
                ss[a] += d * d;
            }
        }
    }
    // torch: per-axis std accumulated in f64 and stored as f32, mean of the three f32 values in
    // f32, `.item() * 3` in f64.
    let std: [f32; 3] = ss.map(|s| (s / (count as f64 - 1.0)).sqrt() as f32);
    let mean = ((std[0] + std[1]) + std[2]) / 3.0f32;
    Ok(RADIUS_STD_FACTOR * f64::from(mean))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_util::Fixture;

    #[test]
    fn fixture_radius_across_views() {
        let steps = Fixture::sfm_steps();
        let aligned = steps.f32("sim3/ff_aligned");
        let want = steps.f64("sim3/radius")[0];
        let dims = Dims { n: 4, h: 42, w: 56 };
        let r = scene_radius(&aligned, dims, RadiusRule::AcrossViews, None).unwrap();
        assert_eq!(r.rule, RadiusRule::AcrossViews);
        // Bit-exact with the official torch computation.
        assert_eq!(r.radius, want, "R = {} want {want}", r.radius);
        assert!((want - 0.9789148271).abs() < 1e-9);
    }

    #[test]
    fn hand_computed_across_views_and_pooled() {
        // N = 2, one pixel: values (0,0,0) and (2,4,6): std across views = sqrt(2), 2 sqrt(2), 3 sqrt(2).
        let dims = Dims { n: 2, h: 1, w: 1 };
        let pts = [0.0, 0.0, 0.0, 2.0, 4.0, 6.0];
        let r = scene_radius(&pts, dims, RadiusRule::AcrossViews, None).unwrap();
        assert!((r.radius - 3.0 * 2.0 * 2f64.sqrt()).abs() < 1e-6);
        // Pooled over the same two points gives the same here (two samples per axis).
        let p = scene_radius(&pts, dims, RadiusRule::Pooled, None).unwrap();
        assert!((p.radius - r.radius).abs() < 1e-6);
        // Two views, two pixels: across-view std differs from pooled std.
        let dims = Dims { n: 2, h: 1, w: 2 };
        let pts = [
            0.0, 0.0, 0.0, 10.0, 10.0, 10.0, 1.0, 1.0, 1.0, 11.0, 11.0, 11.0,
        ];
        let a = scene_radius(&pts, dims, RadiusRule::AcrossViews, None).unwrap();
        assert!(
            (a.radius - 3.0 * 2f64.sqrt().recip()).abs() < 1e-6,
            "{}",
            a.radius
        );
        let p = scene_radius(&pts, dims, RadiusRule::Pooled, None).unwrap();
        // per axis values 0,10,1,11: mean 5.5, ss = 30.25+20.25+20.25+30.25 = 101, var = 101/3
        assert!(
            (p.radius - 3.0 * (101.0f64 / 3.0).sqrt()).abs() < 1e-5,
            "{}",
            p.radius
        );
    }

    #[test]
    fn mask_forces_pooled_and_single_view_falls_back() {
        let dims = Dims { n: 2, h: 1, w: 2 };
        let pts = [
            0.0, 0.0, 0.0, 100.0, 100.0, 100.0, 1.0, 1.0, 1.0, 11.0, 11.0, 11.0,
        ];
        let roi = [true, false, true, false];
        let r = scene_radius(&pts, dims, RadiusRule::AcrossViews, Some(&roi)).unwrap();
        assert_eq!(r.rule, RadiusRule::Pooled);
        assert!((r.radius - 3.0 * 0.5f64.sqrt()).abs() < 1e-6);
        let dims1 = Dims { n: 1, h: 1, w: 2 };
        let r1 = scene_radius(&pts[..6], dims1, RadiusRule::AcrossViews, None).unwrap();
        assert_eq!(r1.rule, RadiusRule::Pooled);
        assert!((r1.radius - 3.0 * 5000f64.sqrt()).abs() < 1e-4);
        // One point only: error, not NaN.
        let one = Dims { n: 1, h: 1, w: 1 };
        assert!(scene_radius(&pts[..3], one, RadiusRule::Pooled, None).is_err());
        // Wrong length.
        assert!(scene_radius(&pts[..5], dims1, RadiusRule::Pooled, None).is_err());
    }
}
