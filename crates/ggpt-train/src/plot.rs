//! The training-curve figure of `ggpt-train plot`, drawn with [`plotters`] into an RGB buffer
//! (bitmap backend; text in the embedded DejaVu Sans through plotters' `ab_glyph` fonts, no
//! system font lookup) and written as PNG.
//!
//! * [`read_metrics`] / [`parse_metrics`]: the training-loss and held-out validation lines of a
//!   `metrics.jsonl`.
//! * [`smooth`]: moving average of the noisy per-step loss.
//! * [`render_figure`] / [`write_figure`]: training loss on top and held-out AUC@5/10 below,
//!   sharing the step axis, each panel with a title and a legend above it and axis titles.

use std::path::Path;
use std::sync::OnceLock;

use image::RgbImage;
use plotters::backend::RGBPixel;
use plotters::coord::Shift;
use plotters::element::DashedPathElement;
use plotters::prelude::*;
use plotters::style::register_font;

use crate::error::{Result, TrainError, io_err};

// ---------------------------------------------------------------------------------------------
// Metrics
// ---------------------------------------------------------------------------------------------

/// Moving average over `window` points (for noisy per-step losses).
pub fn smooth(points: &[(f64, f64)], window: usize) -> Vec<(f64, f64)> {
    let w = window.max(1);
    (0..points.len())
        .map(|i| {
            let a = i.saturating_sub(w - 1);
            let ys = &points[a..=i];
            (
                points[i].0,
                ys.iter().map(|p| p.1).sum::<f64>() / ys.len() as f64,
            )
        })
        .collect()
}

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
        let v: serde_json::Value = serde_json::from_str(line).map_err(|e| TrainError::Format {
            path: path.to_path_buf(),
            message: format!("line {}: {e}", i + 1),
        })?;
        if !v.is_object() {
            return Err(TrainError::Format {
                path: path.to_path_buf(),
                message: format!("line {}: not a JSON object", i + 1),
            });
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

// ---------------------------------------------------------------------------------------------
// The figure
// ---------------------------------------------------------------------------------------------

/// Options of the metrics figure.
#[derive(Debug, Clone)]
pub struct FigureOptions {
    /// Moving-average window of the training loss.
    pub smooth: usize,
    /// Image width (at least 200, at most [`MAX_SIDE`]).
    pub width: u32,
    /// Height of each panel (the image is one or two panels high; at least 150, at most
    /// [`MAX_SIDE`]).
    pub panel_height: u32,
    /// Name of the run, shown in the loss title.
    pub run_label: Option<String>,
}

impl Default for FigureOptions {
    fn default() -> Self {
        FigureOptions {
            smooth: 25,
            width: 1000,
            panel_height: 400,
            run_label: None,
        }
    }
}

/// Largest accepted image width and panel height in pixels.
pub const MAX_SIDE: u32 = 16384;

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

/// The embedded font ([`ggpt_eval::figure::FONT_TTF`], DejaVu Sans).
static FONT_TTF: &[u8] = ggpt_eval::figure::FONT_TTF;
/// Family the embedded font is registered under (plotters' default for axis labels).
const FONT: &str = "sans-serif";
/// Font size of the panel titles.
const TITLE_PX: f64 = 17.0;
/// Font size of tick labels and legend entries.
const TEXT_PX: f64 = 15.0;
/// Font size of the axis titles.
const DESC_PX: f64 = 16.0;
/// Text colour.
const INK: RGBColor = RGBColor(30, 30, 30);
/// Axis and frame colour.
const FRAME: RGBColor = RGBColor(90, 90, 90);
/// Grid line colour.
const GRID: RGBColor = RGBColor(228, 228, 228);
/// Margin left of the y-axis title (plotters draws the rotated title slightly left of its
/// label area).
const LEFT_MARGIN: u32 = 10;
/// Width left of the plot area for the y-axis title and tick labels (the same in both panels,
/// so that their step axes line up).
const Y_LABEL_AREA: u32 = 72;
/// Height under the plot area for the x tick labels and the x-axis title.
const X_LABEL_AREA: u32 = 48;
/// Margin right of the plot area (room for the last x tick label).
const RIGHT_MARGIN: u32 = 24;
/// Space above the title line.
const HEAD_PAD: i32 = 10;
/// Height of the title line.
const TITLE_LINE: i32 = 24;
/// Height of one legend row.
const LEGEND_LINE: i32 = 21;
/// Length of a legend line sample.
const LEGEND_SAMPLE: i32 = 30;
/// Gap between a legend sample and its label.
const LEGEND_GAP: i32 = 6;
/// Gap between two legend entries.
const LEGEND_SPACING: i32 = 20;

/// One plotted series: `(x, y)` points (non-finite ones are skipped) and its style.
struct Series {
    points: Vec<(f64, f64)>,
    rgb: [u8; 3],
    width: u32,
    dashed: bool,
    markers: bool,
    label: String,
}

impl Series {
    fn new(points: Vec<(f64, f64)>, rgb: [u8; 3], width: u32, label: impl Into<String>) -> Self {
        Series {
            points: points
                .into_iter()
                .filter(|(x, y)| x.is_finite() && y.is_finite())
                .collect(),
            rgb,
            width,
            dashed: false,
            markers: false,
            label: label.into(),
        }
    }
    fn style(&self) -> ShapeStyle {
        let [r, g, b] = self.rgb;
        RGBColor(r, g, b).filled().stroke_width(self.width)
    }
}

/// Data extents `(x_min, x_max, y_min, y_max)` of `series`; `None` without any point.
fn extents(series: &[Series]) -> Option<(f64, f64, f64, f64)> {
    let mut pts = series.iter().flat_map(|s| s.points.iter().copied());
    let (x, y) = pts.next()?;
    Some(pts.fold((x, x, y, y), |e, (x, y)| {
        (e.0.min(x), e.1.max(x), e.2.min(y), e.3.max(y))
    }))
}

/// `[lo, hi]` padded by `pad` of its span on each side; a degenerate range is widened around
/// its value.
fn padded(lo: f64, hi: f64, pad: f64) -> (f64, f64) {
    let span = hi - lo;
    if span <= f64::EPSILON * lo.abs().max(hi.abs()).max(1.0) * 16.0 {
        let d = (lo.abs() * 0.05).max(0.5);
        (lo - d, hi + d)
    } else {
        (lo - span * pad, hi + span * pad)
    }
}

/// One panel: its texts, y range and series.
struct Panel<'a> {
    title: String,
    y_title: &'a str,
    y_range: (f64, f64),
    series: &'a [Series],
}

