//! Per-view PNG error maps (colour-mapped point errors, like the paper's qualitative figures).
//!
//! One file per view, `error_maps/view_{i:03}.png`, three panels side by side at ff
//! resolution: the input image, the error of the feed-forward points and the error of the
//! refined points (both after their own Sim(3) alignment to the GT, `pipeline.md` §10.2).
//! Errors are clamped to `[0, max_cm]` and colour-mapped with Turbo (blue = 0, red = `max_cm`);
//! pixels without valid GT are dark grey.

use std::path::PathBuf;

use ggpt_core::Dims;
use ggpt_core::metrics::PointEvaluation;
use ggpt_scene::export::{Rgb8Image, RunOutput};

use crate::{InferError, Result};

/// Default upper end of the colour scale (cm).
pub const DEFAULT_ERROR_MAP_MAX_CM: f64 = 10.0;
/// Colour of pixels without ground truth.
const NO_GT_COLOR: [u8; 3] = [40, 40, 40];

/// Turbo colour map (polynomial approximation by Google, max error < 1 %) at `t ∈ [0, 1]`.
pub fn turbo(t: f64) -> [u8; 3] {
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        1.0
    };
    let (t2, t3, t4, t5) = (t * t, t * t * t, t.powi(4), t.powi(5));
    let r = 0.13572138 + 4.61539260 * t - 42.66032258 * t2 + 132.13108234 * t3 - 152.94239396 * t4
        + 59.28637943 * t5;
    let g = 0.09140261 + 2.19418839 * t + 4.84296658 * t2 - 14.18503333 * t3
        + 4.27729857 * t4
        + 2.82956604 * t5;
    let b = 0.10667330 + 12.64194608 * t - 60.58204836 * t2 + 110.36276771 * t3 - 89.90310912 * t4
        + 27.34824973 * t5;
    [r, g, b].map(|v| (255.0 * v.clamp(0.0, 1.0)).round() as u8)
}

/// Per-pixel error panel of one view from a [`PointEvaluation`] (errors listed over its mask in
/// pixel order).
fn error_image(ev: &PointEvaluation, dims: Dims, max_cm: f64) -> Result<Vec<[u8; 3]>> {
    let px = dims.pixels();
    if ev.mask.len() != px {
        return Err(InferError::Invalid(format!(
            "error map: evaluation mask has {} pixels, expected {px}",
            ev.mask.len()
        )));
    }
    let mut out = vec![NO_GT_COLOR; px];
    let mut errors = ev.errors_cm.iter();
    for (p, _) in ev.mask.iter().enumerate().filter(|(_, m)| **m) {
        let e = errors.next().ok_or_else(|| {
            InferError::Invalid("error map: fewer errors than evaluated pixels".into())
        })?;
        if let Some(o) = out.get_mut(p) {
            *o = turbo(e / max_cm);
        }
    }
    Ok(out)
}

/// Writes the error maps of [`render_error_maps`] through the run's output writer
/// (`error_maps/view_{i:03}.png`, [`RunOutput::write_error_maps`]). Returns the files written.
pub fn write_error_maps(
    out: &mut RunOutput,
    dims: Dims,
    images: &[f32],
    ff: &PointEvaluation,
    refined: &PointEvaluation,
    max_cm: f64,
) -> Result<Vec<PathBuf>> {
    let maps = render_error_maps(dims, images, ff, refined, max_cm)?;
    Ok(out.write_error_maps(&maps)?)
}

