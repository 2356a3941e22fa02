//! Image / map resizing with PyTorch's `F.interpolate` semantics: bilinear with
//! `align_corners = False` and no antialias ([`resize_bilinear`]), and `nearest-exact`
//! ([`resize_nearest_exact`]). The one implementation used by the GGPT_eval preprocessing, the
//! infer-folder reader and the SfM matcher conversion.
//!
//! Source indices and weights are computed in `f32` like PyTorch's
//! `compute_indices_weights_linear`: output index `i` reads source coordinate
//! `max((i + 0.5) in / out - 0.5, 0)`, the upper neighbour clamped to `in - 1`. The two
//! [`BilinearRounding`] variants differ only in how the four taps are combined, i.e. in `f32`
//! rounding; each reproduces one of PyTorch's CPU code paths, so callers pick the one their
//! reference was computed with.

use crate::{CoreError, Result};

/// How the four taps of a bilinear sample are combined (both use the same indices and weights).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BilinearRounding {
    /// Separable interpolation without fused multiply-adds,
    /// `(1 - ly) ((1 - lx) a00 + lx a01) + ly ((1 - lx) a10 + lx a11)`: PyTorch's generic
    /// (channels-first) CPU loop. Used for RGB images (agrees with the GGPT_eval reference
    /// images to `f32` rounding).
    Separable,
    /// PyTorch's channels-last scalar CPU kernel compiled with FMA contraction,
    /// `fma(a11, w11, fma(a10, w10, fma(a00, w00, a01 w01)))` with `w_ab = wy_a wx_b`: the
    /// official RoMa score / warp resize, reproduced bit for bit (`sfm_small` fixture).
    ChannelsLastFma,
}

/// Source taps `(i0, i1, w0, w1)` of each output index along one axis (PyTorch
/// `compute_indices_weights_linear`, `align_corners = false`; `input >= 1`).
fn linear_taps(input: usize, output: usize) -> Vec<(usize, usize, f32, f32)> {
    let scale = input as f32 / output as f32;
    (0..output)
        .map(|i| {
            let real = ((i as f32 + 0.5) * scale - 0.5).max(0.0);
            let i0 = (real.floor() as usize).min(input - 1);
            let lambda = (real - i0 as f32).clamp(0.0, 1.0);
            let i1 = if i0 < input - 1 { i0 + 1 } else { i0 };
            (i0, i1, 1.0 - lambda, lambda)
        })
        .collect()
}

/// Bilinear resize (`align_corners = False`, no antialias) of one `in_h x in_w x channels`
/// row-major `f32` image (channels interleaved; `channels = 1` for a single map) to
/// `out_h x out_w x channels`, with the tap combination `rounding`.
///
/// Errors when `src` does not hold `in_h * in_w * channels` values or a dimension is 0.
pub fn resize_bilinear(
    src: &[f32],
    in_h: usize,
    in_w: usize,
    channels: usize,
    out_h: usize,
    out_w: usize,
    rounding: BilinearRounding,
) -> Result<Vec<f32>> {
    if in_h == 0 || in_w == 0 || channels == 0 || src.len() != in_h * in_w * channels {
        return Err(CoreError::Invalid(format!(
            "resize: {} values for a {in_h}x{in_w} image of {channels} channel(s)",
            src.len()
        )));
    }
    let (ys, xs) = (linear_taps(in_h, out_h), linear_taps(in_w, out_w));
    let row_len = in_w * channels;
    let mut out = Vec::with_capacity(out_h * out_w * channels);
    for &(y0, y1, wy0, wy1) in &ys {
        let r0 = &src[y0 * row_len..(y0 + 1) * row_len];
        let r1 = &src[y1 * row_len..(y1 + 1) * row_len];
        for &(x0, x1, wx0, wx1) in &xs {
            let (c0, c1) = (x0 * channels, x1 * channels);
            for ch in 0..channels {
                let (a00, a01) = (r0[c0 + ch], r0[c1 + ch]);
                let (a10, a11) = (r1[c0 + ch], r1[c1 + ch]);
                out.push(match rounding {
                    BilinearRounding::Separable => {
                        let top = wx0 * a00 + wx1 * a01;
                        let bot = wx0 * a10 + wx1 * a11;
                        wy0 * top + wy1 * bot
                    }
                    BilinearRounding::ChannelsLastFma => {
                        let (w00, w01, w10, w11) = (wy0 * wx0, wy0 * wx1, wy1 * wx0, wy1 * wx1);
                        a11.mul_add(w11, a10.mul_add(w10, a00.mul_add(w00, a01 * w01)))
                    }
                });
            }
        }
    }
    Ok(out)
}

