//! Scatter of the surviving DLT points back to the pixels that observe them (`sfm.md` §10).
//!
//! Every kept track writes its point (SfM frame) into every visible view `t` at pixel
//! `(round(u_t), round(v_t))` (round half to even, like `torch.round`); observations rounding
//! outside the image are clamped to the border (official) or dropped (option). Per pixel the
//! points are averaged (f64 accumulation).

use rayon::prelude::*;

use crate::dlt::{DltOutput, DltStatus};
use crate::error::{Result, SfmError};
use crate::matches::Correspondences;

/// Scatter options.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ScatterOptions {
    /// Drop observations whose rounded pixel lies outside the image instead of clamping them to
    /// the border (a later official revision; default off = clamp, as the fixture pins).
    pub drop_outside: bool,
}

/// The scattered point map and its extras (all `[N, h, w]` in pixel order).
#[derive(Debug, Clone, PartialEq)]
pub struct ScatterResult {
    /// `[N, h, w, 3]` `X_s`: mean of the points landing on each pixel; 0 where none.
    pub points: Vec<f32>,
    /// `[N, h, w]` `M_s`: at least one point landed.
    pub mask: Vec<bool>,
    /// `[N, h, w]` number of points landing on each pixel (`dlt_count`).
    pub count: Vec<u32>,
    /// `[N, h, w]` mean reprojection error (ff pixels) of the contributing tracks, 0 where none
    /// (`dlt_reproj`).
    pub reproj: Vec<f32>,
    /// Observations written.
    pub observations: usize,
    /// Observations clamped onto the border.
    pub clamped: usize,
    /// Observations dropped (outside with `drop_outside`, or non-finite).
    pub dropped: usize,
}

/// Rounds an f32 pixel coordinate half-to-even and maps it into `[0, size)`.
/// Returns `(index, was_outside)`, or `None` when non-finite or (with `drop`) outside.
#[inline]
pub fn pixel_index(c: f32, size: usize, drop: bool) -> Option<(usize, bool)> {
    if !c.is_finite() || size == 0 {
        return None;
    }
    let r = c.round_ties_even();
    let max = (size - 1) as f32;
    let outside = r < 0.0 || r > max;
    if outside && drop {
        return None;
    }
    Some((r.clamp(0.0, max) as usize, outside))
}

/// One scatter observation: target pixel (flat) and whether it was clamped (`None` = dropped),
/// and the index of its track in [`DltOutput::tracks`].
pub type ObservationTarget = (Option<(usize, bool)>, usize);

/// Target pixel (flat `n*h*w + y*w + x`) of every observation of every kept track, in the
/// official order: views in order, then tracks in ascending id; `None` for dropped observations.
/// Also returns the index into `dlt.tracks` of each observation's track.
pub fn observation_targets(
    corr: &Correspondences,
    vis: &[bool],
    dlt: &DltOutput,
    opts: &ScatterOptions,
) -> Result<Vec<ObservationTarget>> {
    corr.validate()?;
    let n = corr.dims.n;
    let (h, w) = (corr.dims.h, corr.dims.w);
    let hw = h * w;
    let nt = n * hw;
    if vis.len() != n * nt {
        return Err(SfmError::Shape(format!(
            "scatter: visibility of {} entries, expected {}",
            vis.len(),
            n * nt
        )));
    }
    let kept: Vec<usize> = dlt
        .tracks
        .iter()
        .enumerate()
        .filter(|(_, t)| t.status == DltStatus::Kept)
        .map(|(i, _)| i)
        .collect();
    let mut out = Vec::new();
    for t in 0..n {
        for &ti in &kept {
            let j = dlt.tracks[ti].track;
            if j >= nt {
                return Err(SfmError::Shape(format!(
                    "scatter: track id {j} out of range (N*h*w = {nt})"
                )));
            }
            if !vis[t * nt + j] {
                continue;
            }
            let i = 2 * (t * nt + j);
            let px = pixel_index(corr.matches[i], w, opts.drop_outside);
            let py = pixel_index(corr.matches[i + 1], h, opts.drop_outside);
            let target = match (px, py) {
                (Some((x, ox)), Some((y, oy))) => Some((t * hw + y * w + x, ox || oy)),
                _ => None,
            };
            out.push((target, ti));
        }
    }
    Ok(out)
}

