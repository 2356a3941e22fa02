//! Per-view PNG error maps (colour-mapped point errors, like the paper's qualitative figures).
//!
//! One file per view, `error_maps/view_{i:03}.png`: a title row, four panels side by side at ff
//! resolution, and a colour bar with its cm scale:
//!
//! ```text
//! | input image | feed-forward error | SfM / DLT points | GGPT refined error |
//! [ turbo colour bar 0 .. max_cm, ticks in cm ]
//! ```
//!
//! Each point set is Sim(3)-aligned to the GT on its own (`pipeline.md` §10.2); the SfM panel
//! shows the error of the SfM points where they exist, i.e. their coverage. All three error
//! panels share one scale: errors clamped to `[0, max_cm]`, Turbo colours (blue = 0, red =
//! `max_cm`). Pixels without GT (or, in the SfM panel, without an SfM point) are dark grey.

use ggpt_core::Dims;
use ggpt_core::metrics::PointEvaluation;
use image::RgbImage;

use crate::figure::Canvas;
use crate::{EvalError, Result};

/// Default upper end of the colour scale (cm).
pub const DEFAULT_ERROR_MAP_MAX_CM: f64 = 10.0;
/// Colour of pixels without ground truth (or without an SfM point in the SfM panel).
const NO_GT_COLOR: [u8; 3] = [40, 40, 40];
/// Background of the title row and the colour-bar strip.
const PAPER: [u8; 3] = [255, 255, 255];
/// Text colour.
const INK: [u8; 3] = [25, 25, 25];
/// Height of the title row (pixels).
const TITLE_H: usize = 22;
/// Height of the colour bar strip (bar + tick labels).
const BAR_STRIP_H: usize = 34;
/// Height of the colour bar itself.
const BAR_H: usize = 10;
/// Gap between panels.
const GAP: usize = 4;
/// Font size of titles and tick labels.
const TEXT_PX: f32 = 13.0;

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

/// Per-pixel error panel of all views from a [`PointEvaluation`] (errors listed over its mask
/// in pixel order).
fn error_image(ev: &PointEvaluation, dims: Dims, max_cm: f64) -> Result<Vec<[u8; 3]>> {
    let px = dims.pixels();
    if ev.mask.len() != px {
        return Err(EvalError::Invalid(format!(
            "error map: evaluation mask has {} pixels, expected {px}",
            ev.mask.len()
        )));
    }
    let mut out = vec![NO_GT_COLOR; px];
    let mut errors = ev.errors_cm.iter();
    for (p, _) in ev.mask.iter().enumerate().filter(|(_, m)| **m) {
        let e = errors.next().ok_or_else(|| {
            EvalError::Invalid("error map: fewer errors than evaluated pixels".into())
        })?;
        if let Some(o) = out.get_mut(p) {
            *o = turbo(e / max_cm);
        }
    }
    Ok(out)
}

/// The point sets of one error map: feed-forward, SfM (optional: a scene whose SfM points
/// could not be evaluated has an empty panel) and refined, each with its evaluation.
#[derive(Debug, Clone, Copy)]
pub struct ErrorMapInputs<'a> {
    /// Feed-forward points.
    pub ff: &'a PointEvaluation,
    /// SfM / DLT points on the pixels they cover.
    pub sfm: Option<&'a PointEvaluation>,
    /// Refined points.
    pub refined: &'a PointEvaluation,
}

/// Tick step of the colour bar for a scale of `max_cm`: 1, 2 or 5 × 10^k, about 5 ticks.
fn tick_step(max_cm: f64) -> f64 {
    let raw = max_cm / 5.0;
    let mag = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * mag)
        .find(|&s| s >= raw)
        .unwrap_or(10.0 * mag)
}

/// `{v}` without a trailing `.0` for whole numbers.
fn tick_label(v: f64) -> String {
    if (v - v.round()).abs() < 1e-9 {
        format!("{}", v.round() as i64)
    } else {
        format!("{v:.1}")
    }
}

/// `text` shortened (from the end) until it fits a panel of `w` pixels with a 2-pixel margin.
fn fit(text: &str, w: usize) -> String {
    let mut t = text.to_string();
    while !t.is_empty() && Canvas::text_width(TEXT_PX, &t) > w as f32 - 4.0 {
        t.pop();
    }
    t
}

