//! Converting raw matcher outputs to ff pixels (`sfm.md` §2.3).
//!
//! All outputs are ff pixels in the pixel-centre convention (top-left pixel centre = `(0, 0)`),
//! computed in f32 in the operation order of the official PyTorch code so that the downstream
//! strict threshold comparisons see the same values.

use ggpt_core::resize::{BilinearRounding, resize_bilinear};

use crate::error::{Result, SfmError};

/// PyTorch `interpolate(mode = "bilinear", align_corners = false)` (no antialias) of one
/// `in_h x in_w` channel (row-major) to `out_h x out_w`, in f32, with the tap order of PyTorch's
/// channels-last CPU kernel ([`BilinearRounding::ChannelsLastFma`]): bit-identical to the
/// official resize of the matcher outputs.
fn resize_map(
    src: &[f32],
    in_h: usize,
    in_w: usize,
    out_h: usize,
    out_w: usize,
) -> Result<Vec<f32>> {
    resize_bilinear(
        src,
        in_h,
        in_w,
        1,
        out_h,
        out_w,
        BilinearRounding::ChannelsLastFma,
    )
    .map_err(|e| match e {
        ggpt_core::CoreError::Invalid(m) => SfmError::Shape(m),
        other => SfmError::Core(other),
    })
}

/// RoMa v1 / v2 (`sfm.md` §2.3): a warp `[hm, wm, 2]` of normalised *edge* coordinates
/// (`-1` / `+1` = image edges) and its score `[hm, wm]` at matcher resolution are resized
/// bilinearly to `(h, w)` and converted to ff pixels `x = (u + 1) / 2 * w - 0.5`.
/// The score is not zeroed where the warp leaves the image.
/// Returns (`[h*w, 2]` match locations in the target view, `[h*w]` scores).
pub fn roma_to_ff(
    warp: &[f32],
    overlap: &[f32],
    hm: usize,
    wm: usize,
    h: usize,
    w: usize,
) -> Result<(Vec<f32>, Vec<f32>)> {
    if warp.len() != hm * wm * 2 || overlap.len() != hm * wm {
        return Err(SfmError::Shape(format!(
            "RoMa warp/overlap: {} / {} values for matcher resolution {hm}x{wm}",
            warp.len(),
            overlap.len()
        )));
    }
    let ux: Vec<f32> = warp.iter().step_by(2).copied().collect();
    let uy: Vec<f32> = warp.iter().skip(1).step_by(2).copied().collect();
    let rx = resize_map(&ux, hm, wm, h, w)?;
    let ry = resize_map(&uy, hm, wm, h, w)?;
    let score = resize_map(overlap, hm, wm, h, w)?;
    let (wf, hf) = (w as f32, h as f32);
    let mut m = Vec::with_capacity(2 * h * w);
    for (x, y) in rx.iter().zip(&ry) {
        m.push((x + 1.0) / 2.0 * wf - 0.5);
        m.push((y + 1.0) / 2.0 * hf - 0.5);
    }
    Ok((m, score))
}

/// UFM (`sfm.md` §2.3): flow `[2, ho, wo]` (channel-first, output pixels) and covisibility
/// `[ho, wo]` are resized bilinearly to `(h, w)`, the flow scaled by `w / wo`, `h / ho` and the
/// pixel grid added; the score is set to 0 where the warp falls outside `[0, w) x [0, h)`.
/// Returns (`[h*w, 2]` locations, `[h*w]` scores).
pub fn ufm_to_ff(
    flow: &[f32],
    covis: &[f32],
    ho: usize,
    wo: usize,
    h: usize,
    w: usize,
) -> Result<(Vec<f32>, Vec<f32>)> {
    let n = ho * wo;
    if flow.len() != 2 * n || covis.len() != n {
        return Err(SfmError::Shape(format!(
            "UFM flow/covisibility: {} / {} values for output resolution {ho}x{wo}",
            flow.len(),
            covis.len()
        )));
    }
    let fx = resize_map(&flow[..n], ho, wo, h, w)?;
    let fy = resize_map(&flow[n..], ho, wo, h, w)?;
    let mut score = resize_map(covis, ho, wo, h, w)?;
    let sx = w as f32 / wo as f32;
    let sy = h as f32 / ho as f32;
    let mut m = Vec::with_capacity(2 * h * w);
    for k in 0..h * w {
        let x = fx[k] * sx + (k % w) as f32;
        let y = fy[k] * sy + (k / w) as f32;
        m.push(x);
        m.push(y);
        let inside = x >= 0.0 && x < w as f32 && y >= 0.0 && y < h as f32;
        if !inside {
            score[k] = 0.0;
        }
    }
    Ok((m, score))
}

