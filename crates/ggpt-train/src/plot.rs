//! A tiny line-plot renderer for the training curve (PNG through the `image` crate): no text
//! rendering, so axes ranges are returned for the caption and written into the docs.

use std::path::Path;

use crate::error::{Result, TrainError};

/// One series: `(x, y)` points and an RGB colour.
#[derive(Debug, Clone)]
pub struct Series {
    /// Points.
    pub points: Vec<(f64, f64)>,
    /// Colour.
    pub rgb: [u8; 3],
}

/// Plot extents `(x_min, x_max, y_min, y_max)` used for the axes.
pub type Extents = (f64, f64, f64, f64);

/// Draws `series` into a `width x height` PNG (white background, grey frame and 4 horizontal
/// grid lines, linear axes over the data range) and returns the extents.
pub fn plot_png(path: &Path, series: &[Series], width: u32, height: u32) -> Result<Extents> {
    let pts = series.iter().flat_map(|s| s.points.iter()).filter(|(x, y)| x.is_finite() && y.is_finite());
    let (mut x0, mut x1, mut y0, mut y1) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
    for &(x, y) in pts {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    if !(x0.is_finite() && y0.is_finite()) {
        return Err(TrainError::Invalid("plot: no finite point".into()));
    }
    if x1 <= x0 {
        x1 = x0 + 1.0;
    }
    if y1 <= y0 {
        y1 = y0 + 1.0;
    }
    let margin = 20i64;
    let (w, h) = (width as i64, height as i64);
    let mut img = image::RgbImage::from_pixel(width, height, image::Rgb([255, 255, 255]));
    let put = |img: &mut image::RgbImage, x: i64, y: i64, c: [u8; 3]| {
        if x >= 0 && y >= 0 && x < w && y < h {
            img.put_pixel(x as u32, y as u32, image::Rgb(c));
        }
    };
    let grey = [200, 200, 200];
    for k in 0..=4 {
        let y = margin + (h - 2 * margin) * k / 4;
        for x in margin..=w - margin {
            put(&mut img, x, y, grey);
        }
    }
    for y in margin..=h - margin {
        put(&mut img, margin, y, grey);
        put(&mut img, w - margin, y, grey);
    }
    let map = |x: f64, y: f64| {
        let px = margin as f64 + (x - x0) / (x1 - x0) * (w - 2 * margin) as f64;
        let py = (h - margin) as f64 - (y - y0) / (y1 - y0) * (h - 2 * margin) as f64;
        (px.round() as i64, py.round() as i64)
    };
    for s in series {
        let mut prev: Option<(i64, i64)> = None;
        for &(x, y) in s.points.iter().filter(|(x, y)| x.is_finite() && y.is_finite()) {
            let p = map(x, y);
            if let Some(q) = prev {
                let n = (p.0 - q.0).abs().max((p.1 - q.1).abs()).max(1);
                for i in 0..=n {
                    let xx = q.0 + (p.0 - q.0) * i / n;
                    let yy = q.1 + (p.1 - q.1) * i / n;
                    put(&mut img, xx, yy, s.rgb);
                    put(&mut img, xx, yy + 1, s.rgb);
                }
            } else {
                put(&mut img, p.0, p.1, s.rgb);
            }
            prev = Some(p);
        }
    }
    img.save(path).map_err(|e| TrainError::Invalid(format!("{}: {e}", path.display())))?;
    Ok((x0, x1, y0, y1))
}

/// Moving average over `window` points (for noisy per-step losses).
pub fn smooth(points: &[(f64, f64)], window: usize) -> Vec<(f64, f64)> {
    let w = window.max(1);
    (0..points.len())
        .map(|i| {
            let a = i.saturating_sub(w - 1);
            let ys = &points[a..=i];
            (points[i].0, ys.iter().map(|p| p.1).sum::<f64>() / ys.len() as f64)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plots_and_smooths() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.png");
        let s = Series { points: (0..50).map(|i| (i as f64, 1.0 / (1.0 + i as f64))).collect(), rgb: [255, 0, 0] };
        let e = plot_png(&p, &[s], 200, 100).unwrap();
        assert_eq!(e.0, 0.0);
        assert_eq!(e.1, 49.0);
        let img = image::open(&p).unwrap().to_rgb8();
        assert!(img.pixels().any(|px| px.0 == [255, 0, 0]));
        let sm = smooth(&[(0.0, 0.0), (1.0, 2.0), (2.0, 4.0)], 2);
        assert_eq!(sm, vec![(0.0, 0.0), (1.0, 1.0), (2.0, 3.0)]);
    }
}
