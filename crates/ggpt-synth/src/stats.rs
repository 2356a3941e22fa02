//! Diagnostics of a generated scene: feed-forward point accuracy (AUC@5/10 cm after a Sim(3)
//! alignment to GT), confidence/error rank correlation, match statistics (score / cycle-error
//! pass rates). Used by the binary's report and by the tests; not part of the pipeline.

use nalgebra::{Matrix3, Point3, Vector3};

use ggpt_core::{Dims, MatchSet};

/// Least-squares similarity (Umeyama 1991) `tgt ≈ s R src + t`. Returns `None` for fewer than
/// 3 points or a degenerate source.
pub fn umeyama(
    src: &[Point3<f64>],
    tgt: &[Point3<f64>],
) -> Option<(f64, Matrix3<f64>, Vector3<f64>)> {
    let n = src.len();
    if n < 3 || tgt.len() != n {
        return None;
    }
    let ms = src.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / n as f64;
    let mt = tgt.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / n as f64;
    let mut cov = Matrix3::zeros();
    let mut var = 0.0;
    for (a, b) in src.iter().zip(tgt) {
        let da = a.coords - ms;
        cov += (b.coords - mt) * da.transpose();
        var += da.norm_squared();
    }
    cov /= n as f64;
    var /= n as f64;
    if var <= 0.0 {
        return None;
    }
    let svd = cov.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let mut d = Matrix3::identity();
    if (u.determinant() * vt.determinant()) < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let r = u * d * vt;
    let s = (svd.singular_values[0] * d[(0, 0)]
        + svd.singular_values[1] * d[(1, 1)]
        + svd.singular_values[2] * d[(2, 2)])
        / var;
    let t = mt - s * r * ms;
    Some((s, r, t))
}

/// Point accuracy of a prediction against metric GT.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct PointAccuracy {
    /// AUC@5 cm in percent (pipeline.md §10.2 definition).
    pub auc5: f64,
    /// AUC@10 cm in percent.
    pub auc10: f64,
    /// Median error (cm).
    pub median_cm: f64,
    /// Pixels evaluated.
    pub count: usize,
}

/// Aligns `pred` (`[P, 3]`, any frame) to `gt` (`[P, 3]`, metres) over `mask` with a trimmed
/// Umeyama (fit on all, then twice on the 70 % smallest residuals: an approximation of the
/// robust Sim(3) of pipeline.md §3.1) and returns AUC@5/10 cm. `None` when too few points.
pub fn point_accuracy(pred: &[f32], gt: &[f32], mask: &[bool]) -> Option<PointAccuracy> {
    let idx: Vec<usize> = mask
        .iter()
        .enumerate()
        .filter(|(_, m)| **m)
        .map(|(i, _)| i)
        .collect();
    let get = |v: &[f32], i: usize| {
        Point3::new(v[3 * i] as f64, v[3 * i + 1] as f64, v[3 * i + 2] as f64)
    };
    let src: Vec<Point3<f64>> = idx.iter().map(|&i| get(pred, i)).collect();
    let tgt: Vec<Point3<f64>> = idx.iter().map(|&i| get(gt, i)).collect();
    let (mut s, mut r, mut t) = umeyama(&src, &tgt)?;
    let mut errs: Vec<f64> = Vec::new();
    for round in 0..3 {
        errs = src
            .iter()
            .zip(&tgt)
            .map(|(a, b)| (s * r * a.coords + t - b.coords).norm() * 100.0)
            .collect();
        if round == 2 {
            break;
        }
        let mut sorted = errs.clone();
        sorted.sort_by(f64::total_cmp);
        let cut = sorted[(sorted.len() as f64 * 0.7) as usize];
        let keep: Vec<usize> = (0..src.len()).filter(|&i| errs[i] <= cut).collect();
        let a: Vec<Point3<f64>> = keep.iter().map(|&i| src[i]).collect();
        let b: Vec<Point3<f64>> = keep.iter().map(|&i| tgt[i]).collect();
        (s, r, t) = umeyama(&a, &b)?;
    }
    let n = errs.len() as f64;
    let recall = |k: f64| errs.iter().filter(|&&e| e < k).count() as f64 / n;
    let auc = |tau: usize| (1..=tau).map(|k| recall(k as f64)).sum::<f64>() / tau as f64 * 100.0;
    let mut sorted = errs.clone();
    sorted.sort_by(f64::total_cmp);
    Some(PointAccuracy {
        auc5: auc(5),
        auc10: auc(10),
        median_cm: sorted[sorted.len() / 2],
        count: errs.len(),
    })
}