/// The drawing area of the figure.
type Area<'a> = DrawingArea<BitMapBackend<'a, RGBPixel>, Shift>;

/// Result of the drawing functions: errors as text (named with the output file by [`render`]).
type DrawResult<T> = std::result::Result<T, String>;

/// A drawing error as text.
fn de(e: impl std::fmt::Display) -> String {
    e.to_string()
}

/// Registers the embedded font with plotters (once per process).
fn ensure_font() -> DrawResult<()> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    if *REGISTERED.get_or_init(|| register_font(FONT, FontStyle::Normal, FONT_TTF).is_ok()) {
        Ok(())
    } else {
        Err("the embedded font (DejaVu Sans) could not be loaded".into())
    }
}

/// Text style of the embedded font at `px` in the text colour.
fn text_style(px: f64) -> TextStyle<'static> {
    (FONT, px).into_font().color(&INK)
}

/// Width in pixels of `text` in `style`.
fn text_width(area: &Area, text: &str, style: &TextStyle) -> DrawResult<i32> {
    let (w, _) = area.estimate_text_size(text, style).map_err(de)?;
    Ok(w as i32)
}

/// Draws `text` in the embedded font at `px` with its top left corner at `(x, y)`, one glyph
/// at a time: plotters' `ab_glyph` text drops each glyph's left side bearing, which spaces the
/// letters unevenly ("loss p er step"), so every glyph is placed at its pen position plus its
/// bearing here (the same advances and kerning as plotters' text width).
fn draw_label(area: &Area, text: &str, px: f64, (x, y): (i32, i32)) -> DrawResult<()> {
    use ab_glyph::{Font, ScaleFont};
    let font = ab_glyph::FontRef::try_from_slice(FONT_TTF).map_err(de)?;
    let font = font.as_scaled(px as f32);
    let style = text_style(px);
    let (mut pen, mut prev) = (0f32, None);
    let mut utf8 = [0u8; 4];
    for c in text.chars() {
        let id = font.glyph_id(c);
        if let Some(p) = prev {
            pen += font.kern(p, id);
        }
        if let Some(g) = font.outline_glyph(font.scaled_glyph(c)) {
            let left = (pen + g.px_bounds().min.x).round() as i32;
            area.draw_text(c.encode_utf8(&mut utf8), &style, (x + left, y))
                .map_err(de)?;
        }
        pen += font.h_advance(id);
        prev = Some(id);
    }
    Ok(())
}