/// One RGB image per view, three panels side by side: image | feed-forward error | refined
/// error (`[h, 3 w, 3]`). `images` is `[N, h, w, 3]` in `[0, 1]`.
pub fn render_error_maps(
    dims: Dims,
    images: &[f32],
    ff: &PointEvaluation,
    refined: &PointEvaluation,
    max_cm: f64,
) -> Result<Vec<Rgb8Image>> {
    if images.len() != 3 * dims.pixels() {
        return Err(InferError::Invalid(format!(
            "error map: {} image values for {} pixels",
            images.len(),
            dims.pixels()
        )));
    }
    if max_cm.is_nan() || max_cm <= 0.0 {
        return Err(InferError::Invalid(format!(
            "error map: colour scale maximum must be > 0 cm, got {max_cm}"
        )));
    }
    let a = error_image(ff, dims, max_cm)?;
    let b = error_image(refined, dims, max_cm)?;
    let (h, w) = (dims.h, dims.w);
    let mut maps = Vec::with_capacity(dims.n);
    for v in 0..dims.n {
        let mut rgb = Vec::with_capacity(3 * 3 * w * h);
        for y in 0..h {
            let row = dims.index(v, y, 0);
            for x in 0..w {
                let p = row + x;
                rgb.extend(
                    images[3 * p..3 * p + 3]
                        .iter()
                        .map(|&c| ggpt_scene::export::color_u8(c)),
                );
            }
            for panel in [&a, &b] {
                for x in 0..w {
                    rgb.extend(panel[row + x]);
                }
            }
        }
        maps.push(Rgb8Image {
            width: 3 * w,
            height: h,
            rgb,
        });
    }
    Ok(maps)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ggpt_core::sim3::{AlignInfo, AlignMethod, Sim3};

    #[test]
    fn turbo_endpoints_and_clamping() {
        assert_eq!(turbo(0.0), [35, 23, 27]); // 255 x (0.1357, 0.0914, 0.1067)
        let red = turbo(1.0);
        assert!(red[0] > 100 && red[2] < 30, "{red:?}");
        let mid = turbo(0.5);
        assert!(mid[1] > 200, "{mid:?}"); // green-ish in the middle
        assert_eq!(turbo(-3.0), turbo(0.0));
        assert_eq!(turbo(f64::NAN), turbo(1.0));
    }

    #[test]
    fn writes_three_panel_pngs() {
        let dims = Dims { n: 2, h: 3, w: 4 };
        let px = dims.pixels();
        let mask: Vec<bool> = (0..px).map(|p| p % 5 != 0).collect();
        let errors: Vec<f64> = mask
            .iter()
            .filter(|m| **m)
            .enumerate()
            .map(|(i, _)| i as f64)
            .collect();
        let ev = PointEvaluation {
            metrics: serde_json::from_value(serde_json::json!({
                "num_points": 0, "recall_pct": [], "auc_1": 0.0, "auc_3": 0.0, "auc_5": 0.0, "auc_10": 0.0,
                "mean_cm": 0.0, "median_cm": 0.0, "ratio": null, "align": {"method": "identity"}, "align_inliers": null,
                "gt_from_pred": [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]
            }))
            .unwrap(),
            sim3: Sim3::identity(),
            align: AlignInfo { method: AlignMethod::Identity, thresholds_tried: vec![], inliers: None, num_inliers: None },
            errors_cm: errors,
            mask,
        };
        let dir = tempfile::tempdir().unwrap();
        let mut out = RunOutput::create(dir.path()).unwrap();
        let images = vec![0.5f32; 3 * px];
        let files = write_error_maps(&mut out, dims, &images, &ev, &ev, 10.0).unwrap();
        assert_eq!(files.len(), 2);
        let img = image::open(&files[1]).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (12, 3));
        // View 1, pixel (y 0, x 0) is p = 12 -> mask true (12 % 5 != 0); panel 2 starts at x = 4.
        assert_eq!(img.get_pixel(0, 0).0, [127, 127, 127]);
        assert_eq!(img.get_pixel(4, 0).0, img.get_pixel(8, 0).0);
        // p = 15 (view 1, y 0, x 3) has no GT -> grey.
        assert_eq!(img.get_pixel(4 + 3, 0).0, NO_GT_COLOR);
        assert!(write_error_maps(&mut out, dims, &images[1..], &ev, &ev, 10.0).is_err());
        assert!(write_error_maps(&mut out, dims, &images, &ev, &ev, 0.0).is_err());
    }
}