/// Pixel-centre-consistent map of a matcher-pixel coordinate to ff pixels (`sfm.md` §2.3):
/// `x_f = s_x x_m + (s_x - 1) / 2` with `s_x = w / w_m` (same for `y`).
pub fn matcher_to_ff(x_m: f64, y_m: f64, hm: usize, wm: usize, h: usize, w: usize) -> (f64, f64) {
    let sx = w as f64 / wm as f64;
    let sy = h as f64 / hm as f64;
    (sx * x_m + (sx - 1.0) / 2.0, sy * y_m + (sy - 1.0) / 2.0)
}

/// Inverse of [`matcher_to_ff`]: the matcher location of an ff pixel, `x_m = (x_f + 0.5) / s_x - 0.5`.
pub fn ff_to_matcher(x_f: f64, y_f: f64, hm: usize, wm: usize, h: usize, w: usize) -> (f64, f64) {
    let sx = w as f64 / wm as f64;
    let sy = h as f64 / hm as f64;
    ((x_f + 0.5) / sx - 0.5, (y_f + 0.5) / sy - 0.5)
}

/// Generic matcher (`sfm.md` §2.3): a dense warp `[hm, wm, 2]` on matcher pixels whose values are
/// matcher-pixel coordinates of the target image (same matcher resolution), and a score
/// `[hm, wm]`. The warp is sampled at the matcher location of each ff pixel centre (bilinear,
/// border-clamped, which is exactly the `align_corners = false` resize) and its values mapped to
/// ff pixels with [`matcher_to_ff`]. Returns (`[h*w, 2]`, `[h*w]`).
pub fn generic_to_ff(
    warp: &[f32],
    score: &[f32],
    hm: usize,
    wm: usize,
    h: usize,
    w: usize,
) -> Result<(Vec<f32>, Vec<f32>)> {
    if warp.len() != hm * wm * 2 || score.len() != hm * wm {
        return Err(SfmError::Shape(format!(
            "generic warp/score: {} / {} values for {hm}x{wm}",
            warp.len(),
            score.len()
        )));
    }
    let ux: Vec<f32> = warp.iter().step_by(2).copied().collect();
    let uy: Vec<f32> = warp.iter().skip(1).step_by(2).copied().collect();
    let rx = resize_map(&ux, hm, wm, h, w)?;
    let ry = resize_map(&uy, hm, wm, h, w)?;
    let sc = resize_map(score, hm, wm, h, w)?;
    let mut m = Vec::with_capacity(2 * h * w);
    for (x, y) in rx.iter().zip(&ry) {
        let (xf, yf) = matcher_to_ff(*x as f64, *y as f64, hm, wm, h, w);
        m.push(xf as f32);
        m.push(yf as f32);
    }
    Ok((m, sc))
}

/// What a raw dense-matcher output holds (`sfm.md` §2.3, `docs/sfm.md` raw-matcher layout).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RawKind {
    /// RoMa v1 / v2: a warp `[.., Hm, Wm, 2]` of normalised edge coordinates (`-1` / `+1` =
    /// image edges) and a certainty (overlap) `[.., Hm, Wm]` ([`roma_to_ff`]).
    RomaWarp,
    /// UFM: a flow `[.., 2, Ho, Wo]` in output pixels and a covisibility `[.., Ho, Wo]`
    /// ([`ufm_to_ff`]).
    UfmFlow,
    /// A generic matcher: a warp `[.., Hm, Wm, 2]` in matcher-pixel coordinates and a score
    /// `[.., Hm, Wm]` ([`generic_to_ff`]).
    PixelWarp,
    /// Already at ff resolution in ff pixels (pixel-centre convention): matches
    /// `[.., h, w, 2]` or `[.., h*w, 2]` and scores `[.., h, w]` or `[.., h*w]` (the official
    /// `pred_matches` / `pred_scores`).
    FfPixels,
}

/// Order of the two leading view axes of a pair array.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PairLayout {
    /// `[s, t]`: entry `[s, t]` matches the pixels of view `s` into view `t` (the raw output
    /// of the official `match_dense`, RoMa's `warp_AB` stacked by `(A, B)`).
    SourceTarget,
    /// `[t, s]`: the official `match_images` output (`pred_matches`) and `MatchSet`'s layout.
    TargetSource,
}

/// One raw dense-matcher output for all ordered view pairs: `primary` (warp / flow / matches)
/// and `score`, each with its shape, the two leading axes being the views `[N, N]` in `layout`
/// order. Diagonal entries are ignored.
#[derive(Debug, Clone, Copy)]
pub struct RawMatches<'a> {
    /// What the arrays hold.
    pub kind: RawKind,
    /// Order of the view axes.
    pub layout: PairLayout,
    /// Warp / flow / matches values (C order).
    pub primary: &'a [f32],
    /// Shape of `primary`.
    pub primary_shape: &'a [usize],
    /// Certainty / covisibility / score values (C order).
    pub score: &'a [f32],
    /// Shape of `score`.
    pub score_shape: &'a [usize],
}

