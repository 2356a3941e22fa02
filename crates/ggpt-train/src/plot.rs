//! The training-curve figure: PNG line plots through the `image` crate, with a built-in 5x7
//! bitmap font (no font crate) for titles, axis titles, "nice" tick values and legends.
//!
//! * [`draw_text`] / [`draw_text_up`]: ASCII text at an integer scale (unknown characters are
//!   drawn as a box).
//! * [`nice_ticks`]: 4–6 tick values on a 1/2/5 × 10^k grid.
//! * [`plot_png`]: one labelled panel of arbitrary series.
//! * [`read_metrics`] + [`write_figure`]: the `ggpt-train plot` figure of a `metrics.jsonl`,
//!   training loss on top and held-out AUC@5/10 below, sharing the step axis.

use std::path::Path;

use image::{Rgb, RgbImage};

use crate::error::{Result, TrainError, io_err};

// ---------------------------------------------------------------------------------------------
// Bitmap font
// ---------------------------------------------------------------------------------------------

/// Glyph width in font pixels.
pub const GLYPH_W: i64 = 5;
/// Glyph height above the baseline (cap height) in font pixels.
pub const GLYPH_H: i64 = 7;
/// Rows below the baseline (descenders of `g j p q y , ;`).
pub const DESCENT: i64 = 2;
/// Rows of a glyph in the table: [`GLYPH_H`] + [`DESCENT`].
pub const GLYPH_ROWS: usize = 9;
/// Horizontal advance per character in font pixels (glyph + 1 column of spacing).
pub const ADVANCE: i64 = 6;

/// Glyph drawn for characters outside the table: a hollow box.
pub const BOX_GLYPH: [u8; GLYPH_ROWS] = [0x1F, 0x11, 0x11, 0x11, 0x11, 0x11, 0x1F, 0x00, 0x00];

/// 5x7 glyphs of printable ASCII `' '..='~'` (plus two descender rows), row-major from the
/// top; bit 4 is the leftmost column.
const FONT: [[u8; GLYPH_ROWS]; 95] = [
    [0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00], // ' '
    [0x04, 0x04, 0x04, 0x04, 0x04, 0x00, 0x04, 0x00, 0x00], // !
    [0x0A, 0x0A, 0x0A, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00], // "
    [0x0A, 0x0A, 0x1F, 0x0A, 0x1F, 0x0A, 0x0A, 0x00, 0x00], // #
    [0x04, 0x0F, 0x14, 0x0E, 0x05, 0x1E, 0x04, 0x00, 0x00], // $
    [0x18, 0x19, 0x02, 0x04, 0x08, 0x13, 0x03, 0x00, 0x00], // %
    [0x0C, 0x12, 0x14, 0x08, 0x15, 0x12, 0x0D, 0x00, 0x00], // &
    [0x0C, 0x04, 0x08, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00], // '
    [0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02, 0x00, 0x00], // (
    [0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08, 0x00, 0x00], // )
    [0x00, 0x04, 0x15, 0x0E, 0x15, 0x04, 0x00, 0x00, 0x00], // *
    [0x00, 0x04, 0x04, 0x1F, 0x04, 0x04, 0x00, 0x00, 0x00], // +
    [0x00, 0x00, 0x00, 0x00, 0x00, 0x0C, 0x0C, 0x04, 0x08], // ,
    [0x00, 0x00, 0x00, 0x1F, 0x00, 0x00, 0x00, 0x00, 0x00], // -
    [0x00, 0x00, 0x00, 0x00, 0x00, 0x0C, 0x0C, 0x00, 0x00], // .
    [0x00, 0x01, 0x02, 0x04, 0x08, 0x10, 0x00, 0x00, 0x00], // /
    [0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E, 0x00, 0x00], // 0
    [0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E, 0x00, 0x00], // 1
    [0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F, 0x00, 0x00], // 2
    [0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E, 0x00, 0x00], // 3
    [0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02, 0x00, 0x00], // 4
    [0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E, 0x00, 0x00], // 5
    [0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E, 0x00, 0x00], // 6
    [0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08, 0x00, 0x00], // 7
    [0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E, 0x00, 0x00], // 8
    [0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C, 0x00, 0x00], // 9
    [0x00, 0x0C, 0x0C, 0x00, 0x0C, 0x0C, 0x00, 0x00, 0x00], // :
    [0x00, 0x00, 0x0C, 0x0C, 0x00, 0x0C, 0x0C, 0x04, 0x08], // ;
    [0x02, 0x04, 0x08, 0x10, 0x08, 0x04, 0x02, 0x00, 0x00], // <
    [0x00, 0x00, 0x1F, 0x00, 0x1F, 0x00, 0x00, 0x00, 0x00], // =
    [0x08, 0x04, 0x02, 0x01, 0x02, 0x04, 0x08, 0x00, 0x00], // >
    [0x0E, 0x11, 0x01, 0x02, 0x04, 0x00, 0x04, 0x00, 0x00], // ?
    [0x0E, 0x11, 0x01, 0x0D, 0x15, 0x15, 0x0E, 0x00, 0x00], // @
    [0x0E, 0x11, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x00, 0x00], // A
    [0x1E, 0x11, 0x11, 0x1E, 0x11, 0x11, 0x1E, 0x00, 0x00], // B
    [0x0E, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0E, 0x00, 0x00], // C
    [0x1C, 0x12, 0x11, 0x11, 0x11, 0x12, 0x1C, 0x00, 0x00], // D
    [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x1F, 0x00, 0x00], // E
    [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x10, 0x00, 0x00], // F
    [0x0E, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0F, 0x00, 0x00], // G
    [0x11, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11, 0x00, 0x00], // H
    [0x0E, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E, 0x00, 0x00], // I
    [0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0C, 0x00, 0x00], // J
    [0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11, 0x00, 0x00], // K
    [0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1F, 0x00, 0x00], // L
    [0x11, 0x1B, 0x15, 0x15, 0x11, 0x11, 0x11, 0x00, 0x00], // M
    [0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11, 0x00, 0x00], // N
    [0x0E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E, 0x00, 0x00], // O
    [0x1E, 0x11, 0x11, 0x1E, 0x10, 0x10, 0x10, 0x00, 0x00], // P
    [0x0E, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0D, 0x00, 0x00], // Q
    [0x1E, 0x11, 0x11, 0x1E, 0x14, 0x12, 0x11, 0x00, 0x00], // R
    [0x0F, 0x10, 0x10, 0x0E, 0x01, 0x01, 0x1E, 0x00, 0x00], // S
    [0x1F, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04, 0x00, 0x00], // T
    [0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E, 0x00, 0x00], // U
    [0x11, 0x11, 0x11, 0x11, 0x11, 0x0A, 0x04, 0x00, 0x00], // V
    [0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0A, 0x00, 0x00], // W
    [0x11, 0x11, 0x0A, 0x04, 0x0A, 0x11, 0x11, 0x00, 0x00], // X
    [0x11, 0x11, 0x11, 0x0A, 0x04, 0x04, 0x04, 0x00, 0x00], // Y
    [0x1F, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1F, 0x00, 0x00], // Z
    [0x0E, 0x08, 0x08, 0x08, 0x08, 0x08, 0x0E, 0x00, 0x00], // [
    [0x00, 0x10, 0x08, 0x04, 0x02, 0x01, 0x00, 0x00, 0x00], // \
    [0x0E, 0x02, 0x02, 0x02, 0x02, 0x02, 0x0E, 0x00, 0x00], // ]
    [0x04, 0x0A, 0x11, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00], // ^
    [0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x1F, 0x00, 0x00], // _
    [0x08, 0x04, 0x02, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00], // `
    [0x00, 0x00, 0x0E, 0x01, 0x0F, 0x11, 0x0F, 0x00, 0x00], // a
    [0x10, 0x10, 0x16, 0x19, 0x11, 0x11, 0x1E, 0x00, 0x00], // b
    [0x00, 0x00, 0x0E, 0x10, 0x10, 0x11, 0x0E, 0x00, 0x00], // c
    [0x01, 0x01, 0x0D, 0x13, 0x11, 0x11, 0x0F, 0x00, 0x00], // d
    [0x00, 0x00, 0x0E, 0x11, 0x1F, 0x10, 0x0E, 0x00, 0x00], // e
    [0x06, 0x09, 0x08, 0x1C, 0x08, 0x08, 0x08, 0x00, 0x00], // f
    [0x00, 0x00, 0x0F, 0x11, 0x11, 0x11, 0x0F, 0x01, 0x0E], // g
    [0x10, 0x10, 0x16, 0x19, 0x11, 0x11, 0x11, 0x00, 0x00], // h
    [0x04, 0x00, 0x0C, 0x04, 0x04, 0x04, 0x0E, 0x00, 0x00], // i
    [0x02, 0x00, 0x06, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0C], // j
    [0x10, 0x10, 0x12, 0x14, 0x18, 0x14, 0x12, 0x00, 0x00], // k
    [0x0C, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E, 0x00, 0x00], // l
    [0x00, 0x00, 0x1A, 0x15, 0x15, 0x11, 0x11, 0x00, 0x00], // m
    [0x00, 0x00, 0x16, 0x19, 0x11, 0x11, 0x11, 0x00, 0x00], // n
    [0x00, 0x00, 0x0E, 0x11, 0x11, 0x11, 0x0E, 0x00, 0x00], // o
    [0x00, 0x00, 0x1E, 0x11, 0x11, 0x11, 0x1E, 0x10, 0x10], // p
    [0x00, 0x00, 0x0F, 0x11, 0x11, 0x11, 0x0F, 0x01, 0x01], // q
    [0x00, 0x00, 0x16, 0x19, 0x10, 0x10, 0x10, 0x00, 0x00], // r
    [0x00, 0x00, 0x0E, 0x10, 0x0E, 0x01, 0x1E, 0x00, 0x00], // s
    [0x08, 0x08, 0x1C, 0x08, 0x08, 0x09, 0x06, 0x00, 0x00], // t
    [0x00, 0x00, 0x11, 0x11, 0x11, 0x13, 0x0D, 0x00, 0x00], // u
    [0x00, 0x00, 0x11, 0x11, 0x11, 0x0A, 0x04, 0x00, 0x00], // v
    [0x00, 0x00, 0x11, 0x11, 0x15, 0x15, 0x0A, 0x00, 0x00], // w
    [0x00, 0x00, 0x11, 0x0A, 0x04, 0x0A, 0x11, 0x00, 0x00], // x
    [0x00, 0x00, 0x11, 0x11, 0x11, 0x11, 0x0F, 0x01, 0x0E], // y
    [0x00, 0x00, 0x1F, 0x02, 0x04, 0x08, 0x1F, 0x00, 0x00], // z
    [0x02, 0x04, 0x04, 0x08, 0x04, 0x04, 0x02, 0x00, 0x00], // {
    [0x04, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04, 0x00, 0x00], // |
    [0x08, 0x04, 0x04, 0x02, 0x04, 0x04, 0x08, 0x00, 0x00], // }
    [0x00, 0x00, 0x08, 0x15, 0x02, 0x00, 0x00, 0x00, 0x00], // ~
];