/// One RGB image per view (`[TITLE_H + h + BAR_STRIP_H, 4 w + 3 GAP, 3]`): titles, then
/// image | feed-forward error | SfM points | refined error, then the colour bar with its cm
/// ticks. `images` is `[N, h, w, 3]` in `[0, 1]`.
pub fn render_error_maps(
    dims: Dims,
    images: &[f32],
    inputs: ErrorMapInputs<'_>,
    max_cm: f64,
) -> Result<Vec<RgbImage>> {
    if images.len() != 3 * dims.pixels() {
        return Err(EvalError::Invalid(format!(
            "error map: {} image values for {} pixels",
            images.len(),
            dims.pixels()
        )));
    }
    if max_cm.is_nan() || max_cm <= 0.0 {
        return Err(EvalError::Invalid(format!(
            "error map: colour scale maximum must be > 0 cm, got {max_cm}"
        )));
    }
    let ff = error_image(inputs.ff, dims, max_cm)?;
    let refined = error_image(inputs.refined, dims, max_cm)?;
    let sfm = match inputs.sfm {
        Some(ev) => error_image(ev, dims, max_cm)?,
        None => vec![NO_GT_COLOR; dims.pixels()],
    };
    let auc = |ev: &PointEvaluation| format!("AUC@5 {:.1}", ev.metrics.auc_5);
    let titles = [
        "input image".to_string(),
        format!("feed-forward error, {}", auc(inputs.ff)),
        match inputs.sfm {
            Some(ev) => format!(
                "SfM points, {:.1} % of pixels",
                100.0 * ev.metrics.ratio.unwrap_or(0.0)
            ),
            None => "SfM points: none evaluated".to_string(),
        },
        format!("GGPT refined error, {}", auc(inputs.refined)),
    ];
    let (h, w) = (dims.h, dims.w);
    let width = 4 * w + 3 * GAP;
    let height = TITLE_H + h + BAR_STRIP_H;
    let mut maps = Vec::with_capacity(dims.n);
    for v in 0..dims.n {
        let mut canvas = Canvas::new(width, height, PAPER);
        let first = dims.index(v, 0, 0);
        let view = first..first + h * w;
        let image: Vec<[u8; 3]> = images[3 * view.start..3 * view.end]
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]].map(ggpt_core::color::color_u8))
            .collect();
        for (k, (panel, title)) in [
            &image[..],
            &ff[view.clone()],
            &sfm[view.clone()],
            &refined[view.clone()],
        ]
        .into_iter()
        .zip(&titles)
        .enumerate()
        {
            let x0 = k * (w + GAP);
            canvas.blit(x0, TITLE_H, w, panel);
            canvas.text(x0 as f32 + 2.0, 4.0, TEXT_PX, &fit(title, w), INK);
        }
        // the colour bar under the three error panels, with ticks in cm
        let (bar_x, bar_w) = (w + GAP, 3 * w + 2 * GAP);
        let bar_y = TITLE_H + h + 4;
        for x in 0..bar_w {
            let c = turbo(x as f64 / (bar_w.max(2) - 1) as f64);
            canvas.fill_rect(bar_x + x, bar_y, 1, BAR_H, c);
        }
        let step = tick_step(max_cm);
        let mut t = 0.0;
        while t <= max_cm + 1e-9 {
            let x = bar_x + ((t / max_cm) * (bar_w - 1) as f64).round() as usize;
            canvas.fill_rect(x, bar_y + BAR_H, 1, 3, INK);
            let label = if t + step > max_cm + 1e-9 {
                format!("{} cm", tick_label(t))
            } else {
                tick_label(t)
            };
            let lw = Canvas::text_width(TEXT_PX, &label);
            // centred on its tick, kept inside the bar where it fits (no clamp: a label wider
            // than a tiny bar would make its bounds cross)
            let lx = (x as f32 - lw / 2.0)
                .min((bar_x + bar_w) as f32 - lw)
                .max(bar_x as f32);
            canvas.text(lx, (bar_y + BAR_H + 3) as f32, TEXT_PX, &label, INK);
            t += step;
        }
        canvas.text(
            2.0,
            (bar_y - 2) as f32,
            TEXT_PX,
            &fit("point error", w),
            INK,
        );
        let image = u32::try_from(width)
            .ok()
            .zip(u32::try_from(height).ok())
            .and_then(|(w, h)| RgbImage::from_raw(w, h, canvas.rgb))
            .ok_or_else(|| EvalError::Invalid(format!("error map: {width}x{height} too large")))?;
        maps.push(image);
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
    fn renders_four_panels_with_titles_and_a_colour_bar() {
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
        let images = vec![0.5f32; 3 * px];
        let inputs = ErrorMapInputs {
            ff: &ev,
            sfm: Some(&ev),
            refined: &ev,
        };
        let maps = render_error_maps(dims, &images, inputs, 10.0).unwrap();
        assert_eq!(maps.len(), 2);
        let img = &maps[1];
        let (w, h) = (dims.w as u32, dims.h as u32);
        let pw = w + GAP as u32;
        assert_eq!(
            img.dimensions(),
            (
                4 * w + 3 * GAP as u32,
                TITLE_H as u32 + h + BAR_STRIP_H as u32
            )
        );
        let y0 = TITLE_H as u32;
        // View 1, pixel (y 0, x 0) is p = 12 -> mask true (12 % 5 != 0).
        assert_eq!(img.get_pixel(0, y0).0, [127, 127, 127]);
        // the three error panels share one scale
        assert_eq!(img.get_pixel(pw, y0).0, img.get_pixel(3 * pw, y0).0);
        assert_eq!(img.get_pixel(pw, y0).0, img.get_pixel(2 * pw, y0).0);
        // p = 15 (view 1, y 0, x 3) has no GT -> grey.
        assert_eq!(img.get_pixel(pw + 3, y0).0, NO_GT_COLOR);
        // the colour bar runs from turbo(0) to turbo(1) under the error panels
        let bar_y = y0 + h + 4;
        assert_eq!(img.get_pixel(pw, bar_y).0, turbo(0.0));
        assert_eq!(
            img.get_pixel(4 * w + 3 * GAP as u32 - 1, bar_y).0,
            turbo(1.0)
        );
        // no SfM evaluation: an empty SfM panel
        let maps = render_error_maps(
            dims,
            &images,
            ErrorMapInputs {
                sfm: None,
                ..inputs
            },
            10.0,
        )
        .unwrap();
        assert_eq!(maps[1].get_pixel(2 * pw, y0).0, NO_GT_COLOR);
        assert!(render_error_maps(dims, &images[1..], inputs, 10.0).is_err());
        assert!(render_error_maps(dims, &images, inputs, 0.0).is_err());
    }

    #[test]
    fn colour_bar_ticks() {
        assert_eq!(tick_step(10.0), 2.0);
        assert_eq!(tick_step(5.0), 1.0);
        assert_eq!(tick_step(30.0), 10.0);
        assert_eq!(tick_step(0.5), 0.1);
        assert_eq!(tick_label(4.0), "4");
        assert_eq!(tick_label(0.5), "0.5");
    }
}