/// `text`, shortened with "…" at the end when wider than `max_w` pixels.
fn fit_text(area: &Area, text: &str, style: &TextStyle, max_w: i32) -> DrawResult<String> {
    if text_width(area, text, style)? <= max_w {
        return Ok(text.to_string());
    }
    let mut chars: Vec<char> = text.chars().collect();
    while !chars.is_empty() {
        chars.pop();
        let t: String = chars.iter().chain(['…'].iter()).collect();
        if text_width(area, &t, style)? <= max_w {
            return Ok(t);
        }
    }
    Ok(String::new())
}

/// Layout of the legend entries of `series` within `width` pixels: rows of
/// `(x offset, series index)`.
fn legend_rows(area: &Area, series: &[Series], width: i32) -> DrawResult<Vec<Vec<(i32, usize)>>> {
    let style = text_style(TEXT_PX);
    let mut rows: Vec<Vec<(i32, usize)>> = Vec::new();
    let mut x = 0;
    for (i, s) in series.iter().enumerate() {
        let w = LEGEND_SAMPLE + LEGEND_GAP + text_width(area, &s.label, &style)?;
        match rows.last_mut() {
            Some(row) if x + w <= width => row.push((x, i)),
            _ => {
                rows.push(vec![(0, i)]);
                x = 0;
            }
        }
        x += w + LEGEND_SPACING;
    }
    Ok(rows)
}