/// Whether `c` has its own glyph (printable ASCII); other characters render as [`BOX_GLYPH`].
pub fn is_supported(c: char) -> bool {
    (' '..='~').contains(&c)
}

/// The 5x7 glyph of `c` (rows from the top, then the descender rows; bit 4 = leftmost
/// column); [`BOX_GLYPH`] for characters outside printable ASCII.
pub fn glyph(c: char) -> [u8; GLYPH_ROWS] {
    if is_supported(c) { FONT[c as usize - ' ' as usize] } else { BOX_GLYPH }
}

/// Width in image pixels of `text` at `scale` (no trailing spacing column).
pub fn text_width(text: &str, scale: u32) -> i64 {
    let n = text.chars().count() as i64;
    if n == 0 { 0 } else { (n * ADVANCE - 1) * scale as i64 }
}

/// Height in image pixels of one text line at `scale` above the baseline (descenders reach
/// [`DESCENT`] font pixels lower).
pub fn text_height(scale: u32) -> i64 {
    GLYPH_H * scale as i64
}

/// `text`, shortened with ".." at the end when wider than `max_w` pixels at `scale`.
pub fn fit_text(text: &str, max_w: i64, scale: u32) -> String {
    if text_width(text, scale) <= max_w {
        return text.to_string();
    }
    let n = ((max_w / scale.max(1) as i64 + 1) / ADVANCE).max(2) as usize;
    text.chars().take(n - 2).chain("..".chars()).collect()
}

/// Sets one pixel, ignoring coordinates outside the image.
fn put(img: &mut RgbImage, x: i64, y: i64, rgb: [u8; 3]) {
    if x >= 0 && y >= 0 && x < img.width() as i64 && y < img.height() as i64 {
        img.put_pixel(x as u32, y as u32, Rgb(rgb));
    }
}

/// Fills the inclusive rectangle `[x0, x1] x [y0, y1]` (clipped to the image).
fn fill(img: &mut RgbImage, x0: i64, y0: i64, x1: i64, y1: i64, rgb: [u8; 3]) {
    for y in y0..=y1 {
        for x in x0..=x1 {
            put(img, x, y, rgb);
        }
    }
}

