//! A small RGB canvas for figures written as PNG (the error maps, [`crate::error_maps`]): rectangles,
//! pixel blocks and text in the embedded font, with no system font lookup.
//!
//! Hand-written because the error maps are image panels with a title row and a colour bar:
//! a plotting crate would add nothing but a second copy of the panels. Text is rasterised with
//! `ab_glyph` (the font crate `plotters` uses for `ggpt-train plot`, which shares the font).

use ab_glyph::{Font, FontRef, PxScale, ScaleFont, point};

/// The embedded font: DejaVu Sans (Bitstream Vera license, `assets/LICENSE-DejaVuSans.txt`).
pub static FONT_TTF: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");

/// An RGB8 image being drawn: `[height, width, 3]` row-major bytes.
#[derive(Debug, Clone, PartialEq)]
pub struct Canvas {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// `[height, width, 3]` bytes.
    pub rgb: Vec<u8>,
}

impl Canvas {
    /// A canvas filled with `background`.
    pub fn new(width: usize, height: usize, background: [u8; 3]) -> Self {
        let mut rgb = Vec::with_capacity(3 * width * height);
        for _ in 0..width * height {
            rgb.extend_from_slice(&background);
        }
        Self { width, height, rgb }
    }

    /// Sets one pixel; outside the canvas nothing happens.
    pub fn put(&mut self, x: usize, y: usize, c: [u8; 3]) {
        if x < self.width && y < self.height {
            let i = 3 * (y * self.width + x);
            self.rgb[i..i + 3].copy_from_slice(&c);
        }
    }

    /// Fills the rectangle `[x, x + w) × [y, y + h)` (clipped to the canvas).
    pub fn fill_rect(&mut self, x: usize, y: usize, w: usize, h: usize, c: [u8; 3]) {
        for yy in y..(y + h).min(self.height) {
            for xx in x..(x + w).min(self.width) {
                self.put(xx, yy, c);
            }
        }
    }

    /// Copies a `[h, w]` block of pixels with its top left corner at `(x, y)` (clipped).
    pub fn blit(&mut self, x: usize, y: usize, w: usize, pixels: &[[u8; 3]]) {
        for (r, row) in pixels.chunks(w.max(1)).enumerate() {
            for (c, &p) in row.iter().enumerate() {
                self.put(x + c, y + r, p);
            }
        }
    }

    /// Draws `text` in the embedded font, `px` pixels high, with the top of its line box at
    /// `(x, y)`; glyph coverage blends `color` over the canvas. Returns the advance width.
    pub fn text(&mut self, x: f32, y: f32, px: f32, text: &str, color: [u8; 3]) -> f32 {
        let Ok(font) = FontRef::try_from_slice(FONT_TTF) else {
            return 0.0;
        };
        let baseline = y + font.as_scaled(PxScale::from(px)).ascent();
        let (glyphs, width) = layout(&font, px, text);
        for (id, pen) in glyphs {
            let glyph = id.with_scale_and_position(px, point(x + pen, baseline));
            let Some(outline) = font.outline_glyph(glyph) else {
                continue;
            };
            let bounds = outline.px_bounds();
            outline.draw(|gx, gy, coverage| {
                let (px_x, px_y) = (bounds.min.x + gx as f32, bounds.min.y + gy as f32);
                if px_x < 0.0 || px_y < 0.0 {
                    return;
                }
                let (xx, yy) = (px_x as usize, px_y as usize);
                if xx >= self.width || yy >= self.height {
                    return;
                }
                let i = 3 * (yy * self.width + xx);
                let a = coverage.clamp(0.0, 1.0);
                for (dst, &src) in self.rgb[i..i + 3].iter_mut().zip(&color) {
                    let under = f32::from(*dst);
                    *dst = (under + a * (f32::from(src) - under)).round() as u8;
                }
            });
        }
        width
    }

    /// The advance width of `text` at `px` (what [`Self::text`] returns), for centring.
    pub fn text_width(px: f32, text: &str) -> f32 {
        match FontRef::try_from_slice(FONT_TTF) {
            Ok(font) => layout(&font, px, text).1,
            Err(_) => 0.0,
        }
    }
}

/// Horizontal layout of `text` at `px`: each glyph with its pen offset from the start (kerning
/// included), and the total advance width.
fn layout(font: &FontRef<'_>, px: f32, text: &str) -> (Vec<(ab_glyph::GlyphId, f32)>, f32) {
    let scaled = font.as_scaled(PxScale::from(px));
    let mut pen = 0.0;
    let mut previous = None;
    let mut glyphs = Vec::with_capacity(text.len());
    for ch in text.chars() {
        let id = scaled.glyph_id(ch);
        if let Some(p) = previous {
            pen += scaled.kern(p, id);
        }
        glyphs.push((id, pen));
        pen += scaled.h_advance(id);
        previous = Some(id);
    }
    (glyphs, pen)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_draws_ink_inside_its_box_only() {
        let mut c = Canvas::new(120, 30, [255, 255, 255]);
        let w = c.text(4.0, 4.0, 16.0, "AUC 5 cm", [0, 0, 0]);
        assert!((w - Canvas::text_width(16.0, "AUC 5 cm")).abs() < 1e-3);
        assert!(w > 40.0 && w < 100.0, "{w}");
        let dark: Vec<(usize, usize)> = (0..30)
            .flat_map(|y| (0..120).map(move |x| (x, y)))
            .filter(|&(x, y)| c.rgb[3 * (y * 120 + x)] < 128)
            .collect();
        assert!(dark.len() > 50, "{} dark pixels", dark.len());
        assert!(
            dark.iter()
                .all(|&(x, y)| x >= 3 && (x as f32) <= 5.0 + w && (3..25).contains(&y))
        );
    }

    #[test]
    fn rectangles_and_blits_clip() {
        let mut c = Canvas::new(4, 3, [0, 0, 0]);
        c.fill_rect(2, 1, 10, 10, [9, 9, 9]);
        c.blit(3, 2, 2, &[[1, 2, 3], [4, 5, 6], [7, 8, 9], [1, 1, 1]]);
        assert_eq!(&c.rgb[3 * (4 + 2)..3 * (4 + 2) + 3], &[9, 9, 9]);
        assert_eq!(&c.rgb[3 * (2 * 4 + 3)..3 * (2 * 4 + 3) + 3], &[1, 2, 3]);
        assert_eq!(&c.rgb[0..3], &[0, 0, 0]);
    }
}