/// Draws one panel into `area`: title line and legend rows on top, then the chart (grid, axes
/// with tick labels and titles, frame, series; dashed series underneath). Returns the plot area
/// in image pixels.
fn draw_panel(area: &Area, x_range: (f64, f64), p: &Panel) -> DrawResult<Rect> {
    let (aw, _) = area.dim_in_pixel();
    let plot_w = aw as i32 - (LEFT_MARGIN + Y_LABEL_AREA + RIGHT_MARGIN) as i32;
    let rows = legend_rows(area, p.series, plot_w)?;
    let head_h = HEAD_PAD + TITLE_LINE + rows.len() as i32 * LEGEND_LINE;
    let (head, body) = area.split_vertically(head_h);
    let mut chart = ChartBuilder::on(&body)
        .margin_top(6)
        .margin_bottom(2)
        .margin_left(LEFT_MARGIN)
        .margin_right(RIGHT_MARGIN)
        .x_label_area_size(X_LABEL_AREA)
        .y_label_area_size(Y_LABEL_AREA)
        .build_cartesian_2d(x_range.0..x_range.1, p.y_range.0..p.y_range.1)
        .map_err(de)?;
    // whole-number tick labels on long ranges (steps, AUC in %); plotters' own formatting
    // (at least one decimal) on short ones
    let whole = |v: &f64| format!("{:.0}", v.round() + 0.0);
    let mut mesh = chart.configure_mesh();
    mesh.x_labels(8)
        .y_labels(7)
        .label_style(text_style(TEXT_PX))
        .axis_desc_style(text_style(DESC_PX))
        .x_desc("step")
        .y_desc(p.y_title)
        .bold_line_style(GRID)
        .light_line_style(TRANSPARENT)
        .axis_style(FRAME);
    if x_range.1 - x_range.0 >= 10.0 {
        mesh.x_label_formatter(&whole);
    }
    if p.y_range.1 - p.y_range.0 >= 10.0 {
        mesh.y_label_formatter(&whole);
    }
    mesh.draw().map_err(de)?;
    let dashed = p.series.iter().filter(|s| s.dashed);
    for s in dashed.chain(p.series.iter().filter(|s| !s.dashed)) {
        let pts = s.points.iter().copied();
        if s.dashed {
            chart
                .draw_series(DashedLineSeries::new(pts, 10, 6, s.style()))
                .map_err(de)?;
        } else {
            let points = if s.markers { s.width + 2 } else { 0 };
            chart
                .draw_series(LineSeries::new(pts, s.style()).point_size(points))
                .map_err(de)?;
        }
    }
    // frame around the plot area (the mesh draws the left and bottom axes only)
    let (xr, yr) = chart.plotting_area().get_pixel_range();
    let (bx, by) = area.get_base_pixel();
    let (x0, y0, x1, y1) = (
        xr.start - bx,
        yr.start - by,
        xr.end - 1 - bx,
        yr.end - 1 - by,
    );
    area.draw(&Rectangle::new([(x0, y0), (x1, y1)], FRAME))
        .map_err(de)?;
    // title and legend, starting at the left edge of the plot area
    let title_style = text_style(TITLE_PX);
    let title = fit_text(&head, &p.title, &title_style, aw as i32 - x0 - 4)?;
    draw_label(&head, &title, TITLE_PX, (x0, HEAD_PAD))?;
    for (r, row) in rows.iter().enumerate() {
        let y = HEAD_PAD + TITLE_LINE + r as i32 * LEGEND_LINE;
        // vertical middle of the lower-case letters of the label
        let yc = y + 3;
        for &(dx, i) in row {
            let s = &p.series[i];
            let (x, style) = (x0 + dx, s.style());
            let line = vec![(x, yc), (x + LEGEND_SAMPLE, yc)];
            if s.dashed {
                head.draw(&DashedPathElement::new(line, 8, 5, style))
                    .map_err(de)?;
            } else {
                head.draw(&PathElement::new(line, style)).map_err(de)?;
            }
            if s.markers {
                head.draw(&Circle::new(
                    (x + LEGEND_SAMPLE / 2, yc),
                    s.width + 2,
                    style,
                ))
                .map_err(de)?;
            }
            let lx = x + LEGEND_SAMPLE + LEGEND_GAP;
            draw_label(&head, &s.label, TEXT_PX, (lx, y))?;
        }
    }
    Ok(Rect {
        x0: i64::from(xr.start),
        y0: i64::from(yr.start),
        x1: i64::from(xr.end - 1),
        y1: i64::from(yr.end - 1),
    })
}

/// Draws the figure into `buf` (RGB8, `size`): the loss panel, and the val panel below it when
/// given, each `panel_h` high. Returns their plot areas.
fn draw_figure(
    buf: &mut [u8],
    size: (u32, u32),
    panel_h: u32,
    x_range: (f64, f64),
    loss: &Panel,
    val: Option<&Panel>,
) -> DrawResult<(Rect, Option<Rect>)> {
    ensure_font()?;
    let root = BitMapBackend::<RGBPixel>::with_buffer_and_format(buf, size)
        .map_err(de)?
        .into_drawing_area();
    root.fill(&WHITE).map_err(de)?;
    let plots = match val {
        Some(val) => {
            let (top, bottom) = root.split_vertically(panel_h);
            let loss_plot = draw_panel(&top, x_range, loss)?;
            let val_plot = draw_panel(&bottom, x_range, val)?;
            // thin separator between the panels
            let y = panel_h as i32 - 1;
            root.draw(&PathElement::new(
                vec![(0, y), (size.0 as i32 - 1, y)],
                GRID,
            ))
            .map_err(de)?;
            (loss_plot, Some(val_plot))
        }
        None => (draw_panel(&root, x_range, loss)?, None),
    };
    root.present().map_err(de)?;
    Ok(plots)
}