/// Calls `set(tx, ty)` for every lit pixel of `text` in text space (`tx` to the right, `ty`
/// down, in image pixels at `scale`).
fn for_text_pixels(text: &str, scale: u32, mut set: impl FnMut(i64, i64)) {
    let s = scale.max(1) as i64;
    for (i, c) in text.chars().enumerate() {
        let g = glyph(c);
        for (row, bits) in g.iter().enumerate() {
            for col in 0..GLYPH_W {
                if bits & (0x10 >> col) != 0 {
                    let (gx, gy) = ((i as i64 * ADVANCE + col) * s, row as i64 * s);
                    for dy in 0..s {
                        for dx in 0..s {
                            set(gx + dx, gy + dy);
                        }
                    }
                }
            }
        }
    }
}

/// Draws `text` with its top-left corner at `(x, y)`, every font pixel a `scale x scale`
/// square; returns the drawn width ([`text_width`]). Pixels outside the image are dropped.
pub fn draw_text(img: &mut RgbImage, x: i64, y: i64, text: &str, rgb: [u8; 3], scale: u32) -> i64 {
    for_text_pixels(text, scale, |tx, ty| put(img, x + tx, y + ty, rgb));
    text_width(text, scale)
}

/// Draws `text` rotated 90° counter-clockwise (reading bottom to top, as a y-axis title): the
/// text starts at `(x, y)` = bottom-left corner of the rotated box and extends upwards; the
/// box is [`text_height`] wide. Returns the drawn length.
pub fn draw_text_up(img: &mut RgbImage, x: i64, y: i64, text: &str, rgb: [u8; 3], scale: u32) -> i64 {
    for_text_pixels(text, scale, |tx, ty| put(img, x + ty, y - tx, rgb));
    text_width(text, scale)
}

// ---------------------------------------------------------------------------------------------
// Ticks
// ---------------------------------------------------------------------------------------------

/// Index range `(first, last)` of the multiples of `step` inside `[lo, hi]` (with a tiny
/// tolerance so that end points on the grid count).
fn tick_range(lo: f64, hi: f64, step: f64) -> (i64, i64) {
    ((lo / step - 1e-9).ceil() as i64, (hi / step + 1e-9).floor() as i64)
}

/// The smallest step on the 1/2/5 × 10^k grid with at most `max_ticks` multiples inside
/// `[lo, hi]`.
pub fn nice_step(lo: f64, hi: f64, max_ticks: usize) -> f64 {
    let span = (hi - lo).abs().max(f64::MIN_POSITIVE * 1e10);
    let max_ticks = max_ticks.max(2) as i64;
    let mut e = (span / max_ticks as f64).log10().floor() as i32 - 1;
    loop {
        for m in [1.0, 2.0, 5.0] {
            let s = m * 10f64.powi(e);
            let (a, b) = tick_range(lo, hi, s);
            if b - a + 1 <= max_ticks {
                return s;
            }
        }
        e += 1;
    }
}

/// "Nice" tick values inside `[lo, hi]`: the multiples of [`nice_step`] (at most `max_ticks`),
/// e.g. `0.27..0.83` → 0.3, 0.4, …, 0.8 and `0..600` → 0, 200, 400, 600 for `max_ticks = 6`.
pub fn nice_ticks(lo: f64, hi: f64, max_ticks: usize) -> Vec<f64> {
    if !(lo.is_finite() && hi.is_finite()) || hi < lo {
        return Vec::new();
    }
    let s = nice_step(lo, hi, max_ticks);
    let (a, b) = tick_range(lo, hi, s);
    (a..=b).map(|i| i as f64 * s).collect()
}

/// Number of decimals to print the multiples of `step` exactly.
fn tick_decimals(step: f64) -> usize {
    if step >= 1.0 { 0 } else { (-step.log10() - 1e-9).ceil().max(0.0) as usize }
}

/// Formats a tick value with `decimals` decimals (no "-0").
fn format_tick(v: f64, decimals: usize) -> String {
    let s = format!("{v:.decimals$}");
    if s.starts_with('-') && s[1..].chars().all(|c| c == '0' || c == '.') { s[1..].to_string() } else { s }
}

/// A linear axis: displayed range, tick values and their labels.
#[derive(Debug, Clone)]
pub struct Axis {
    /// Lower end of the displayed range.
    pub lo: f64,
    /// Upper end of the displayed range.
    pub hi: f64,
    /// Tick values (inside `[lo, hi]`).
    pub ticks: Vec<f64>,
    /// Tick labels.
    pub labels: Vec<String>,
}

impl Axis {
    /// An axis over `[lo, hi]` with 4–6 nice ticks where possible: when fewer than 4 multiples
    /// of the step fall inside the range, the range grows by one step at the cheaper end (at
    /// most twice). A degenerate range is widened around its value.
    pub fn new(lo: f64, hi: f64) -> Axis {
        let (mut lo, mut hi) = (lo, hi);
        if hi - lo <= f64::EPSILON * lo.abs().max(hi.abs()).max(1.0) * 16.0 {
            let d = (lo.abs() * 0.05).max(0.5);
            lo -= d;
            hi += d;
        }
        let mut step = nice_step(lo, hi, 6);
        let count = |lo: f64, hi: f64, s: f64| {
            let (a, b) = tick_range(lo, hi, s);
            b - a + 1
        };
        for _ in 0..2 {
            if count(lo, hi, step) >= 4 {
                break;
            }
            let (a, b) = tick_range(lo, hi, step);
            let (lo_ext, hi_ext) = ((a - 1) as f64 * step, (b + 1) as f64 * step);
            if lo - lo_ext <= hi_ext - hi {
                lo = lo_ext;
            } else {
                hi = hi_ext;
            }
        }
        if count(lo, hi, step) < 4 {
            step = nice_step(lo, hi, 8);
        }
        let (a, b) = tick_range(lo, hi, step);
        let ticks: Vec<f64> = (a..=b).map(|i| i as f64 * step).collect();
        let d = tick_decimals(step);
        let labels = ticks.iter().map(|&t| format_tick(t, d)).collect();
        Axis { lo, hi, ticks, labels }
    }

    /// [`Axis::new`] over the data range `[lo, hi]` padded by `pad` of its span on each side.
    pub fn padded(lo: f64, hi: f64, pad: f64) -> Axis {
        let d = (hi - lo) * pad;
        Axis::new(lo - d, hi + d)
    }
}

// ---------------------------------------------------------------------------------------------
// Series and panels
// ---------------------------------------------------------------------------------------------

/// One series: `(x, y)` points (non-finite ones are skipped) and its style.
#[derive(Debug, Clone)]
pub struct Series {
    /// Points.
    pub points: Vec<(f64, f64)>,
    /// Colour.
    pub rgb: [u8; 3],
    /// Line thickness in pixels.
    pub thickness: u32,
    /// Dashed line.
    pub dashed: bool,
    /// Square marker at every point.
    pub markers: bool,
    /// Legend label (no legend entry when empty).
    pub label: String,
}