/// Nearest-exact source index `min(floor((i + 0.5) * in / out), in - 1)` (f32, like PyTorch).
fn nearest_exact(out: usize, inp: usize) -> Vec<usize> {
    let scale = inp as f32 / out as f32;
    (0..out)
        .map(|i| (((i as f32 + 0.5) * scale).floor() as usize).min(inp.saturating_sub(1)))
        .collect()
}

/// Nearest-exact resize (PyTorch `mode = "nearest-exact"`) of one `H x W` f32 map; values
/// outside `src` (a short input) read as 0.
pub fn resize_nearest_exact(
    src: &[f32],
    hin: usize,
    win: usize,
    hout: usize,
    wout: usize,
) -> Vec<f32> {
    let (iy, ix) = (nearest_exact(hout, hin), nearest_exact(wout, win));
    iy.iter()
        .flat_map(|&y| {
            ix.iter()
                .map(move |&x| src.get(y * win + x).copied().unwrap_or(0.0))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bilinear_identity_upsample_downsample_and_errors() {
        for r in [
            BilinearRounding::Separable,
            BilinearRounding::ChannelsLastFma,
        ] {
            let src = [0.0f32, 1.0, 2.0, 3.0];
            assert_eq!(
                resize_bilinear(&src, 2, 2, 1, 2, 2, r).unwrap(),
                src.to_vec()
            );
            // 1 x 2 -> 1 x 4: PyTorch gives [0, 0.25, 0.75, 1]
            let out = resize_bilinear(&[0.0, 1.0], 1, 2, 1, 1, 4, r).unwrap();
            assert_eq!(out, vec![0.0, 0.25, 0.75, 1.0]);
            // 1 x 4 -> 1 x 2 (downsample): source coords 0.5, 2.5
            let out = resize_bilinear(&[0.0, 1.0, 2.0, 3.0], 1, 4, 1, 1, 2, r).unwrap();
            assert_eq!(out, vec![0.5, 2.5]);
            assert!(resize_bilinear(&[0.0; 3], 2, 2, 1, 1, 1, r).is_err());
            assert!(resize_bilinear(&[], 0, 2, 1, 1, 1, r).is_err());
        }
    }

    #[test]
    fn channels_are_interleaved_and_resized_independently() {
        // 2 x 2 x 2: channel 1 = 10 x channel 0.
        let src = [0.0f32, 0.0, 1.0, 10.0, 2.0, 20.0, 3.0, 30.0];
        let one = resize_bilinear(
            &[0.0, 1.0, 2.0, 3.0],
            2,
            2,
            1,
            3,
            5,
            BilinearRounding::Separable,
        )
        .unwrap();
        let two = resize_bilinear(&src, 2, 2, 2, 3, 5, BilinearRounding::Separable).unwrap();
        assert_eq!(two.len(), 2 * one.len());
        for (i, v) in one.iter().enumerate() {
            assert_eq!(two[2 * i], *v);
            assert!((two[2 * i + 1] - 10.0 * v).abs() < 1e-5);
        }
    }

    #[test]
    fn nearest_exact_indices() {
        // 1 x 4 -> 1 x 2: source indices floor(0.5 * 2) = 1, floor(1.5 * 2) = 3.
        assert_eq!(
            resize_nearest_exact(&[0.0, 1.0, 2.0, 3.0], 1, 4, 1, 2),
            vec![1.0, 3.0]
        );
    }
}