/// Spearman rank correlation of two equally long samples (average ranks for ties).
pub fn spearman(a: &[f64], b: &[f64]) -> f64 {
    fn ranks(v: &[f64]) -> Vec<f64> {
        let mut idx: Vec<usize> = (0..v.len()).collect();
        idx.sort_by(|&i, &j| v[i].total_cmp(&v[j]));
        let mut r = vec![0.0; v.len()];
        let mut i = 0;
        while i < idx.len() {
            let mut j = i;
            while j + 1 < idx.len() && v[idx[j + 1]] == v[idx[i]] {
                j += 1;
            }
            let avg = (i + j) as f64 / 2.0;
            for &q in &idx[i..=j] {
                r[q] = avg;
            }
            i = j + 1;
        }
        r
    }
    let (ra, rb) = (ranks(a), ranks(b));
    let n = a.len().min(b.len()) as f64;
    let ma = ra.iter().sum::<f64>() / n;
    let mb = rb.iter().sum::<f64>() / n;
    let (mut c, mut va, mut vb) = (0.0, 0.0, 0.0);
    for (x, y) in ra.iter().zip(&rb) {
        c += (x - ma) * (y - mb);
        va += (x - ma).powi(2);
        vb += (y - mb).powi(2);
    }
    if va <= 0.0 || vb <= 0.0 {
        0.0
    } else {
        c / (va * vb).sqrt()
    }
}

/// Cycle error of `sfm.md` §3 for the pair `(s -> t)`: `|| bilinear_zero_pad(T_{t->s}) (T_{s->t}(p)) - p ||`
/// for every pixel `p` of view `s` (ff pixels). `m`: `[N, N, hw, 2]` matches `[t, s, k]`.
pub fn cycle_error(m: &[f32], dims: Dims, s: usize, t: usize) -> Vec<f32> {
    let (n, hw, w, h) = (dims.n, dims.hw(), dims.w, dims.h);
    let fwd = &m[2 * (t * n + s) * hw..2 * (t * n + s + 1) * hw];
    let back = &m[2 * (s * n + t) * hw..2 * (s * n + t + 1) * hw];
    let sample = |x: f64, y: f64| -> (f64, f64) {
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let mut acc = (0.0, 0.0);
        for (dx, dy, wgt) in [
            (0.0, 0.0, (1.0 - fx) * (1.0 - fy)),
            (1.0, 0.0, fx * (1.0 - fy)),
            (0.0, 1.0, (1.0 - fx) * fy),
            (1.0, 1.0, fx * fy),
        ] {
            let (xi, yi) = (x0 + dx, y0 + dy);
            if xi >= 0.0 && yi >= 0.0 && xi < w as f64 && yi < h as f64 {
                let k = yi as usize * w + xi as usize;
                acc.0 += wgt * back[2 * k] as f64;
                acc.1 += wgt * back[2 * k + 1] as f64;
            }
        }
        acc
    };
    (0..hw)
        .map(|k| {
            let (px, py) = ((k % w) as f64, (k / w) as f64);
            let (bx, by) = sample(fwd[2 * k] as f64, fwd[2 * k + 1] as f64);
            ((bx - px).hypot(by - py)) as f32
        })
        .collect()
}