impl Series {
    /// A solid 2-pixel line without label.
    pub fn line(points: Vec<(f64, f64)>, rgb: [u8; 3]) -> Series {
        Series { points, rgb, thickness: 2, dashed: false, markers: false, label: String::new() }
    }
    /// With line thickness `t`.
    pub fn thickness(mut self, t: u32) -> Series {
        self.thickness = t.max(1);
        self
    }
    /// Dashed.
    pub fn dashed(mut self) -> Series {
        self.dashed = true;
        self
    }
    /// With point markers.
    pub fn markers(mut self) -> Series {
        self.markers = true;
        self
    }
    /// With a legend label.
    pub fn label(mut self, l: impl Into<String>) -> Series {
        self.label = l.into();
        self
    }
    fn finite(&self) -> impl Iterator<Item = (f64, f64)> + '_ {
        self.points.iter().copied().filter(|(x, y)| x.is_finite() && y.is_finite())
    }
}

/// Plot extents `(x_min, x_max, y_min, y_max)` of the finite data points.
pub type Extents = (f64, f64, f64, f64);

/// Data extents of `series` (finite points only); `None` without any.
pub fn extents(series: &[Series]) -> Option<Extents> {
    let (mut x0, mut x1, mut y0, mut y1) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
    for (x, y) in series.iter().flat_map(|s| s.finite()) {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    x0.is_finite().then_some((x0, x1, y0, y1))
}

/// Inclusive pixel rectangle of a plot area.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rect {
    /// Left column.
    pub x0: i64,
    /// Top row.
    pub y0: i64,
    /// Right column.
    pub x1: i64,
    /// Bottom row.
    pub y1: i64,
}

impl Rect {
    /// Whether `(x, y)` lies inside.
    pub fn contains(&self, x: i64, y: i64) -> bool {
        x >= self.x0 && x <= self.x1 && y >= self.y0 && y <= self.y1
    }
}

/// Text colour.
const INK: [u8; 3] = [30, 30, 30];
/// Axis frame and tick colour.
const FRAME: [u8; 3] = [90, 90, 90];
/// Grid line colour.
const GRID: [u8; 3] = [228, 228, 228];
/// Length of a tick mark outside the frame.
const TICK_LEN: i64 = 5;
/// Length of a line sample in the legend.
const LEGEND_SAMPLE: i64 = 30;
/// Gap between a legend sample and its label, in font pixels.
const LEGEND_GAP: i64 = 4;

/// Text of one panel (all optional).
#[derive(Debug, Clone, Default)]
pub struct PanelText {
    /// Title line above the plot.
    pub title: Option<String>,
    /// Title under the x axis.
    pub x_title: Option<String>,
    /// Title left of the y axis (rotated).
    pub y_title: Option<String>,
}

/// One-segment brush: a `t x t` square centred on `(x, y)`, clipped to `clip`.
fn brush(img: &mut RgbImage, clip: &Rect, x: i64, y: i64, t: i64, rgb: [u8; 3]) {
    let a = -(t - 1) / 2;
    for dy in a..a + t {
        for dx in a..a + t {
            if clip.contains(x + dx, y + dy) {
                put(img, x + dx, y + dy, rgb);
            }
        }
    }
}

/// Draws the polyline `pts` (pixel coordinates) with the style of `s` (thickness, dashes along
/// the walked length, markers at the vertices), clipped to `clip`.
fn polyline(img: &mut RgbImage, clip: &Rect, pts: &[(i64, i64)], s: &Series) {
    let t = s.thickness.max(1) as i64;
    let (on, period) = (9 + 2 * t, 15 + 3 * t);
    let mut walked = 0i64;
    if let [p] = pts {
        brush(img, clip, p.0, p.1, t, s.rgb);
    }
    for w in pts.windows(2) {
        let (q, p) = (w[0], w[1]);
        let n = (p.0 - q.0).abs().max((p.1 - q.1).abs()).max(1);
        for i in 0..=n {
            if i > 0 {
                walked += 1;
            }
            if s.dashed && walked % period >= on {
                continue;
            }
            let x = q.0 + ((p.0 - q.0) as f64 * i as f64 / n as f64).round() as i64;
            let y = q.1 + ((p.1 - q.1) as f64 * i as f64 / n as f64).round() as i64;
            brush(img, clip, x, y, t, s.rgb);
        }
    }
    if s.markers {
        let m = t + 4;
        for p in pts {
            brush(img, clip, p.0, p.1, m, s.rgb);
        }
    }
}

/// Layout of the legend entries of `series` within `width` pixels: rows of `(x offset, index)`.
fn legend_rows(series: &[Series], width: i64, scale: u32) -> Vec<Vec<(i64, usize)>> {
    let gap = 10 * scale as i64;
    let mut rows: Vec<Vec<(i64, usize)>> = Vec::new();
    let mut x = 0i64;
    for (i, s) in series.iter().enumerate().filter(|(_, s)| !s.label.is_empty()) {
        let w = LEGEND_SAMPLE + LEGEND_GAP * scale as i64 + text_width(&s.label, scale);
        if rows.is_empty() || (x > 0 && x + w > width) {
            rows.push(Vec::new());
            x = 0;
        }
        rows.last_mut().expect("row").push((x, i));
        x += w + gap;
    }
    rows
}

/// Total width of one legend row.
fn legend_row_width(series: &[Series], row: &[(i64, usize)], scale: u32) -> i64 {
    row.last().map_or(0, |&(x, i)| x + LEGEND_SAMPLE + LEGEND_GAP * scale as i64 + text_width(&series[i].label, scale))
}

/// Left margin (image left to plot area) that fits the y-axis title and the tick labels.
fn left_margin(axes: &[&Axis], has_y_title: bool, scale: u32) -> i64 {
    let label_w = axes.iter().flat_map(|a| a.labels.iter()).map(|l| text_width(l, scale)).max().unwrap_or(0);
    let title = if has_y_title { text_height(scale) + 6 * scale as i64 } else { 0 };
    4 * scale as i64 + title + label_w + 4 * scale as i64 + TICK_LEN
}