/// Scatters the kept DLT tracks (`sfm.md` §10). `vis` is the DLT visibility `[N, N hw]` used by
/// the triangulation, `corr` the correspondences (ff pixels).
///
/// Views are processed in parallel (rayon): an observation in view `t` only writes pixels of view
/// `t`, and within a view the tracks are visited in ascending id, so every pixel accumulates its
/// points in the official order ([`observation_targets`]) whatever the thread count.
pub fn scatter(
    corr: &Correspondences,
    vis: &[bool],
    dlt: &DltOutput,
    opts: &ScatterOptions,
) -> Result<ScatterResult> {
    corr.validate()?;
    let n = corr.dims.n;
    let (h, w) = (corr.dims.h, corr.dims.w);
    let hw = h * w;
    let nt = n * hw;
    if vis.len() != n * nt {
        return Err(SfmError::Shape(format!(
            "scatter: visibility of {} entries, expected {}",
            vis.len(),
            n * nt
        )));
    }
    let kept: Vec<&crate::dlt::DltTrack> = dlt
        .tracks
        .iter()
        .filter(|t| t.status == DltStatus::Kept)
        .collect();
    if let Some(t) = kept.iter().find(|t| t.track >= nt) {
        return Err(SfmError::Shape(format!(
            "scatter: track id {} out of range (N*h*w = {nt})",
            t.track
        )));
    }
    let px = corr.dims.pixels();
    let mut points = vec![0f32; 3 * px];
    let mut reproj = vec![0f32; px];
    let mut count = vec![0u32; px];
    if px == 0 {
        return Ok(ScatterResult {
            points,
            mask: Vec::new(),
            count,
            reproj,
            observations: 0,
            clamped: 0,
            dropped: 0,
        });
    }
    // compact copy of the kept tracks (id, point, reprojection error): every view reads it once
    let kept_ids: Vec<usize> = kept.iter().map(|t| t.track).collect();
    let kept_vals: Vec<[f64; 4]> = kept
        .iter()
        .map(|t| [t.point[0], t.point[1], t.point[2], t.reproj_mean])
        .collect();
    // per view: (observations, clamped, dropped)
    let stats: Vec<(usize, usize, usize)> = points
        .par_chunks_mut(3 * hw)
        .zip(reproj.par_chunks_mut(hw))
        .zip(count.par_chunks_mut(hw))
        .enumerate()
        .map(|(t, ((pts, rep), cnt))| {
            // one view at a time keeps the random-access accumulators small (cache)
            let mut sum = vec![[0f64; 4]; hw];
            let (mut observations, mut clamped, mut dropped) = (0, 0, 0);
            let vis_t = &vis[t * nt..(t + 1) * nt];
            let m_t = &corr.matches[2 * t * nt..2 * (t + 1) * nt];
            for (&j, val) in kept_ids.iter().zip(&kept_vals) {
                if !vis_t[j] {
                    continue;
                }
                let target = match (
                    pixel_index(m_t[2 * j], w, opts.drop_outside),
                    pixel_index(m_t[2 * j + 1], h, opts.drop_outside),
                ) {
                    (Some((x, ox)), Some((y, oy))) => Some((y * w + x, ox || oy)),
                    _ => None,
                };
                let Some((p, outside)) = target else {
                    dropped += 1;
                    continue;
                };
                observations += 1;
                clamped += usize::from(outside);
                let acc = &mut sum[p];
                for a in 0..4 {
                    acc[a] += val[a];
                }
                cnt[p] = cnt[p].saturating_add(1);
            }
            for p in 0..hw {
                if cnt[p] > 0 {
                    let c = f64::from(cnt[p]);
                    for a in 0..3 {
                        pts[3 * p + a] = (sum[p][a] / c) as f32;
                    }
                    rep[p] = (sum[p][3] / c) as f32;
                }
            }
            (observations, clamped, dropped)
        })
        .collect();
    let (observations, clamped, dropped) = stats
        .iter()
        .fold((0, 0, 0), |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2));
    let mask = count.iter().map(|&c| c > 0).collect();
    Ok(ScatterResult {
        points,
        mask,
        count,
        reproj,
        observations,
        clamped,
        dropped,
    })
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;
    use crate::dlt::DltTrack;
    use ggpt_core::Dims;

    #[test]
    fn rounding_half_to_even_and_clamp() {
        assert_eq!(pixel_index(2.5, 10, false), Some((2, false)));
        assert_eq!(pixel_index(3.5, 10, false), Some((4, false)));
        assert_eq!(pixel_index(-0.5, 10, false), Some((0, false))); // -0 is inside
        assert_eq!(pixel_index(-0.6, 10, false), Some((0, true)));
        assert_eq!(pixel_index(9.5, 10, false), Some((9, true)));
        assert_eq!(pixel_index(9.5, 10, true), None);
        assert_eq!(pixel_index(f32::NAN, 10, false), None);
    }

    fn track(j: usize, p: [f64; 3], status: DltStatus) -> DltTrack {
        DltTrack {
            track: j,
            num_views: 2,
            point: p,
            w: 1.0,
            reproj_mean: 0.5,
            max_angle_deg: 10.0,
            status,
        }
    }

    #[test]
    fn averages_and_clamps() {
        // N = 2, h = 1, w = 3.
        let dims = Dims { n: 2, h: 1, w: 3 };
        let e = 12;
        let mut corr = Correspondences {
            dims,
            matches: vec![0.0; 2 * e],
            scores: vec![1.0; e],
            cycle: vec![0.0; e],
        };
        corr.apply_diagonal();
        // track 0 (view 0, pixel 0) lands in view 1 at x = 1.5 -> 2; track 1 (view 0 pixel 1) at x = 7 -> clamped 2
        let i0 = corr.idx(1, 0, 0);
        corr.matches[2 * i0] = 1.5;
        let i1 = corr.idx(1, 0, 1);
        corr.matches[2 * i1] = 7.0;
        let nt = 6;
        let mut vis = vec![false; 2 * nt];
        for j in 0..3 {
            vis[j] = true;
        }
        for j in 3..6 {
            vis[nt + j] = true;
        }
        vis[nt] = true;
        vis[nt + 1] = true;
        let dlt = DltOutput {
            tracks: vec![
                track(0, [1.0, 2.0, 3.0], DltStatus::Kept),
                track(1, [3.0, 4.0, 5.0], DltStatus::Kept),
                track(2, [9.0, 9.0, 9.0], DltStatus::RejectAngle),
            ],
        };
        let r = scatter(&corr, &vis, &dlt, &ScatterOptions::default()).unwrap();
        assert_eq!(r.count, vec![1, 1, 0, 0, 0, 2]);
        assert_eq!(&r.points[15..18], &[2.0, 3.0, 4.0]);
        assert_eq!(&r.points[0..3], &[1.0, 2.0, 3.0]);
        assert_eq!(r.mask, vec![true, true, false, false, false, true]);
        assert_eq!((r.observations, r.clamped, r.dropped), (4, 1, 0));
        let r = scatter(&corr, &vis, &dlt, &ScatterOptions { drop_outside: true }).unwrap();
        assert_eq!(r.count, vec![1, 1, 0, 0, 0, 1]);
        assert_eq!(r.dropped, 1);
        assert_eq!(r.reproj[5], 0.5);
    }

    /// The parallel per-view scatter equals the sequential accumulation in the official order
    /// ([`observation_targets`]) bit for bit, on random data with collisions, clamps and drops.
    #[test]
    fn parallel_scatter_equals_sequential_official_order() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        let dims = Dims { n: 3, h: 5, w: 7 };
        let (n, hw) = (dims.n, dims.hw());
        let nt = n * hw;
        let e = n * nt;
        let mut corr = Correspondences {
            dims,
            matches: (0..2 * e).map(|_| rng.random_range(-2.0f32..9.0)).collect(),
            scores: vec![1.0; e],
            cycle: vec![0.0; e],
        };
        corr.apply_diagonal();
        let vis: Vec<bool> = (0..e).map(|_| rng.random_bool(0.6)).collect();
        let tracks = (0..nt)
            .map(|j| {
                let p = [
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(1.0..3.0),
                ];
                track(
                    j,
                    p,
                    if rng.random_bool(0.8) {
                        DltStatus::Kept
                    } else {
                        DltStatus::RejectReproj
                    },
                )
            })
            .collect();
        let dlt = DltOutput { tracks };
        for opts in [
            ScatterOptions::default(),
            ScatterOptions { drop_outside: true },
        ] {
            let r = scatter(&corr, &vis, &dlt, &opts).unwrap();
            let px = dims.pixels();
            let (mut sum, mut cnt) = (vec![0f64; 3 * px], vec![0u32; px]);
            let mut dropped = 0;
            for (target, ti) in observation_targets(&corr, &vis, &dlt, &opts).unwrap() {
                match target {
                    Some((p, _)) => {
                        for a in 0..3 {
                            sum[3 * p + a] += dlt.tracks[ti].point[a];
                        }
                        cnt[p] += 1;
                    }
                    None => dropped += 1,
                }
            }
            assert_eq!(r.count, cnt);
            assert_eq!(r.dropped, dropped);
            assert_eq!(dropped > 0, opts.drop_outside);
            for p in 0..px {
                for a in 0..3 {
                    let want = if cnt[p] > 0 {
                        (sum[3 * p + a] / cnt[p] as f64) as f32
                    } else {
                        0.0
                    };
                    assert_eq!(r.points[3 * p + a].to_bits(), want.to_bits(), "pixel {p}");
                }
            }
        }
    }
}