impl RawMatches<'_> {
    /// Converts to ff pixels for a scene of `n` views at ff resolution `h x w`: the `MatchSet`
    /// layout `[t, s, k]` (`pred_matches [N, N, h*w, 2]`, `pred_scores [N, N, h*w]`; no cycle
    /// error: the SfM stage computes it). `what` names the arrays in errors (a file and key, or
    /// the Python argument).
    pub fn to_ff(&self, n: usize, h: usize, w: usize, what: &str) -> Result<(Vec<f32>, Vec<f32>)> {
        let hw = h * w;
        let shape_err = |expected: String| {
            SfmError::Shape(format!(
                "{what}: shapes {:?} / {:?}, expected {expected} (the feed-forward prediction has N={n} views at {h}x{w})",
                self.primary_shape, self.score_shape
            ))
        };
        let lead = |s: &[usize]| s.len() >= 2 && s[0] == n && s[1] == n;
        if !lead(self.primary_shape) || !lead(self.score_shape) {
            return Err(shape_err(format!("[N={n}, N={n}, ...] for both")));
        }
        let (p, sc) = (&self.primary_shape[2..], &self.score_shape[2..]);
        // (per-pair primary length, per-pair score length, the pair's conversion)
        type Convert<'b> = Box<dyn Fn(&[f32], &[f32]) -> Result<(Vec<f32>, Vec<f32>)> + 'b>;
        let (pl, sl, convert): (usize, usize, Convert<'_>) = match (self.kind, p, sc) {
            (RawKind::RomaWarp, [hm, wm, 2], [a, b]) if (a, b) == (hm, wm) => {
                let (hm, wm) = (*hm, *wm);
                (
                    hm * wm * 2,
                    hm * wm,
                    Box::new(move |x: &[f32], y: &[f32]| roma_to_ff(x, y, hm, wm, h, w)),
                )
            }
            (RawKind::PixelWarp, [hm, wm, 2], [a, b]) if (a, b) == (hm, wm) => {
                let (hm, wm) = (*hm, *wm);
                (
                    hm * wm * 2,
                    hm * wm,
                    Box::new(move |x: &[f32], y: &[f32]| generic_to_ff(x, y, hm, wm, h, w)),
                )
            }
            (RawKind::UfmFlow, [2, ho, wo], [a, b]) if (a, b) == (ho, wo) => {
                let (ho, wo) = (*ho, *wo);
                (
                    2 * ho * wo,
                    ho * wo,
                    Box::new(move |x: &[f32], y: &[f32]| ufm_to_ff(x, y, ho, wo, h, w)),
                )
            }
            (RawKind::FfPixels, pm, ps)
                if (pm == [h, w, 2] || pm == [hw, 2]) && (ps == [h, w] || ps == [hw]) =>
            {
                (
                    2 * hw,
                    hw,
                    Box::new(|x: &[f32], y: &[f32]| Ok((x.to_vec(), y.to_vec()))),
                )
            }
            (kind, _, _) => {
                return Err(shape_err(match kind {
                    RawKind::RomaWarp | RawKind::PixelWarp => {
                        "[N, N, Hm, Wm, 2] / [N, N, Hm, Wm]".into()
                    }
                    RawKind::UfmFlow => "[N, N, 2, Ho, Wo] / [N, N, Ho, Wo]".into(),
                    RawKind::FfPixels => {
                        format!("[N, N, {h}, {w}, 2] / [N, N, {h}, {w}] (or h*w = {hw} flattened)")
                    }
                }));
            }
        };
        if self.primary.len() != n * n * pl || self.score.len() != n * n * sl {
            return Err(SfmError::Shape(format!(
                "{what}: {} / {} values for shapes {:?} / {:?}",
                self.primary.len(),
                self.score.len(),
                self.primary_shape,
                self.score_shape
            )));
        }
        let mut matches = vec![0f32; 2 * n * n * hw];
        let mut scores = vec![0f32; n * n * hw];
        for s in 0..n {
            for t in 0..n {
                if s == t {
                    continue;
                }
                let q = match self.layout {
                    PairLayout::SourceTarget => s * n + t,
                    PairLayout::TargetSource => t * n + s,
                };
                let (m, score) = convert(
                    &self.primary[q * pl..(q + 1) * pl],
                    &self.score[q * sl..(q + 1) * sl],
                )?;
                let b = (t * n + s) * hw;
                matches[2 * b..2 * (b + hw)].copy_from_slice(&m);
                scores[b..b + hw].copy_from_slice(&score);
            }
        }
        Ok((matches, scores))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn raw_pairs_follow_their_layout_and_shapes_are_checked() {
        // 2 views at ff 1x2, generic ff-pixel matches: pair [0 -> 1] = x + 10, [1 -> 0] = x + 20.
        let (n, h, w) = (2, 1, 2);
        let mut m = vec![0f32; n * n * h * w * 2];
        let mut sc = vec![0f32; n * n * h * w];
        for (q, add) in [(1usize, 10.0f32), (2, 20.0)] {
            for k in 0..2 {
                m[(q * 2 + k) * 2] = k as f32 + add;
                sc[q * 2 + k] = add / 100.0;
            }
        }
        let raw = RawMatches {
            kind: RawKind::FfPixels,
            layout: PairLayout::SourceTarget,
            primary: &m,
            primary_shape: &[2, 2, 1, 2, 2],
            score: &sc,
            score_shape: &[2, 2, 1, 2],
        };
        let (pm, ps) = raw.to_ff(n, h, w, "m").unwrap();
        // [t=1, s=0] is the source-target pair (0, 1): +10
        let at = |t: usize, s: usize, k: usize| pm[((t * n + s) * 2 + k) * 2];
        assert_eq!((at(1, 0, 1), at(0, 1, 1)), (11.0, 21.0));
        assert_eq!(ps[n * 2], 0.1);
        let (pm2, _) = RawMatches {
            layout: PairLayout::TargetSource,
            ..raw
        }
        .to_ff(n, h, w, "m")
        .unwrap();
        assert_eq!(pm2[(n * 2 + 1) * 2], 21.0);
        let e = raw.to_ff(3, h, w, "matches[0]").unwrap_err().to_string();
        assert!(e.contains("matches[0]") && e.contains("N=3"), "{e}");
        let e = RawMatches {
            kind: RawKind::UfmFlow,
            ..raw
        }
        .to_ff(n, h, w, "m")
        .unwrap_err()
        .to_string();
        assert!(e.contains("[N, N, 2, Ho, Wo]"), "{e}");
    }

    #[test]
    fn roma_edges_map_to_pixel_edges() {
        // 1x2 matcher warp with u = -1 (left edge) and +1 (right edge), resized to 1x2 (identity).
        let warp = [-1.0, -1.0, 1.0, 1.0];
        let (m, s) = roma_to_ff(&warp, &[0.3, 0.7], 1, 2, 1, 2).unwrap();
        assert_eq!(m, vec![-0.5, -0.5, 1.5, 0.5]);
        assert_eq!(s, vec![0.3, 0.7]);
    }

    #[test]
    fn ufm_adds_grid_and_zeroes_outside() {
        // 1x3 at half resolution of 1x... use same resolution: flow +1 in x.
        let flow = [1.0, 1.0, 1.0, 0.0, 0.0, 0.0];
        let (m, s) = ufm_to_ff(&flow, &[0.9, 0.8, 0.7], 1, 3, 1, 3).unwrap();
        assert_eq!(m, vec![1.0, 0.0, 2.0, 0.0, 3.0, 0.0]);
        assert_eq!(s, vec![0.9, 0.8, 0.0]);
    }

    #[test]
    fn ufm_scales_flow() {
        // output 1x2, ff 1x4: flow of 1 output pixel = 2 ff pixels.
        let flow = [1.0, 1.0, 0.0, 0.0];
        let (m, _) = ufm_to_ff(&flow, &[1.0, 1.0], 1, 2, 1, 4).unwrap();
        let xs: Vec<f32> = m.iter().step_by(2).copied().collect();
        assert_eq!(xs, vec![2.0, 3.0, 4.0, 5.0]);
    }

    #[test]
    fn generic_mapping_is_pixel_centre_consistent() {
        // matcher 2 px wide, ff 4 px: matcher pixel 0 covers ff [-.5, 1.5] -> centre 0.5.
        assert_eq!(matcher_to_ff(0.0, 0.0, 1, 2, 1, 4), (0.5, 0.0));
        assert_eq!(matcher_to_ff(-0.5, 0.0, 1, 2, 1, 4).0, -0.5);
        let (xm, _) = ff_to_matcher(0.5, 0.0, 1, 2, 1, 4);
        assert_eq!(xm, 0.0);
        // identity warp on matcher pixels maps to identity on ff pixels (inside the clamp zone).
        let warp = [0.0, 0.0, 1.0, 0.0];
        let (m, _) = generic_to_ff(&warp, &[1.0, 1.0], 1, 2, 1, 4).unwrap();
        let xs: Vec<f32> = m.iter().step_by(2).copied().collect();
        assert_eq!(xs, vec![0.5, 1.0, 2.0, 2.5]);
    }
}