/// Draws one panel into the band `top..top + height` of `img`: title line with the legend
/// (right-aligned on the title line when it fits, else on rows of its own), grid at the
/// ticks, frame, tick marks and labels, axis titles and the series. Returns the plot area.
#[allow(clippy::too_many_arguments)]
fn draw_panel(
    img: &mut RgbImage,
    top: i64,
    height: i64,
    left: i64,
    right: i64,
    x_axis: &Axis,
    y_axis: &Axis,
    series: &[Series],
    text: &PanelText,
    scale: u32,
) -> Rect {
    let sc = scale as i64;
    let th = text_height(scale);
    let line = th + (DESCENT + 3) * sc;
    let plot_w = right - left;
    // title + legend
    let mut y = top + 5 * sc;
    // a title wider than the plot starts further left and, if still too wide, is shortened
    let title_w = text.title.as_deref().map_or(0, |t| {
        let title_x = if text_width(t, scale) <= plot_w { left } else { (right - text_width(t, scale)).max(4 * sc) };
        let t = fit_text(t, right - title_x, scale);
        draw_text(img, title_x, y, &t, INK, scale) - (left - title_x)
    });
    let rows = legend_rows(series, plot_w, scale);
    let one_row_w = if rows.len() == 1 { legend_row_width(series, &rows[0], scale) } else { i64::MAX };
    let legend_on_title = text.title.is_some() && rows.len() == 1 && title_w + 16 * sc + one_row_w <= plot_w;
    let mut legend_at: Vec<(i64, i64, usize)> = Vec::new();
    if legend_on_title {
        let x = right - one_row_w;
        legend_at.extend(rows[0].iter().map(|&(dx, i)| (x + dx, y, i)));
    } else {
        if text.title.is_some() {
            y += line;
        }
        for row in &rows {
            legend_at.extend(row.iter().map(|&(dx, i)| (left + dx, y, i)));
            y += line;
        }
    }
    if text.title.is_some() && (legend_on_title || rows.is_empty()) {
        y += line;
    }
    let full = Rect { x0: 0, y0: 0, x1: img.width() as i64 - 1, y1: img.height() as i64 - 1 };
    for &(x, ly, i) in &legend_at {
        let s = &series[i];
        let sample = Series { points: Vec::new(), markers: false, ..s.clone() };
        polyline(img, &full, &[(x, ly + th / 2), (x + LEGEND_SAMPLE - 1, ly + th / 2)], &sample);
        if s.markers {
            brush(img, &full, x + LEGEND_SAMPLE / 2, ly + th / 2, s.thickness as i64 + 4, s.rgb);
        }
        draw_text(img, x + LEGEND_SAMPLE + LEGEND_GAP * sc, ly, &s.label, INK, scale);
    }
    let plot_top = y + 3 * sc;
    let bottom_text = TICK_LEN + 3 * sc + th + if text.x_title.is_some() { 4 * sc + th } else { 0 } + 4 * sc;
    let plot = Rect { x0: left, y0: plot_top, x1: right, y1: (top + height - 1 - bottom_text).max(plot_top + 1) };
    let map_x = |x: f64| plot.x0 as f64 + (x - x_axis.lo) / (x_axis.hi - x_axis.lo) * (plot.x1 - plot.x0) as f64;
    let map_y = |y: f64| plot.y1 as f64 - (y - y_axis.lo) / (y_axis.hi - y_axis.lo) * (plot.y1 - plot.y0) as f64;
    // grid, ticks, labels
    for (t, l) in x_axis.ticks.iter().zip(&x_axis.labels) {
        let px = map_x(*t).round() as i64;
        fill(img, px, plot.y0, px, plot.y1, GRID);
        fill(img, px, plot.y1, px, plot.y1 + TICK_LEN, FRAME);
        let w = text_width(l, scale);
        let lx = (px - w / 2).clamp(0, img.width() as i64 - w);
        draw_text(img, lx, plot.y1 + TICK_LEN + 3 * sc, l, INK, scale);
    }
    for (t, l) in y_axis.ticks.iter().zip(&y_axis.labels) {
        let py = map_y(*t).round() as i64;
        fill(img, plot.x0, py, plot.x1, py, GRID);
        fill(img, plot.x0 - TICK_LEN, py, plot.x0, py, FRAME);
        let w = text_width(l, scale);
        draw_text(img, plot.x0 - TICK_LEN - 3 * sc - w, py - th / 2, l, INK, scale);
    }
    fill(img, plot.x0, plot.y0, plot.x1, plot.y0, FRAME);
    fill(img, plot.x0, plot.y1, plot.x1, plot.y1, FRAME);
    fill(img, plot.x0, plot.y0, plot.x0, plot.y1, FRAME);
    fill(img, plot.x1, plot.y0, plot.x1, plot.y1, FRAME);
    if let Some(t) = &text.x_title {
        let w = text_width(t, scale);
        draw_text(img, (plot.x0 + plot.x1) / 2 - w / 2, plot.y1 + TICK_LEN + 3 * sc + th + 4 * sc, t, INK, scale);
    }
    if let Some(t) = &text.y_title {
        let w = text_width(t, scale);
        draw_text_up(img, 4 * sc, (plot.y0 + plot.y1) / 2 + w / 2, t, INK, scale);
    }
    // series inside the frame, dashed ones first (underneath)
    let inner = Rect { x0: plot.x0 + 1, y0: plot.y0 + 1, x1: plot.x1 - 1, y1: plot.y1 - 1 };
    for s in series.iter().filter(|s| s.dashed).chain(series.iter().filter(|s| !s.dashed)) {
        let pts: Vec<(i64, i64)> = s.finite().map(|(x, y)| (map_x(x).round() as i64, map_y(y).round() as i64)).collect();
        polyline(img, &inner, &pts, s);
    }
    plot
}

/// Font scale for an image of `width x height`: 2 unless the image is small.
fn auto_scale(width: u32, height: u32) -> u32 {
    if width >= 480 && height >= 240 { 2 } else { 1 }
}

/// Draws `series` into a `width x height` PNG: white background, one panel with nice ticks
/// and tick labels on both axes, grid lines at the ticks, a legend of the labelled series and
/// the optional titles of `text`. Returns the data extents (finite points).
pub fn plot_png_with(path: &Path, series: &[Series], width: u32, height: u32, text: &PanelText) -> Result<Extents> {
    let e = extents(series).ok_or_else(|| TrainError::Invalid("plot: no finite point".into()))?;
    let scale = auto_scale(width, height);
    let x_axis = Axis::new(e.0, e.1);
    let y_axis = Axis::padded(e.2, e.3, 0.05);
    let mut img = RgbImage::from_pixel(width, height, Rgb([255, 255, 255]));
    let left = left_margin(&[&y_axis], text.y_title.is_some(), scale);
    let right = width as i64 - 1 - right_margin(&x_axis, scale);
    draw_panel(&mut img, 0, height as i64, left, right, &x_axis, &y_axis, series, text, scale);
    save(&img, path)?;
    Ok(e)
}

/// [`plot_png_with`] without titles.
pub fn plot_png(path: &Path, series: &[Series], width: u32, height: u32) -> Result<Extents> {
    plot_png_with(path, series, width, height, &PanelText::default())
}

/// Right margin: half of the widest x tick label (the last one is centred on the frame).
fn right_margin(x_axis: &Axis, scale: u32) -> i64 {
    let w = x_axis.labels.last().map_or(0, |l| text_width(l, scale));
    (w / 2 + 4 * scale as i64).max(12 * scale as i64)
}