/// Formats an optional number with one decimal ("n/a" for NaN).
fn f1(v: f64) -> String {
    if v.is_finite() {
        format!("{v:.1}")
    } else {
        "n/a".into()
    }
}

/// [`render_figure`], with drawing errors naming `target`.
fn render(m: &Metrics, o: &FigureOptions, target: &Path) -> Result<(RgbImage, FigureSummary)> {
    if o.width > MAX_SIDE || o.panel_height > MAX_SIDE {
        return Err(TrainError::Invalid(format!(
            "plot: width {} / panel height {} above {MAX_SIDE} pixels",
            o.width, o.panel_height
        )));
    }
    let avg = smooth(&m.train, o.smooth);
    let raw = Series::new(m.train.clone(), RAW_LOSS_RGB, 1, "loss per step");
    let (Some(&last_avg), Some(le)) = (avg.last(), extents(std::slice::from_ref(&raw))) else {
        return Err(TrainError::Invalid(
            "plot: no finite training loss yet".into(),
        ));
    };
    let avg_label = format!("moving average ({} steps)", o.smooth.max(1));
    let loss_series = [raw, Series::new(avg, AVG_LOSS_RGB, 3, avg_label)];
    let pick = |f: fn(&ValPoint) -> f64| -> Vec<(f64, f64)> {
        m.val.iter().map(|v| (v.step, f(v))).collect()
    };
    // AUC@5 solid with markers, AUC@10 dashed
    let val_series = [
        (pick(|v| v.input_auc5), INPUT_AUC5_RGB, false, "input AUC@5"),
        (
            pick(|v| v.refined_auc5),
            REFINED_AUC5_RGB,
            false,
            "refined AUC@5",
        ),
        (
            pick(|v| v.input_auc10),
            INPUT_AUC10_RGB,
            true,
            "input AUC@10",
        ),
        (
            pick(|v| v.refined_auc10),
            REFINED_AUC10_RGB,
            true,
            "refined AUC@10",
        ),
    ]
    .map(|(points, rgb, dashed, label)| Series {
        dashed,
        markers: !dashed,
        ..Series::new(points, rgb, 2, label)
    });
    let ve = extents(&val_series);
    let (mut x0, mut x1) = (le.0, le.1);
    if let Some(v) = ve {
        x0 = x0.min(v.0);
        x1 = x1.max(v.1);
    }
    let steps = (x0, x1);
    if x0 >= 0.0 && x0 <= 0.1 * x1 {
        x0 = 0.0;
    }
    let x_range = if x1 > x0 {
        (x0, x1)
    } else {
        padded(x0, x1, 0.0)
    };
    let run = o
        .run_label
        .as_deref()
        .map_or(String::new(), |r| format!(" (run {r})"));
    let loss_panel = Panel {
        title: format!(
            "Training loss{run}, step {:.0}: moving average {:.4}",
            last_avg.0, last_avg.1
        ),
        y_title: "loss",
        y_range: padded(le.2, le.3, 0.05),
        series: &loss_series,
    };
    let last_val = m.val.last().copied().filter(|_| ve.is_some());
    let val_panel = match (ve, last_val) {
        (Some(ve), Some(last)) => {
            let chunks = last
                .chunks
                .map_or(String::new(), |c| format!(" ({c} chunks)"));
            Some(Panel {
                title: format!(
                    "Held-out validation{chunks}, step {:.0}: AUC@5 input {} → refined {}",
                    last.step,
                    f1(last.input_auc5),
                    f1(last.refined_auc5)
                ),
                y_title: "AUC (%)",
                y_range: padded(ve.2, ve.3, 0.06),
                series: &val_series,
            })
        }
        _ => None,
    };
    let (w, ph) = (o.width.max(200), o.panel_height.max(150));
    let h = if val_panel.is_some() { 2 * ph } else { ph };
    let mut buf = vec![255u8; w as usize * h as usize * 3];
    let draw_err = |message: String| TrainError::Format {
        path: target.to_path_buf(),
        message: format!("drawing the figure: {message}"),
    };
    let (loss_plot, val_plot) = draw_figure(
        &mut buf,
        (w, h),
        ph,
        x_range,
        &loss_panel,
        val_panel.as_ref(),
    )
    .map_err(draw_err)?;
    let img = RgbImage::from_raw(w, h, buf)
        .ok_or_else(|| draw_err(format!("buffer does not hold {w}x{h} RGB pixels")))?;
    let summary = FigureSummary {
        width: w,
        height: h,
        steps,
        loss: (le.2, le.3),
        last_loss_avg: last_avg,
        auc: val_plot.and(ve).map(|v| (v.2, v.3)),
        last_val: val_plot.and(last_val),
        loss_plot,
        val_plot,
    };
    Ok((img, summary))
}

