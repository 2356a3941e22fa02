//! BA track selection (`sfm.md` §6): greedy per-view selection of reliable tracks, the
//! Shi–Tomasi substitute ranking score, and the BA observations / initial points of the
//! selected tracks.
//!
//! A track is `j = s * hw + k` (source view `s`, pixel `k = y * w + x`). Visibility masks are
//! `[t, j]` (`t * N hw + j`), i.e. the target-major correspondence layout flattened.

use nalgebra::Point3;

use crate::error::{Result, SfmError};
use crate::matches::Correspondences;

/// A track whose initial point has a coordinate with `|c| >= 3000` (or a non-finite one) is not
/// added to the BA (`sfm.md` §7.1, official upper bound + [project] abs / non-finite).
pub const MAX_BA_POINT_COORD: f64 = 3000.0;

/// Record of the greedy selection (mirrors the `tracks/*` fixture tensors).
#[derive(Debug, Clone, PartialEq)]
pub struct TrackSelection {
    /// Track ids in selection order (per view turn: descending ranking score).
    pub selected_order: Vec<usize>,
    /// The view whose turn selected each entry of `selected_order`.
    pub selected_view: Vec<usize>,
    /// `[N hw]` selection mask.
    pub selected: Vec<bool>,
    /// Per view turn: `mintrack_per_view - coverage` before the turn.
    pub to_select_num: Vec<i64>,
    /// `[n][view]` coverage at the start of view `n`'s turn.
    pub coverage_before: Vec<Vec<usize>>,
    /// Candidates per turn, `-1` when the turn was skipped.
    pub num_candidates: Vec<i64>,
    /// Coverage per view after the loop.
    pub coverage_final: Vec<usize>,
}

impl TrackSelection {
    /// Selected track ids in ascending order (BA point order).
    pub fn track_ids(&self) -> Vec<usize> {
        let mut ids = self.selected_order.clone();
        ids.sort_unstable();
        ids
    }
}

/// Greedy per-view BA track selection (`sfm.md` §6.1).
///
/// * `m_ba`: `[N, N hw]` BA visibility `[t, j]` (diagonal included, i.e. `m_ba[s, s hw + k]` true);
/// * `rank`: `[N hw]` ranking score of each track's source pixel (higher = better; NaN ranks last);
/// * ties are broken by the lower track index.
pub fn select_ba_tracks(
    m_ba: &[bool],
    n: usize,
    hw: usize,
    rank: &[f32],
    mintrack_per_view: usize,
) -> Result<TrackSelection> {
    let nt = n * hw;
    if m_ba.len() != n * nt {
        return Err(SfmError::Shape(format!(
            "track selection: BA mask of {} entries, expected {}",
            m_ba.len(),
            n * nt
        )));
    }
    if rank.len() != nt {
        return Err(SfmError::Shape(format!(
            "track selection: ranking score of {} entries, expected N*h*w = {nt}",
            rank.len()
        )));
    }
    let vis_count: Vec<u32> = (0..nt)
        .map(|j| (0..n).filter(|&t| m_ba[t * nt + j]).count() as u32)
        .collect();
    let mut sel = TrackSelection {
        selected_order: Vec::new(),
        selected_view: Vec::new(),
        selected: vec![false; nt],
        to_select_num: Vec::with_capacity(n),
        coverage_before: Vec::with_capacity(n),
        num_candidates: Vec::with_capacity(n),
        coverage_final: vec![0; n],
    };
    let key = |j: usize| -> f32 {
        let r = rank[j];
        if r.is_nan() { f32::NEG_INFINITY } else { r }
    };
    for view in 0..n {
        let need = mintrack_per_view as i64 - sel.coverage_final[view] as i64;
        sel.to_select_num.push(need);
        sel.coverage_before.push(sel.coverage_final.clone());
        if need <= 0 {
            sel.num_candidates.push(-1);
            continue;
        }
        let row = &m_ba[view * nt..(view + 1) * nt];
        let mut cand: Vec<usize> = (0..nt)
            .filter(|&j| row[j] && vis_count[j] >= 2 && !sel.selected[j])
            .collect();
        sel.num_candidates.push(cand.len() as i64);
        let cmp = |a: &usize, b: &usize| key(*b).total_cmp(&key(*a)).then(a.cmp(b));
        let take = (need as usize).min(cand.len());
        if take < cand.len() && take > 0 {
            cand.select_nth_unstable_by(take - 1, cmp);
            cand.truncate(take);
        }
        cand.sort_unstable_by(cmp);
        cand.truncate(take);
        for &j in &cand {
            sel.selected[j] = true;
            sel.selected_order.push(j);
            sel.selected_view.push(view);
            for t in 0..n {
                if m_ba[t * nt + j] {
                    sel.coverage_final[t] += 1;
                }
            }
        }
    }
    Ok(sel)
}