/// Saves `img` as PNG (or whatever the extension says).
fn save(img: &RgbImage, path: &Path) -> Result<()> {
    img.save(path).map_err(|e| TrainError::Invalid(format!("{}: {e}", path.display())))
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

// ---------------------------------------------------------------------------------------------
// The metrics figure
// ---------------------------------------------------------------------------------------------

/// One held-out validation line of `metrics.jsonl` (`kind: "val"`); missing or null (NaN)
/// values are NaN.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ValPoint {
    /// Training step.
    pub step: f64,
    /// Number of validation chunks, when given.
    pub chunks: Option<u64>,
    /// AUC@5 (%) of the feed-forward input points.
    pub input_auc5: f64,
    /// AUC@5 (%) of the refined points.
    pub refined_auc5: f64,
    /// AUC@10 (%) of the input points.
    pub input_auc10: f64,
    /// AUC@10 (%) of the refined points.
    pub refined_auc10: f64,
}

/// The plotted content of a `metrics.jsonl`.
#[derive(Debug, Clone, Default)]
pub struct Metrics {
    /// `(step, loss)` of the `kind: "train"` lines with a finite step and loss.
    pub train: Vec<(f64, f64)>,
    /// The `kind: "val"` lines with a finite step.
    pub val: Vec<ValPoint>,
}

/// Parses the text of a `metrics.jsonl` (`path` only names it in errors): every non-blank line
/// must be a JSON object (else an error naming the file and the 1-based line); lines of other
/// kinds are ignored, non-finite or missing values (`null`, as NaN is written) are skipped.
pub fn parse_metrics(text: &str, path: &Path) -> Result<Metrics> {
    let mut m = Metrics::default();
    let num = |v: &serde_json::Value| v.as_f64().filter(|x| x.is_finite()).unwrap_or(f64::NAN);
    for (i, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let v: serde_json::Value = serde_json::from_str(line)
            .map_err(|e| TrainError::Format { path: path.to_path_buf(), message: format!("line {}: {e}", i + 1) })?;
        if !v.is_object() {
            return Err(TrainError::Format { path: path.to_path_buf(), message: format!("line {}: not a JSON object", i + 1) });
        }
        let step = num(&v["step"]);
        if !step.is_finite() {
            continue;
        }
        match v["kind"].as_str() {
            Some("train") => {
                let loss = num(&v["loss"]);
                if loss.is_finite() {
                    m.train.push((step, loss));
                }
            }
            Some("val") => {
                let val = &v["val"];
                m.val.push(ValPoint {
                    step,
                    chunks: val["chunks"].as_u64(),
                    input_auc5: num(&val["input_auc5"]),
                    refined_auc5: num(&val["refined_auc5"]),
                    input_auc10: num(&val["input_auc10"]),
                    refined_auc10: num(&val["refined_auc10"]),
                });
            }
            _ => {}
        }
    }
    Ok(m)
}

/// Reads and parses a `metrics.jsonl` ([`parse_metrics`]).
pub fn read_metrics(path: &Path) -> Result<Metrics> {
    let text = std::fs::read_to_string(path).map_err(io_err(path))?;
    parse_metrics(&text, path)
}

/// Options of the metrics figure.
#[derive(Debug, Clone)]
pub struct FigureOptions {
    /// Moving-average window of the training loss.
    pub smooth: usize,
    /// Image width.
    pub width: u32,
    /// Height of each panel (the image is one or two panels high).
    pub panel_height: u32,
    /// Name of the run, shown in the loss title.
    pub run_label: Option<String>,
}

impl Default for FigureOptions {
    fn default() -> Self {
        FigureOptions { smooth: 25, width: 1000, panel_height: 400, run_label: None }
    }
}

/// Raw per-step training loss (light red).
pub const RAW_LOSS_RGB: [u8; 3] = [245, 175, 175];
/// Moving average of the training loss (bold red).
pub const AVG_LOSS_RGB: [u8; 3] = [200, 30, 30];
/// AUC@5 of the input points (grey).
pub const INPUT_AUC5_RGB: [u8; 3] = [95, 95, 95];
/// AUC@5 of the refined points (blue).
pub const REFINED_AUC5_RGB: [u8; 3] = [30, 90, 200];
/// AUC@10 of the input points (light grey, dashed).
pub const INPUT_AUC10_RGB: [u8; 3] = [175, 175, 175];
/// AUC@10 of the refined points (light blue, dashed).
pub const REFINED_AUC10_RGB: [u8; 3] = [130, 170, 235];

/// What [`render_figure`] drew.
#[derive(Debug, Clone)]
pub struct FigureSummary {
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Step range of the data.
    pub steps: (f64, f64),
    /// Range of the raw training loss.
    pub loss: (f64, f64),
    /// Last `(step, moving average)` of the loss.
    pub last_loss_avg: (f64, f64),
    /// Range of the plotted AUC values, with a val panel.
    pub auc: Option<(f64, f64)>,
    /// The last val line, with a val panel.
    pub last_val: Option<ValPoint>,
    /// Plot area of the loss panel.
    pub loss_plot: Rect,
    /// Plot area of the val panel.
    pub val_plot: Option<Rect>,
}

/// Formats an optional number with one decimal ("n/a" for NaN).
fn f1(v: f64) -> String {
    if v.is_finite() { format!("{v:.1}") } else { "n/a".into() }
}