/// Renders the metrics figure: the training-loss panel (raw per-step loss light, moving
/// average bold) and, when there is at least one finite val value, the held-out AUC@5/AUC@10
/// panel (input grey, refined blue; AUC@10 dashed and lighter) below it on the same step axis.
pub fn render_figure(m: &Metrics, o: &FigureOptions) -> Result<(RgbImage, FigureSummary)> {
    render(m, o, Path::new("(figure in memory)"))
}

/// [`render_figure`] written to `path` (PNG, atomically); drawing errors name `path`.
pub fn write_figure(path: &Path, m: &Metrics, o: &FigureOptions) -> Result<FigureSummary> {
    let (img, s) = render(m, o, path)?;
    ggpt_core::io::png::write_rgb8(
        path,
        img.width() as usize,
        img.height() as usize,
        img.as_raw(),
    )?;
    Ok(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Number of pixels of colour `rgb` inside `r`.
    fn count(img: &RgbImage, r: &Rect, rgb: [u8; 3]) -> usize {
        img.enumerate_pixels()
            .filter(|(x, y, p)| r.contains(i64::from(*x), i64::from(*y)) && p.0 == rgb)
            .count()
    }

    /// Number of dark (text-coloured, anti-aliased included) pixels inside `r`.
    fn ink(img: &RgbImage, r: &Rect) -> usize {
        img.enumerate_pixels()
            .filter(|(x, y, p)| {
                r.contains(i64::from(*x), i64::from(*y)) && p.0.iter().all(|&c| c < 110)
            })
            .count()
    }

    #[test]
    fn plot_smooths() {
        let sm = smooth(&[(0.0, 0.0), (1.0, 2.0), (2.0, 4.0)], 2);
        assert_eq!(sm, vec![(0.0, 0.0), (1.0, 1.0), (2.0, 3.0)]);
        assert_eq!(
            smooth(&[(5.0, 1.0), (6.0, 3.0)], 0),
            vec![(5.0, 1.0), (6.0, 3.0)]
        );
        assert!(smooth(&[], 25).is_empty());
    }

    fn metrics_text(with_val: bool) -> String {
        let mut s = String::new();
        for step in 1..=240 {
            let loss = if step == 17 {
                "null".to_string()
            } else {
                format!(
                    "{}",
                    0.3 + 0.6 / (1.0 + step as f64 / 30.0) + 0.05 * ((step * 7) % 5) as f64 / 5.0
                )
            };
            s += &format!("{{\"step\":{step},\"kind\":\"train\",\"loss\":{loss},\"lr\":0.001}}\n");
            if with_val && step % 50 == 0 {
                let r = 20.0 + step as f64 / 6.0;
                let r10 = if step == 100 {
                    "null".to_string()
                } else {
                    format!("{}", r + 20.0)
                };
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
        let o = FigureOptions {
            run_label: Some("test".into()),
            ..FigureOptions::default()
        };
        let s = write_figure(&out, &m, &o).unwrap();
        let img = image::open(&out).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (o.width, 2 * o.panel_height));
        assert_eq!((s.width, s.height), img.dimensions());
        // summary values
        assert_eq!(s.steps, (1.0, 240.0));
        let (lo, hi) = m
            .train
            .iter()
            .fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.1), b.max(p.1)));
        assert_eq!(s.loss, (lo, hi));
        let avg = smooth(&m.train, o.smooth);
        assert_eq!(s.last_loss_avg, avg[avg.len() - 1]);
        assert_eq!(s.last_loss_avg.0, 240.0);
        assert_eq!(s.auc, Some((20.0 + 50.0 / 6.0, 20.0 + 200.0 / 6.0 + 20.0)));
        assert_eq!(s.last_val, Some(m.val[3]));
        // the plot areas: one per panel, lined up on the step axis
        let vp = s.val_plot.expect("val panel");
        let ph = i64::from(o.panel_height);
        assert!(
            s.loss_plot.y0 > 0 && s.loss_plot.y1 < ph,
            "{:?}",
            s.loss_plot
        );
        assert!(vp.y0 > ph && vp.y1 < 2 * ph, "{vp:?}");
        assert_eq!((s.loss_plot.x0, s.loss_plot.x1), (vp.x0, vp.x1));
        assert!(s.loss_plot.x1 - s.loss_plot.x0 > i64::from(o.width) * 3 / 4);
        assert!(s.loss_plot.y1 - s.loss_plot.y0 > ph / 2);
        // each series in its own panel
        for c in [RAW_LOSS_RGB, AVG_LOSS_RGB] {
            assert!(count(&img, &s.loss_plot, c) > 100, "loss colour {c:?}");
            assert_eq!(count(&img, &vp, c), 0);
        }
        for c in [
            INPUT_AUC5_RGB,
            REFINED_AUC5_RGB,
            INPUT_AUC10_RGB,
            REFINED_AUC10_RGB,
        ] {
            assert!(count(&img, &vp, c) > 50, "val colour {c:?}");
            assert_eq!(count(&img, &s.loss_plot, c), 0);
        }
        // text outside the plot areas: titles and legends above, tick labels and axis titles
        // left and below
        let w = i64::from(o.width);
        let above = |p: &Rect, top: i64| Rect {
            x0: 0,
            y0: top,
            x1: w - 1,
            y1: p.y0 - 1,
        };
        assert!(ink(&img, &above(&s.loss_plot, 0)) > 300);
        assert!(ink(&img, &above(&vp, ph)) > 300);
        for p in [&s.loss_plot, &vp] {
            let left = Rect {
                x0: 0,
                y0: p.y0,
                x1: p.x0 - 2,
                y1: p.y1,
            };
            assert!(ink(&img, &left) > 100, "y tick labels and title");
            let below = Rect {
                x0: p.x0,
                y0: p.y1 + 2,
                x1: w - 1,
                y1: p.y1 + i64::from(X_LABEL_AREA),
            };
            assert!(ink(&img, &below) > 100, "x tick labels and title");
        }

        // in memory: the same pixels
        let (mem, _) = render_figure(&m, &o).unwrap();
        assert!(mem == img);

        // without val lines: the loss panel only
        std::fs::write(&mpath, metrics_text(false)).unwrap();
        let m = read_metrics(&mpath).unwrap();
        let s = write_figure(&out, &m, &o).unwrap();
        let img = image::open(&out).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (o.width, o.panel_height));
        assert!(s.val_plot.is_none() && s.auc.is_none() && s.last_val.is_none());
        assert!(count(&img, &s.loss_plot, AVG_LOSS_RGB) > 100);
        assert!(img.pixels().all(|p| p.0 != REFINED_AUC5_RGB));
    }

    #[test]
    fn plot_figure_edge_cases() {
        // a single point, small image: a degenerate range is widened, nothing panics
        let m = Metrics {
            train: vec![(3.0, 0.5)],
            val: vec![ValPoint {
                step: 3.0,
                chunks: None,
                input_auc5: f64::NAN,
                refined_auc5: 40.0,
                input_auc10: f64::NAN,
                refined_auc10: f64::NAN,
            }],
        };
        let o = FigureOptions {
            width: 10,
            panel_height: 10,
            ..FigureOptions::default()
        };
        let (img, s) = render_figure(&m, &o).unwrap();
        assert_eq!(img.dimensions(), (200, 300));
        assert_eq!(s.steps, (3.0, 3.0));
        assert_eq!(s.auc, Some((40.0, 40.0)));
        assert!(img.pixels().any(|p| p.0 == AVG_LOSS_RGB));
        assert!(img.pixels().any(|p| p.0 == REFINED_AUC5_RGB));
        // val lines without any finite AUC: no val panel
        let mut m2 = m.clone();
        m2.val[0].refined_auc5 = f64::NAN;
        let (img, s) = render_figure(&m2, &o).unwrap();
        assert_eq!(img.dimensions(), (200, 150));
        assert!(s.val_plot.is_none() && s.last_val.is_none());
        // no training loss yet; absurd sizes
        let e = render_figure(&Metrics::default(), &o).unwrap_err();
        assert!(e.to_string().contains("no finite training loss"), "{e}");
        let huge = FigureOptions {
            width: MAX_SIDE + 1,
            ..FigureOptions::default()
        };
        assert!(render_figure(&m, &huge).is_err());
        // an unwritable output (a directory in the way) names the file
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("curve.png");
        std::fs::create_dir(&out).unwrap();
        let e = write_figure(&out, &m, &o).unwrap_err().to_string();
        assert!(e.contains("curve.png"), "{e}");
    }

    #[test]
    fn plot_metrics_errors_name_file_and_line() {
        let dir = tempfile::tempdir().unwrap();
        let mpath = dir.path().join("metrics.jsonl");
        // a line that is not JSON
        std::fs::write(
            &mpath,
            "{\"step\":1,\"kind\":\"train\",\"loss\":0.5}\n{\"step\":2,\"kind\n",
        )
        .unwrap();
        let e = read_metrics(&mpath).unwrap_err().to_string();
        assert!(e.contains("metrics.jsonl") && e.contains("line 2"), "{e}");
        // JSON, but not an object
        std::fs::write(
            &mpath,
            "\n{\"step\":1,\"kind\":\"train\",\"loss\":0.5}\n\n[1, 2]\n",
        )
        .unwrap();
        let e = read_metrics(&mpath).unwrap_err().to_string();
        assert!(
            e.contains("metrics.jsonl") && e.contains("line 4: not a JSON object"),
            "{e}"
        );
        // a missing file
        let e = read_metrics(&dir.path().join("nope.jsonl"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("nope.jsonl"), "{e}");
        // other kinds, missing steps and null values are skipped
        let m = parse_metrics(
            "{\"step\":1,\"kind\":\"train\",\"loss\":null}\n{\"kind\":\"train\",\"loss\":1}\n\
             {\"step\":2,\"kind\":\"eval\",\"loss\":1}\n{\"step\":3,\"kind\":\"train\",\"loss\":0.25}\n\
             {\"step\":3,\"kind\":\"val\",\"val\":{\"refined_auc5\":12.5}}\n",
            Path::new("m.jsonl"),
        )
        .unwrap();
        assert_eq!(m.train, vec![(3.0, 0.25)]);
        assert_eq!(m.val.len(), 1);
        assert_eq!((m.val[0].chunks, m.val[0].refined_auc5), (None, 12.5));
        assert!(m.val[0].input_auc5.is_nan());
    }
}