/// Shi–Tomasi corner score (`sfm.md` §6.2, [project] substitute for SuperPoint) of every pixel of
/// every view: grey `0.299 R + 0.587 G + 0.114 B` (f32), 3x3 Sobel gradients, 5x5 structure tensor
/// (replicated borders everywhere), smaller eigenvalue `(a + c)/2 - sqrt(((a - c)/2)^2 + b^2)`.
/// `images`: `[N, h, w, 3]` RGB in `[0, 1]`. Returns `[N hw]`.
pub fn shi_tomasi(images: &[f32], n: usize, h: usize, w: usize) -> Result<Vec<f32>> {
    let hw = h * w;
    if images.len() != 3 * n * hw || h == 0 || w == 0 {
        return Err(SfmError::Shape(format!(
            "shi_tomasi: {} image values for N={n} h={h} w={w}",
            images.len()
        )));
    }
    let mut out = Vec::with_capacity(n * hw);
    let clampi = |v: isize, hi: usize| -> usize { v.clamp(0, hi as isize - 1) as usize };
    for v in 0..n {
        let img = &images[3 * v * hw..3 * (v + 1) * hw];
        let g: Vec<f32> = img
            .chunks_exact(3)
            .map(|p| 0.299f32 * p[0] + 0.587f32 * p[1] + 0.114f32 * p[2])
            .collect();
        let at = |y: isize, x: isize| -> f64 { g[clampi(y, h) * w + clampi(x, w)] as f64 };
        let mut gx = vec![0f64; hw];
        let mut gy = vec![0f64; hw];
        for y in 0..h as isize {
            for x in 0..w as isize {
                let k = y as usize * w + x as usize;
                gx[k] = (at(y - 1, x + 1) + 2.0 * at(y, x + 1) + at(y + 1, x + 1))
                    - (at(y - 1, x - 1) + 2.0 * at(y, x - 1) + at(y + 1, x - 1));
                gy[k] = (at(y + 1, x - 1) + 2.0 * at(y + 1, x) + at(y + 1, x + 1))
                    - (at(y - 1, x - 1) + 2.0 * at(y - 1, x) + at(y - 1, x + 1));
            }
        }
        for y in 0..h as isize {
            for x in 0..w as isize {
                let (mut a, mut b, mut c) = (0f64, 0f64, 0f64);
                for dy in -2..=2 {
                    for dx in -2..=2 {
                        let q = clampi(y + dy, h) * w + clampi(x + dx, w);
                        a += gx[q] * gx[q];
                        b += gx[q] * gy[q];
                        c += gy[q] * gy[q];
                    }
                }
                let score = (a + c) / 2.0 - (((a - c) / 2.0).powi(2) + b * b).sqrt();
                out.push(score as f32);
            }
        }
    }
    Ok(out)
}

/// One BA observation: view, index of the point in [`BaTracks::points`], location (ff pixels,
/// pixel-centre convention).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackObservation {
    /// View index.
    pub view: usize,
    /// Index into [`BaTracks::points`].
    pub point: usize,
    /// `(x, y)` in ff pixels (pixel-centre convention), the f32 match widened.
    pub xy: [f64; 2],
}

/// BA input built from the selected tracks (`sfm.md` §7.1 problem layout).
#[derive(Debug, Clone, PartialEq)]
pub struct BaTracks {
    /// Track ids of the BA points, ascending (BA point `i` = COLMAP point id `i + 1`).
    pub track_ids: Vec<usize>,
    /// Initial points `X_d[s_j, k_j]` (feed-forward frame, scene units).
    pub points: Vec<Point3<f64>>,
    /// Observations listed per view (in order), then by ascending point index.
    pub observations: Vec<TrackObservation>,
    /// Selected tracks left out because their initial point is non-finite or has `|c| >= 3000`.
    pub excluded: usize,
}