/// Renders the metrics figure: the training-loss panel (raw per-step loss light, moving
/// average bold) and, when there is at least one finite val value, the held-out AUC@5/AUC@10
/// panel (input grey, refined blue; AUC@10 dashed and lighter) below it on the same step axis.
pub fn render_figure(m: &Metrics, o: &FigureOptions) -> Result<(RgbImage, FigureSummary)> {
    if m.train.is_empty() {
        return Err(TrainError::Invalid("plot: no finite training loss yet".into()));
    }
    let avg = smooth(&m.train, o.smooth);
    let loss_series = vec![
        Series::line(m.train.clone(), RAW_LOSS_RGB).thickness(1).label("loss per step"),
        Series::line(avg.clone(), AVG_LOSS_RGB).thickness(3).label(format!("moving average ({} steps)", o.smooth.max(1))),
    ];
    let pick = |f: fn(&ValPoint) -> f64| -> Vec<(f64, f64)> { m.val.iter().map(|v| (v.step, f(v))).filter(|p| p.1.is_finite()).collect() };
    let val_series: Vec<Series> = vec![
        Series::line(pick(|v| v.input_auc5), INPUT_AUC5_RGB).markers().label("input AUC@5"),
        Series::line(pick(|v| v.refined_auc5), REFINED_AUC5_RGB).markers().label("refined AUC@5"),
        Series::line(pick(|v| v.input_auc10), INPUT_AUC10_RGB).dashed().label("input AUC@10"),
        Series::line(pick(|v| v.refined_auc10), REFINED_AUC10_RGB).dashed().label("refined AUC@10"),
    ];
    let has_val = val_series.iter().any(|s| !s.points.is_empty());
    let le = extents(&loss_series).expect("finite train points");
    let ve = if has_val { extents(&val_series) } else { None };
    let (mut x0, mut x1) = (le.0, le.1);
    if let Some(v) = ve {
        x0 = x0.min(v.0);
        x1 = x1.max(v.1);
    }
    let steps = (x0, x1);
    if x0 >= 0.0 && x0 <= 0.1 * x1 {
        x0 = 0.0;
    }
    let x_axis = Axis::new(x0, x1);
    let loss_axis = Axis::padded(le.2, le.3, 0.05);
    let val_axis = ve.map(|v| Axis::padded(v.2, v.3, 0.06));
    let scale = 2;
    let (w, ph) = (o.width.max(200), o.panel_height.max(150));
    let height = if has_val { 2 * ph } else { ph };
    let mut img = RgbImage::from_pixel(w, height, Rgb([255, 255, 255]));
    let mut axes = vec![&loss_axis];
    axes.extend(val_axis.as_ref());
    let left = left_margin(&axes, true, scale);
    let right = w as i64 - 1 - right_margin(&x_axis, scale);
    let last_avg = *avg.last().expect("non-empty");
    let run = o.run_label.as_deref().map_or(String::new(), |r| format!(" (run {r})"));
    let loss_text = PanelText {
        title: Some(format!("Training loss{run}, step {:.0}: moving average {:.4}", last_avg.0, last_avg.1)),
        x_title: Some("step".into()),
        y_title: Some("loss".into()),
    };
    let loss_plot = draw_panel(&mut img, 0, ph as i64, left, right, &x_axis, &loss_axis, &loss_series, &loss_text, scale);
    let mut summary = FigureSummary {
        width: w,
        height,
        steps,
        loss: (le.2, le.3),
        last_loss_avg: last_avg,
        auc: None,
        last_val: None,
        loss_plot,
        val_plot: None,
    };
    if let (Some(va), Some(ve)) = (&val_axis, ve) {
        let last = *m.val.last().expect("val lines");
        let chunks = last.chunks.map_or(String::new(), |c| format!(" ({c} chunks)"));
        let text = PanelText {
            title: Some(format!(
                "Held-out validation{chunks}, step {:.0}: AUC@5 input {} -> refined {}",
                last.step,
                f1(last.input_auc5),
                f1(last.refined_auc5)
            )),
            x_title: Some("step".into()),
            y_title: Some("AUC (%)".into()),
        };
        // thin separator between the panels
        fill(&mut img, 0, ph as i64 - 1, w as i64 - 1, ph as i64 - 1, GRID);
        summary.val_plot = Some(draw_panel(&mut img, ph as i64, ph as i64, left, right, &x_axis, va, &val_series, &text, scale));
        summary.auc = Some((ve.2, ve.3));
        summary.last_val = Some(last);
    }
    Ok((img, summary))
}