/// Pass rates of one matcher over the off-diagonal entries.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct MatchStats {
    /// Fraction with score > 0.6 (BA threshold, sfm.md §5).
    pub score_gt_06: f64,
    /// Fraction with score > 0.6 and cycle error < 2 px (the BA mask).
    pub ba_pass: f64,
    /// Fraction with score > 0.1 and cycle error < 4 px (the DLT mask before the epipolar test).
    pub dlt_pass: f64,
}

/// Computes [`MatchStats`] for a match set of a scene with dimensions `dims`.
pub fn match_stats(ms: &MatchSet, dims: Dims) -> MatchStats {
    let (n, hw) = (dims.n, dims.hw());
    let (mut total, mut s06, mut ba, mut dlt) = (0usize, 0usize, 0usize, 0usize);
    for s in 0..n {
        for t in 0..n {
            if s == t {
                continue;
            }
            let cyc = cycle_error(&ms.pred_matches, dims, s, t);
            let sc = &ms.pred_scores[(t * n + s) * hw..(t * n + s + 1) * hw];
            for (c, &score) in cyc.iter().zip(sc) {
                total += 1;
                s06 += usize::from(score > 0.6);
                ba += usize::from(score > 0.6 && *c < 2.0);
                dlt += usize::from(score > 0.1 && *c < 4.0);
            }
        }
    }
    let f = |c: usize| {
        if total > 0 {
            c as f64 / total as f64
        } else {
            0.0
        }
    };
    MatchStats {
        score_gt_06: f(s06),
        ba_pass: f(ba),
        dlt_pass: f(dlt),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cycle_error_matches_the_spec_test_vector() {
        // sfm.md §3: w = 4, h = 3, A->B(p) = p + (0.5, 0.25), B->A(q) = q - (0.5, 0).
        let dims = Dims { n: 2, h: 3, w: 4 };
        let hw = dims.hw();
        let mut m = vec![0f32; 2 * 4 * hw];
        for k in 0..hw {
            let (x, y) = ((k % 4) as f32, (k / 4) as f32);
            // [t=1, s=0]: A->B ; [t=0, s=1]: B->A.
            m[2 * (2 * hw + k)] = x + 0.5;
            m[2 * (2 * hw + k) + 1] = y + 0.25;
            m[2 * (hw + k)] = x - 0.5;
            m[2 * (hw + k) + 1] = y;
        }
        let e = cycle_error(&m, dims, 0, 1);
        let want = [
            0.25,
            0.25,
            0.25,
            1.754459,
            0.25,
            0.25,
            0.25,
            1.789728,
            0.5,
            0.559017,
            std::f64::consts::FRAC_1_SQRT_2,
            2.411723,
        ];
        for (a, b) in e.iter().zip(want) {
            assert!((*a as f64 - b).abs() < 1e-5, "{e:?}");
        }
    }

    #[test]
    fn umeyama_recovers_a_similarity_and_spearman_ranks() {
        let r = nalgebra::Rotation3::from_euler_angles(0.1, -0.2, 0.3).into_inner();
        let src: Vec<Point3<f64>> = (0..20)
            .map(|i| Point3::new(i as f64 * 0.1, (i * i) as f64 * 0.01, (i % 3) as f64))
            .collect();
        let tgt: Vec<Point3<f64>> = src
            .iter()
            .map(|p| Point3::from(2.0 * r * p.coords + Vector3::new(1.0, 2.0, 3.0)))
            .collect();
        let (s, rr, t) = umeyama(&src, &tgt).unwrap_or((0.0, Matrix3::zeros(), Vector3::zeros()));
        assert!(
            (s - 2.0).abs() < 1e-9
                && (rr - r).norm() < 1e-9
                && (t - Vector3::new(1.0, 2.0, 3.0)).norm() < 1e-9
        );
        assert!((spearman(&[1.0, 2.0, 3.0], &[10.0, 20.0, 35.0]) - 1.0).abs() < 1e-12);
        assert!((spearman(&[1.0, 2.0, 3.0], &[3.0, 2.0, 1.0]) + 1.0).abs() < 1e-12);
    }
}