/// Builds the BA observations and initial points of the selected tracks.
///
/// * `selected_ids`: selected track ids (any order; sorted here);
/// * `m_ba`: `[N, N hw]` BA visibility; `corr`: the correspondences (ff pixels);
/// * `ff_points`: `[N, h, w, 3]` feed-forward points (feed-forward frame).
pub fn build_ba_tracks(
    selected_ids: &[usize],
    m_ba: &[bool],
    corr: &Correspondences,
    ff_points: &[f32],
) -> Result<BaTracks> {
    corr.validate()?;
    let n = corr.dims.n;
    let hw = corr.dims.hw();
    let nt = n * hw;
    if m_ba.len() != n * nt || ff_points.len() != 3 * nt {
        return Err(SfmError::Shape(format!(
            "BA tracks: mask of {} / ff points of {} values, expected {} / {}",
            m_ba.len(),
            ff_points.len(),
            n * nt,
            3 * nt
        )));
    }
    let mut ids: Vec<usize> = selected_ids.to_vec();
    ids.sort_unstable();
    ids.dedup();
    let mut track_ids = Vec::with_capacity(ids.len());
    let mut points = Vec::with_capacity(ids.len());
    let mut excluded = 0;
    for &j in &ids {
        let p = ff_points
            .get(3 * j..3 * j + 3)
            .ok_or_else(|| SfmError::Shape(format!("track id {j} out of range")))?;
        let pt = Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        if pt
            .iter()
            .any(|c| !c.is_finite() || c.abs() >= MAX_BA_POINT_COORD)
        {
            excluded += 1;
            continue;
        }
        track_ids.push(j);
        points.push(pt);
    }
    let mut observations = Vec::new();
    for t in 0..n {
        for (pi, &j) in track_ids.iter().enumerate() {
            if m_ba[t * nt + j] {
                let (s, k) = (j / hw, j % hw);
                let i = corr.idx(t, s, k);
                observations.push(TrackObservation {
                    view: t,
                    point: pi,
                    xy: [corr.matches[2 * i] as f64, corr.matches[2 * i + 1] as f64],
                });
            }
        }
    }
    Ok(BaTracks {
        track_ids,
        points,
        observations,
        excluded,
    })
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;
    use ggpt_core::Dims;

    #[test]
    fn greedy_selection_counts_and_ties() {
        // N = 2, hw = 3: tracks 0..6. Visibility rows [t][j].
        let n = 2;
        let hw = 3;
        let mut m = vec![false; n * n * hw];
        let nt = n * hw;
        // diagonal: view 0 sees its tracks 0..3, view 1 its tracks 3..6
        for j in 0..3 {
            m[j] = true;
        }
        for j in 3..6 {
            m[nt + j] = true;
        }
        // tracks 0, 1 of view 0 also seen in view 1; track 4 of view 1 seen in view 0
        m[nt] = true;
        m[nt + 1] = true;
        m[4] = true;
        let rank = [0.5, 0.5, 0.9, 0.1, 0.2, 0.3];
        let s = select_ba_tracks(&m, n, hw, &rank, 1).unwrap();
        // view 0: candidates 0, 1, 4 (2 has only one view); best rank 0.5 tie -> track 0
        assert_eq!(s.selected_order, vec![0]);
        assert_eq!(s.num_candidates, vec![3, -1]);
        assert_eq!(s.coverage_final, vec![1, 1]);
        let s = select_ba_tracks(&m, n, hw, &rank, 2).unwrap();
        assert_eq!(s.selected_order, vec![0, 1]);
        assert_eq!(s.to_select_num, vec![2, 0]);
        let s = select_ba_tracks(&m, n, hw, &rank, 3).unwrap();
        assert_eq!(s.selected_order, vec![0, 1, 4]);
        assert_eq!(s.selected_view, vec![0, 0, 0]);
        assert_eq!(s.track_ids(), vec![0, 1, 4]);
        assert!(select_ba_tracks(&m, n, hw, &rank[..5], 3).is_err());
    }

    #[test]
    fn shi_tomasi_flat_edge_corner() {
        // flat image: 0 everywhere
        let (h, w) = (9, 9);
        let flat = vec![0.5f32; 3 * h * w];
        assert!(
            shi_tomasi(&flat, 1, h, w)
                .unwrap()
                .iter()
                .all(|v| v.abs() < 1e-9)
        );
        // vertical edge: a > 0, b = c = 0 -> smaller eigenvalue 0
        let mut edge = vec![0.0f32; 3 * h * w];
        for y in 0..h {
            for x in 5..w {
                for c in 0..3 {
                    edge[3 * (y * w + x) + c] = 1.0;
                }
            }
        }
        let e = shi_tomasi(&edge, 1, h, w).unwrap();
        assert!(e.iter().all(|v| v.abs() < 1e-6), "{e:?}");
        // corner: bright quadrant -> positive min eigenvalue at the corner
        let mut corner = vec![0.0f32; 3 * h * w];
        for y in 4..h {
            for x in 4..w {
                for c in 0..3 {
                    corner[3 * (y * w + x) + c] = 1.0;
                }
            }
        }
        let s = shi_tomasi(&corner, 1, h, w).unwrap();
        let at = s[4 * w + 4];
        assert!(at > 1.0, "{at}");
        assert!(at >= s[8 * w + 8] && at > s[0]);
        // manual value at the corner pixel (3,3)-(4,4) region: check symmetry x <-> y
        assert!((s[4 * w + 3] - s[3 * w + 4]).abs() < 1e-5);
    }

    /// `g = 0.01 x y`: interior Sobel gradients are `gx = 0.08 y`, `gy = 0.08 x`; the score is
    /// the smaller eigenvalue of their 5x5 structure tensor.
    #[test]
    fn shi_tomasi_exact_value_on_bilinear_image() {
        let (h, w) = (11, 12);
        let mut img = vec![0f32; 3 * h * w];
        for y in 0..h {
            for x in 0..w {
                let g = 0.01 * (x * y) as f32;
                img[3 * (y * w + x)..3 * (y * w + x) + 3].copy_from_slice(&[g, g, g]);
            }
        }
        let s = shi_tomasi(&img, 1, h, w).unwrap();
        for (x0, y0) in [(4usize, 5usize), (6, 3), (8, 7)] {
            let (mut a, mut b, mut c) = (0f64, 0f64, 0f64);
            for y in y0 - 2..=y0 + 2 {
                for x in x0 - 2..=x0 + 2 {
                    let (gx, gy) = (0.08 * y as f64, 0.08 * x as f64);
                    a += gx * gx;
                    b += gx * gy;
                    c += gy * gy;
                }
            }
            let want = (a + c) / 2.0 - (((a - c) / 2.0).powi(2) + b * b).sqrt();
            let got = s[y0 * w + x0] as f64;
            assert!(
                (got - want).abs() <= 1e-4 * want.abs().max(1e-3),
                "({x0},{y0}): {got} vs {want}"
            );
        }
    }

    #[test]
    fn ba_tracks_layout_and_exclusion() {
        let dims = Dims { n: 2, h: 1, w: 2 };
        let e = 8;
        let mut corr = Correspondences {
            dims,
            matches: (0..2 * e).map(|v| v as f32).collect(),
            scores: vec![1.0; e],
            cycle: vec![0.0; e],
        };
        corr.apply_diagonal();
        let m = vec![true; 8];
        let mut ff = vec![1.0f32; 12];
        ff[3 * 2] = 3000.0; // track 2 excluded
        let b = build_ba_tracks(&[3, 0, 2], &m, &corr, &ff).unwrap();
        assert_eq!(b.track_ids, vec![0, 3]);
        assert_eq!(b.excluded, 1);
        let obs: Vec<(usize, usize)> = b.observations.iter().map(|o| (o.view, o.point)).collect();
        assert_eq!(obs, vec![(0, 0), (0, 1), (1, 0), (1, 1)]);
        // view 0 observation of track 3 (s = 1, k = 1) = matches[t=0, s=1, k=1]
        let i = corr.idx(0, 1, 1);
        assert_eq!(
            b.observations[1].xy,
            [corr.matches[2 * i] as f64, corr.matches[2 * i + 1] as f64]
        );
        // source view observation = pixel centre
        assert_eq!(b.observations[0].xy, [0.0, 0.0]);
    }
}