/// [`render_figure`] written to `path` (PNG).
pub fn write_figure(path: &Path, m: &Metrics, o: &FigureOptions) -> Result<FigureSummary> {
    let (img, s) = render_figure(m, o)?;
    save(&img, path)?;
    Ok(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Number of pixels of colour `rgb` inside `r`.
    fn count(img: &RgbImage, r: &Rect, rgb: [u8; 3]) -> usize {
        img.enumerate_pixels().filter(|(x, y, p)| r.contains(*x as i64, *y as i64) && p.0 == rgb).count()
    }

    #[test]
    fn plot_font_covers_every_supported_character() {
        let supported: Vec<char> = ('0'..='9')
            .chain('A'..='Z')
            .chain('a'..='z')
            .chain(".-+%@()/:,_=<>[]!?#*'\"&$;^`{|}~\\".chars())
            .collect();
        for c in supported {
            assert!(is_supported(c));
            assert!(glyph(c).iter().any(|&r| r != 0), "empty glyph for {c:?}");
            assert!(glyph(c).iter().all(|&r| r < 0x20), "glyph wider than 5 for {c:?}");
            let mut img = RgbImage::from_pixel(20, 20, Rgb([255, 255, 255]));
            draw_text(&mut img, 2, 2, &c.to_string(), [0, 0, 0], 2);
            assert!(img.pixels().any(|p| p.0 == [0, 0, 0]), "nothing drawn for {c:?}");
        }
        assert!(glyph(' ').iter().all(|&r| r == 0));
        // every printable ASCII character but space has a distinct, non-empty glyph
        let all: Vec<[u8; GLYPH_ROWS]> = ('!'..='~').map(glyph).collect();
        for (i, g) in all.iter().enumerate() {
            assert!(g.iter().any(|&r| r != 0));
            assert!(all[i + 1..].iter().all(|h| h != g), "duplicate glyph {:?}", (b'!' + i as u8) as char);
        }
        for c in ['é', '→', '\t', 'µ'] {
            assert!(!is_supported(c));
            assert_eq!(glyph(c), BOX_GLYPH);
        }
        // scale 2: a 10x14 box outline
        let mut img = RgbImage::from_pixel(16, 20, Rgb([255, 255, 255]));
        assert_eq!(draw_text(&mut img, 1, 1, "é", [0, 0, 0], 2), 10);
        assert_eq!(img.get_pixel(1, 1).0, [0, 0, 0]);
        assert_eq!(img.get_pixel(10, 14).0, [0, 0, 0]);
        assert_eq!(img.get_pixel(5, 7).0, [255, 255, 255]);
        assert_eq!(text_width("AUC (%)", 2), (7 * 6 - 1) * 2);
        assert_eq!(fit_text("AUC (%)", 1000, 2), "AUC (%)");
        let f = fit_text("a long title line", 100, 2);
        assert!(f.ends_with("..") && text_width(&f, 2) <= 100 && text_width(&f, 2) > 100 - 2 * 6 * 2, "{f}");
        // rotated text draws the same number of pixels
        let mut a = RgbImage::from_pixel(100, 100, Rgb([255, 255, 255]));
        let mut b = a.clone();
        draw_text(&mut a, 5, 5, "loss", [0, 0, 0], 2);
        draw_text_up(&mut b, 5, 90, "loss", [0, 0, 0], 2);
        let n = |i: &RgbImage| i.pixels().filter(|p| p.0 == [0, 0, 0]).count();
        assert_eq!(n(&a), n(&b));
        assert!(n(&a) > 0);
    }

    fn close(a: &[f64], b: &[f64]) -> bool {
        a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-9)
    }

    #[test]
    fn plot_nice_ticks() {
        let t = nice_ticks(0.27, 0.83, 6);
        assert!(close(&t, &[0.3, 0.4, 0.5, 0.6, 0.7, 0.8]), "{t:?}");
        let t = nice_ticks(0.0, 600.0, 6);
        assert!(close(&t, &[0.0, 200.0, 400.0, 600.0]), "{t:?}");
        let t = nice_ticks(0.0, 600.0, 7);
        assert!(close(&t, &[0.0, 100.0, 200.0, 300.0, 400.0, 500.0, 600.0]), "{t:?}");
        let t = nice_ticks(12.3, 74.1, 6);
        assert!(close(&t, &[20.0, 30.0, 40.0, 50.0, 60.0, 70.0]), "{t:?}");
        let t = nice_ticks(-0.013, 0.021, 6);
        assert!(close(&t, &[-0.01, 0.0, 0.01, 0.02]), "{t:?}");
        // axes: 4-6 ticks, labels with the decimals of the step
        for (lo, hi) in [(0.27, 0.83), (0.0, 179.0), (1.0, 179.0), (0.0, 600.0), (13.7, 75.2), (0.31, 0.33), (5.0, 5.0), (0.0, 12345.0), (-3.0, 2.5)] {
            let a = Axis::new(lo, hi);
            assert!((4..=8).contains(&a.ticks.len()), "{lo}..{hi}: {:?}", a.ticks);
            assert!(a.lo <= lo.min(hi) && a.hi >= hi.max(lo), "{lo}..{hi}: {}..{}", a.lo, a.hi);
            assert!(a.ticks.iter().all(|t| *t >= a.lo - 1e-9 && *t <= a.hi + 1e-9));
        }
        assert_eq!(Axis::new(0.27, 0.83).labels, ["0.3", "0.4", "0.5", "0.6", "0.7", "0.8"]);
        assert_eq!(Axis::new(0.0, 179.0).labels, ["0", "50", "100", "150"]);
        assert_eq!(Axis::new(-0.013, 0.021).labels, ["-0.01", "0.00", "0.01", "0.02"]);
    }

    #[test]
    fn plots_and_smooths() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.png");
        let mut pts: Vec<(f64, f64)> = (0..50).map(|i| (i as f64, 1.0 / (1.0 + i as f64))).collect();
        pts[10].1 = f64::NAN;
        let s = Series::line(pts, [255, 0, 0]).label("1/(1+x)");
        let e = plot_png(&p, &[s], 200, 100).unwrap();
        assert_eq!(e, (0.0, 49.0, 1.0 / 50.0, 1.0));
        let img = image::open(&p).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (200, 100));
        assert!(img.pixels().any(|px| px.0 == [255, 0, 0]));
        let sm = smooth(&[(0.0, 0.0), (1.0, 2.0), (2.0, 4.0)], 2);
        assert_eq!(sm, vec![(0.0, 0.0), (1.0, 1.0), (2.0, 3.0)]);
    }

    fn metrics_text(with_val: bool) -> String {
        let mut s = String::new();
        for step in 1..=240 {
            let loss = if step == 17 { "null".to_string() } else { format!("{}", 0.3 + 0.6 / (1.0 + step as f64 / 30.0) + 0.05 * ((step * 7) % 5) as f64 / 5.0) };
            s += &format!("{{\"step\":{step},\"kind\":\"train\",\"loss\":{loss},\"lr\":0.001}}\n");
            if with_val && step % 50 == 0 {
                let r = 20.0 + step as f64 / 6.0;
                let r10 = if step == 100 { "null".to_string() } else { format!("{}", r + 20.0) };
                s += &format!(
                    "{{\"step\":{step},\"kind\":\"val\",\"loss\":0.4,\"val\":{{\"chunks\":48,\"loss\":0.4,\"input_auc5\":33.0,\"input_auc10\":59.9,\"refined_auc5\":{r},\"refined_auc10\":{r10}}}}}\n"
                );
            }
        }
        s + "\n"
    }

    #[test]
    fn plot_figure_end_to_end() {
        let dir = tempfile::tempdir().unwrap();
        let mpath = dir.path().join("metrics.jsonl");
        std::fs::write(&mpath, metrics_text(true)).unwrap();
        let m = read_metrics(&mpath).unwrap();
        assert_eq!(m.train.len(), 239, "the null loss is skipped");
        assert_eq!(m.val.len(), 4);
        assert!(m.val[1].refined_auc10.is_nan());
        let out = dir.path().join("curve.png");
        let o = FigureOptions { run_label: Some("test".into()), ..FigureOptions::default() };
        let s = write_figure(&out, &m, &o).unwrap();
        let img = image::open(&out).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (o.width, 2 * o.panel_height));
        assert_eq!((s.width, s.height), img.dimensions());
        assert_eq!(s.steps, (1.0, 240.0));
        let vp = s.val_plot.expect("val panel");
        assert!(s.loss_plot.y1 < o.panel_height as i64 && vp.y0 > o.panel_height as i64);
        for c in [RAW_LOSS_RGB, AVG_LOSS_RGB] {
            assert!(count(&img, &s.loss_plot, c) > 100, "loss colour {c:?}");
            assert_eq!(count(&img, &vp, c), 0);
        }
        for c in [INPUT_AUC5_RGB, REFINED_AUC5_RGB, INPUT_AUC10_RGB, REFINED_AUC10_RGB] {
            assert!(count(&img, &vp, c) > 50, "val colour {c:?}");
            assert_eq!(count(&img, &s.loss_plot, c), 0);
        }
        // text (ink) outside the plot areas: titles, tick labels, axis titles, legends
        let top_band = Rect { x0: 0, y0: 0, x1: o.width as i64 - 1, y1: s.loss_plot.y0 - 1 };
        assert!(count(&img, &top_band, INK) > 200);
        let left_band = Rect { x0: 0, y0: 0, x1: s.loss_plot.x0 - 1, y1: img.height() as i64 - 1 };
        assert!(count(&img, &left_band, INK) > 200);

        // without val lines: the loss panel only
        std::fs::write(&mpath, metrics_text(false)).unwrap();
        let m = read_metrics(&mpath).unwrap();
        let s = write_figure(&out, &m, &o).unwrap();
        let img = image::open(&out).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (o.width, o.panel_height));
        assert!(s.val_plot.is_none() && s.auc.is_none());
        assert!(count(&img, &s.loss_plot, AVG_LOSS_RGB) > 100);
        let full = Rect { x0: 0, y0: 0, x1: 10_000, y1: 10_000 };
        assert_eq!(count(&img, &full, REFINED_AUC5_RGB), 0);

        // a line that is not JSON: error naming the file and the line
        std::fs::write(&mpath, "{\"step\":1,\"kind\":\"train\",\"loss\":0.5}\n{\"step\":2,\"kind\n").unwrap();
        let e = read_metrics(&mpath).unwrap_err().to_string();
        assert!(e.contains("metrics.jsonl") && e.contains("line 2"), "{e}");
        // no training loss yet
        assert!(render_figure(&Metrics::default(), &o).is_err());
    }
}
