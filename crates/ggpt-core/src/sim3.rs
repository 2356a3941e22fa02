//! Sim(3) estimation (`pipeline.md` §3.1): Umeyama's closed form and the robust LO-RANSAC
//! estimator with COLMAP semantics (`pycolmap.estimate_sim3d_robust`), plus the retry schedule
//! used by scene preparation and evaluation.
//!
//! A similarity maps a *source* frame to a *target* frame: `S(x) = s R x + t`
//! (`tgt_from_src`). All estimation is in `f64`. Point units are those of the frames (scene
//! units or metres); `max_error` is a distance in the **target** frame.

use nalgebra::{DMatrix, Matrix3, Matrix3x4, Point3, Vector3};
use rand::Rng;

use crate::{CoreError, Result};

/// Default RANSAC inlier threshold (`pipeline.md` §3.1, official `max_error = 0.03`), target units.
pub const DEFAULT_MAX_ERROR: f64 = 0.03;
/// A-priori inlier ratio that caps the number of RANSAC trials (`pipeline.md` §3.1).
pub const DEFAULT_MIN_INLIER_RATIO: f64 = 0.8;
/// RANSAC confidence used by the trial-count formula (COLMAP default, `pipeline.md` §3.1).
pub const DEFAULT_CONFIDENCE: f64 = 0.99;
/// Multiplier of the trial-count formula (COLMAP `dyn_num_trials_multiplier`, `pipeline.md` §3.1).
pub const DEFAULT_TRIALS_MULTIPLIER: f64 = 3.0;
/// Number of samples `M` with which the a-priori trial cap is computed (COLMAP, `pipeline.md` §3.1).
pub const TRIAL_CAP_NUM_SAMPLES: usize = 100_000;
/// Maximum number of local-optimisation refits after a new best sample model (`pipeline.md` §3.1).
pub const MAX_LOCAL_REFITS: usize = 10;
/// Minimal sample size of the similarity estimator.
pub const MIN_SAMPLE: usize = 3;
/// Retry factor of the alignment schedule (`pipeline.md` §3.1: 0.03, 0.09, 0.27, 0.81).
pub const RETRY_FACTOR: f64 = 3.0;
/// The schedule retries while the previous threshold was at most this value (`pipeline.md` §3.1).
pub const RETRY_LAST_THRESHOLD: f64 = 0.3;

/// A similarity transform `S(x) = scale * rotation * x + translation` (named by use, e.g.
/// `tgt_from_src`, `sfm_from_ff`). `rotation` is orthonormal with determinant +1.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sim3 {
    /// Scale `s > 0`.
    pub scale: f64,
    /// Rotation `R` (orthonormal, det +1).
    pub rotation: Matrix3<f64>,
    /// Translation `t` (target units).
    pub translation: Vector3<f64>,
}

impl Default for Sim3 {
    fn default() -> Self {
        Self::identity()
    }
}

impl Sim3 {
    /// The identity transform.
    pub fn identity() -> Self {
        Sim3 {
            scale: 1.0,
            rotation: Matrix3::identity(),
            translation: Vector3::zeros(),
        }
    }

    /// Applies the transform to a point of the source frame, giving target-frame coordinates.
    pub fn apply(&self, p: &Point3<f64>) -> Point3<f64> {
        Point3::from(self.scale * (self.rotation * p.coords) + self.translation)
    }

    /// The 3x4 matrix `[s R | t]` (target-from-source).
    pub fn to_matrix3x4(&self) -> Matrix3x4<f64> {
        let mut m = Matrix3x4::zeros();
        m.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(self.rotation * self.scale));
        m.set_column(3, &self.translation);
        m
    }

    /// `[s R | t]` cast to `f32`, the form the official pipeline applies to `f32` point maps.
    pub fn to_matrix3x4_f32(&self) -> Matrix3x4<f32> {
        self.to_matrix3x4().map(|v| v as f32)
    }

    /// The inverse transform (`src_from_tgt`). Fails for a non-positive or non-finite scale.
    pub fn inverse(&self) -> Result<Sim3> {
        if !(self.scale.is_finite() && self.scale > 0.0) {
            return Err(CoreError::Numeric(format!(
                "Sim3::inverse: scale {} is not positive",
                self.scale
            )));
        }
        let rt = self.rotation.transpose();
        let inv_s = 1.0 / self.scale;
        Ok(Sim3 {
            scale: inv_s,
            rotation: rt,
            translation: -(rt * self.translation) * inv_s,
        })
    }

    /// Composition `self ∘ other` (apply `other` first): `a_from_c = a_from_b.compose(&b_from_c)`.
    pub fn compose(&self, other: &Sim3) -> Sim3 {
        Sim3 {
            scale: self.scale * other.scale,
            rotation: self.rotation * other.rotation,
            translation: self.scale * (self.rotation * other.translation) + self.translation,
        }
    }

    /// True when every component is finite.
    pub fn is_finite(&self) -> bool {
        self.scale.is_finite()
            && self.rotation.iter().all(|v| v.is_finite())
            && self.translation.iter().all(|v| v.is_finite())
    }
}

/// Applies a 3x4 `f32` matrix `m = [s R | t]` to interleaved `f32` points (`[.., 3]`, source
/// frame), in `f32` with the official summation order `((m_i0 x + m_i1 y) + m_i2 z) + m_i3`
/// per row (`pipeline.md` §3: reproduces the `sfm_small` aligned points bit-exactly).
/// A trailing partial point (length not a multiple of 3) is left unchanged.
pub fn apply_matrix_f32(m: &Matrix3x4<f32>, points: &mut [f32]) {
    for p in points.chunks_exact_mut(3) {
        let (x, y, z) = (p[0], p[1], p[2]);
        for (r, out) in p.iter_mut().enumerate() {
            *out = ((m[(r, 0)] * x + m[(r, 1)] * y) + m[(r, 2)] * z) + m[(r, 3)];
        }
    }
}

fn check_pairs(src: &[Point3<f64>], tgt: &[Point3<f64>], what: &str) -> Result<()> {
    if src.len() != tgt.len() {
        return Err(CoreError::Numeric(format!(
            "{what}: {} source points but {} target points",
            src.len(),
            tgt.len()
        )));
    }
    Ok(())
}

/// Umeyama's closed-form least-squares similarity `tgt ≈ s R src + t` (`pipeline.md` §3.1),
/// with the reflection correction `E = diag(1, 1, sign(det U det V))` on the smallest singular
/// value. `src` and `tgt` are corresponding points (same length) in the source / target frames.
///
/// Fails (`CoreError::Numeric`) for mismatched lengths, fewer than 3 pairs, non-finite input,
/// zero source variance or a non-finite result.
pub fn umeyama(src: &[Point3<f64>], tgt: &[Point3<f64>]) -> Result<Sim3> {
    check_pairs(src, tgt, "umeyama")?;
    umeyama_iter(src.len(), src.iter().zip(tgt.iter()))
}

/// Umeyama over the pairs `(src[i], tgt[i])` with `i` in `indices`, as COLMAP's similarity
/// estimator inside RANSAC: the sample is rejected when the *uncentred* `3 x n` matrix of the
/// source or of the target points has rank < 3 (COLMAP's `FullPivLU` check).
fn umeyama_subset(src: &[Point3<f64>], tgt: &[Point3<f64>], indices: &[usize]) -> Result<Sim3> {
    if !(full_rank(src, indices) && full_rank(tgt, indices)) {
        return Err(CoreError::Numeric("umeyama: rank-deficient sample".into()));
    }
    let pairs = indices
        .iter()
        .filter_map(|&i| Some((src.get(i)?, tgt.get(i)?)));
    umeyama_iter(indices.len(), pairs)
}

/// Relative threshold on the Gram eigenvalues `λ_min / λ_max` below which a large point set
/// counts as rank-deficient (the Gram matrix squares the condition number, so this is the
/// rounding level of its entries rather than COLMAP's LU pivot threshold; only exactly
/// degenerate sets reach it).
const GRAM_RANK_REL_EPS: f64 = 1e2 * f64::EPSILON;

/// True when the uncentred `3 x n` matrix of the selected points has rank 3 (COLMAP rejects
/// samples whose `FullPivLU` rank is < 3). Minimal samples (`n = 3`): singular values of the
/// 3x3 matrix above `3 ε σ_max`, the relative threshold of a full-pivot LU. Larger sets: the
/// eigenvalues of the 3x3 Gram matrix `Σ p p^T` (O(n), no allocation).
fn full_rank(points: &[Point3<f64>], indices: &[usize]) -> bool {
    if indices.len() < MIN_SAMPLE {
        return false;
    }
    let mut gram = Matrix3::zeros();
    let mut cols = Vec::with_capacity(MIN_SAMPLE);
    for &i in indices {
        let Some(p) = points.get(i) else { return false };
        if !p.coords.iter().all(|v| v.is_finite()) {
            return false;
        }
        if indices.len() == MIN_SAMPLE {
            cols.push(p.coords);
        } else {
            gram += p.coords * p.coords.transpose();
        }
    }
    if indices.len() == MIN_SAMPLE {
        let m = Matrix3::from_columns(&cols);
        let Some(svd) = nalgebra::linalg::SVD::try_new_unordered(
            DMatrix::from_column_slice(3, 3, m.as_slice()),
            false,
            false,
            f64::EPSILON * 5.0,
            10_000,
        ) else {
            return false;
        };
        let sv = svd.singular_values.as_slice();
        let max = sv.iter().copied().fold(0.0_f64, f64::max);
        return max > 0.0 && sv.iter().filter(|&&v| v > max * 3.0 * f64::EPSILON).count() == 3;
    }
    let Some(eig) = gram.try_symmetric_eigen(f64::EPSILON, 10_000) else {
        return false;
    };
    let ev = eig.eigenvalues;
    let max = ev.max();
    max > 0.0 && ev.min() > max * GRAM_RANK_REL_EPS
}

fn umeyama_iter<'a, I>(n_expected: usize, pairs: I) -> Result<Sim3>
where
    I: Iterator<Item = (&'a Point3<f64>, &'a Point3<f64>)> + Clone,
{
    let n = pairs.clone().count();
    if n != n_expected || n < MIN_SAMPLE {
        return Err(CoreError::Numeric(format!(
            "umeyama: {n} point pairs, need at least {MIN_SAMPLE}"
        )));
    }
    let nf = n as f64;
    let mut mu_s = Vector3::zeros();
    let mut mu_t = Vector3::zeros();
    for (s, t) in pairs.clone() {
        mu_s += s.coords;
        mu_t += t.coords;
    }
    mu_s /= nf;
    mu_t /= nf;
    if !(mu_s.iter().all(|v| v.is_finite()) && mu_t.iter().all(|v| v.is_finite())) {
        return Err(CoreError::Numeric("umeyama: non-finite input point".into()));
    }
    let mut sigma = Matrix3::zeros();
    let mut var_s = 0.0;
    for (s, t) in pairs {
        let ds = s.coords - mu_s;
        let dt = t.coords - mu_t;
        sigma += dt * ds.transpose();
        var_s += ds.norm_squared();
    }
    sigma /= nf;
    var_s /= nf;
    if !(var_s.is_finite() && var_s > 0.0) {
        return Err(CoreError::Numeric(format!(
            "umeyama: degenerate source (variance {var_s})"
        )));
    }
    // General (Golub–Kahan) SVD through a dynamic matrix: nalgebra's static 3x3 path squares the
    // condition number (eigen-decomposition of Σ^T Σ).
    let dyn_sigma = DMatrix::from_column_slice(3, 3, sigma.as_slice());
    let svd =
        nalgebra::linalg::SVD::try_new_unordered(dyn_sigma, true, true, f64::EPSILON * 5.0, 10_000)
            .ok_or_else(|| CoreError::Numeric("umeyama: SVD did not converge".into()))?;
    let (Some(u), Some(v_t)) = (svd.u.as_ref(), svd.v_t.as_ref()) else {
        return Err(CoreError::Numeric(
            "umeyama: SVD returned no singular vectors".into(),
        ));
    };
    let u = Matrix3::from_iterator(u.iter().copied());
    let v_t = Matrix3::from_iterator(v_t.iter().copied());
    let d = svd.singular_values.as_slice();
    // Index of the smallest singular value: the reflection fix goes there.
    let mut min_i = 0;
    for i in 1..3 {
        if d.get(i).copied().unwrap_or(f64::INFINITY)
            < d.get(min_i).copied().unwrap_or(f64::INFINITY)
        {
            min_i = i;
        }
    }
    let mut e = Vector3::new(1.0, 1.0, 1.0);
    if u.determinant() * v_t.determinant() < 0.0 {
        e[min_i] = -1.0;
    }
    let rotation = u * Matrix3::from_diagonal(&e) * v_t;
    let trace_de: f64 = d.iter().zip(e.iter()).map(|(a, b)| a * b).sum();
    let scale = trace_de / var_s;
    let translation = mu_t - scale * (rotation * mu_s);
    let sim = Sim3 {
        scale,
        rotation,
        translation,
    };
    if !sim.is_finite() || scale <= 0.0 {
        return Err(CoreError::Numeric(format!(
            "umeyama: degenerate result (scale {scale})"
        )));
    }
    Ok(sim)
}

/// Options of [`robust_sim3`] (`pipeline.md` §3.1). Defaults are the official values.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RobustSim3Options {
    /// Inlier threshold: a pair is an inlier iff `||S(src) - tgt||^2 <= max_error^2` (target units).
    pub max_error: f64,
    /// A-priori inlier ratio; only caps the number of trials, never rejects a model.
    pub min_inlier_ratio: f64,
    /// Confidence of the trial-count formula.
    pub confidence: f64,
    /// Multiplier of the trial-count formula.
    pub trials_multiplier: f64,
    /// Hard cap on trials (in addition to the a-priori cap); `usize::MAX` for none.
    pub max_trials: usize,
    /// Maximum local-optimisation refits per new best sample model.
    pub max_local_refits: usize,
}

impl Default for RobustSim3Options {
    fn default() -> Self {
        RobustSim3Options {
            max_error: DEFAULT_MAX_ERROR,
            min_inlier_ratio: DEFAULT_MIN_INLIER_RATIO,
            confidence: DEFAULT_CONFIDENCE,
            trials_multiplier: DEFAULT_TRIALS_MULTIPLIER,
            max_trials: usize::MAX,
            max_local_refits: MAX_LOCAL_REFITS,
        }
    }
}

impl RobustSim3Options {
    /// Default options with the given inlier threshold.
    pub fn with_max_error(max_error: f64) -> Self {
        RobustSim3Options {
            max_error,
            ..Default::default()
        }
    }
}

/// Result of [`robust_sim3`].
#[derive(Debug, Clone, PartialEq)]
pub struct RobustSim3Result {
    /// Best model (`tgt_from_src`): a sample model or a local-optimisation refit, not refitted
    /// once more on its final inliers.
    pub sim3: Sim3,
    /// Inlier mask under `sim3` (`residual <= max_error^2`), one entry per input pair.
    pub inliers: Vec<bool>,
    /// Number of inliers.
    pub num_inliers: usize,
    /// Sum of the squared residuals of the inliers.
    pub residual_sum: f64,
    /// RANSAC trials performed.
    pub num_trials: usize,
    /// Local-optimisation refits performed (all trials together).
    pub num_local_refits: usize,
    /// True when the best model came from a local-optimisation refit.
    pub best_is_local: bool,
}

/// Number of trials needed so that, with probability `confidence`, one 3-sample is all-inlier
/// when `num_inliers` of `num_samples` pairs are inliers, times `multiplier` (COLMAP
/// `ComputeNumTrials`, with the without-replacement probability of `pipeline.md` §3.1).
/// Returns `usize::MAX` when the formula is unbounded (no inlier) and 1 when every sample is good.
pub fn compute_num_trials(
    num_inliers: usize,
    num_samples: usize,
    confidence: f64,
    multiplier: f64,
) -> usize {
    let nom = 1.0 - confidence;
    if nom <= 0.0 {
        return usize::MAX;
    }
    let (k, m) = (num_inliers as f64, num_samples as f64);
    let mut p = 1.0;
    for i in 0..MIN_SAMPLE {
        let i = i as f64;
        if m - i <= 0.0 {
            p = 0.0;
            break;
        }
        p *= ((k - i) / (m - i)).max(0.0);
    }
    let denom = 1.0 - p;
    if denom <= 0.0 {
        return 1;
    }
    if denom >= 1.0 {
        return usize::MAX;
    }
    let trials = (nom.ln() / denom.ln() * multiplier).ceil();
    if trials.is_finite() && trials < usize::MAX as f64 {
        trials.max(0.0) as usize
    } else {
        usize::MAX
    }
}

/// Support of a model: inlier count and the sum of inlier squared residuals.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Support {
    num_inliers: usize,
    residual_sum: f64,
}

impl Support {
    const WORST: Support = Support {
        num_inliers: 0,
        residual_sum: f64::INFINITY,
    };

    /// More inliers is better; equal counts -> smaller residual sum is better.
    fn better_than(&self, other: &Support) -> bool {
        self.num_inliers > other.num_inliers
            || (self.num_inliers == other.num_inliers && self.residual_sum < other.residual_sum)
    }
}

fn residuals_into(s: &Sim3, src: &[Point3<f64>], tgt: &[Point3<f64>], out: &mut Vec<f64>) {
    out.clear();
    let m = s.rotation * s.scale;
    out.extend(
        src.iter()
            .zip(tgt.iter())
            .map(|(a, b)| (m * a.coords + s.translation - b.coords).norm_squared()),
    );
}

fn evaluate(residuals: &[f64], max_sq: f64) -> Support {
    let mut sup = Support {
        num_inliers: 0,
        residual_sum: 0.0,
    };
    for &r in residuals {
        if r <= max_sq {
            sup.num_inliers += 1;
            sup.residual_sum += r;
        }
    }
    sup
}

/// Robust similarity `tgt ≈ S(src)` by LO-RANSAC with COLMAP semantics (`pipeline.md` §3.1):
/// 3-point Umeyama samples drawn from `rng`, squared-distance residuals, inlier iff
/// `residual <= max_error^2`, support = (more inliers, then smaller inlier residual sum), local
/// optimisation (Umeyama refit on the best model's inliers, repeated while the inlier count grows,
/// at most `max_local_refits` times) whenever a sample model becomes the best with more than 3
/// inliers, trial cap from `min_inlier_ratio` (20 trials with the defaults) and dynamic stopping
/// from the best inlier ratio.
///
/// `src` and `tgt` are corresponding points (same length), source and target frames; `max_error`
/// is in target units. Fails (`CoreError::Numeric`) for mismatched lengths, fewer than 3 pairs or
/// when the best model has fewer than 3 inliers.
pub fn robust_sim3<R: Rng + ?Sized>(
    src: &[Point3<f64>],
    tgt: &[Point3<f64>],
    options: &RobustSim3Options,
    rng: &mut R,
) -> Result<RobustSim3Result> {
    check_pairs(src, tgt, "robust_sim3")?;
    let n = src.len();
    if n < MIN_SAMPLE {
        return Err(CoreError::Numeric(format!(
            "robust_sim3: {n} point pairs, need at least {MIN_SAMPLE}"
        )));
    }
    if !(options.max_error.is_finite() && options.max_error >= 0.0) {
        return Err(CoreError::Numeric(format!(
            "robust_sim3: invalid max_error {}",
            options.max_error
        )));
    }
    let max_sq = options.max_error * options.max_error;
    let prior_inliers = (options.min_inlier_ratio * TRIAL_CAP_NUM_SAMPLES as f64) as usize;
    let max_trials = options.max_trials.min(compute_num_trials(
        prior_inliers,
        TRIAL_CAP_NUM_SAMPLES,
        options.confidence,
        options.trials_multiplier,
    ));

    let mut best_support = Support::WORST;
    let mut best: Option<Sim3> = None;
    let mut best_is_local = false;
    let mut dyn_max_trials = max_trials;
    let mut num_trials = 0usize;
    let mut num_local_refits = 0usize;
    let mut residuals = Vec::with_capacity(n);
    let mut best_residuals: Vec<f64> = Vec::with_capacity(n);
    let mut inlier_idx: Vec<usize> = Vec::with_capacity(n);

    while num_trials < max_trials {
        let trial = num_trials;
        num_trials += 1;
        let sample = rand::seq::index::sample(rng, n, MIN_SAMPLE).into_vec();
        if let Ok(model) = umeyama_subset(src, tgt, &sample) {
            residuals_into(&model, src, tgt, &mut residuals);
            let support = evaluate(&residuals, max_sq);
            if support.better_than(&best_support) {
                best_support = support;
                best = Some(model);
                best_is_local = false;
                std::mem::swap(&mut best_residuals, &mut residuals);
                if support.num_inliers > MIN_SAMPLE {
                    for _ in 0..options.max_local_refits {
                        inlier_idx.clear();
                        inlier_idx.extend(
                            best_residuals
                                .iter()
                                .enumerate()
                                .filter(|(_, r)| **r <= max_sq)
                                .map(|(i, _)| i),
                        );
                        let prev_inliers = best_support.num_inliers;
                        num_local_refits += 1;
                        if let Ok(local) = umeyama_subset(src, tgt, &inlier_idx) {
                            residuals_into(&local, src, tgt, &mut residuals);
                            let local_support = evaluate(&residuals, max_sq);
                            if local_support.better_than(&best_support) {
                                best_support = local_support;
                                best = Some(local);
                                best_is_local = true;
                                std::mem::swap(&mut best_residuals, &mut residuals);
                            }
                        }
                        if best_support.num_inliers <= prev_inliers {
                            break;
                        }
                    }
                }
                dyn_max_trials = compute_num_trials(
                    best_support.num_inliers,
                    n,
                    options.confidence,
                    options.trials_multiplier,
                );
            }
            // COLMAP checks dynamic stopping after each evaluated model.
            if trial >= dyn_max_trials {
                break;
            }
        }
    }

    match best {
        Some(sim3) if best_support.num_inliers >= MIN_SAMPLE => {
            let inliers: Vec<bool> = best_residuals.iter().map(|r| *r <= max_sq).collect();
            Ok(RobustSim3Result {
                sim3,
                inliers,
                num_inliers: best_support.num_inliers,
                residual_sum: best_support.residual_sum,
                num_trials,
                num_local_refits,
                best_is_local,
            })
        }
        _ => Err(CoreError::Numeric(format!(
            "robust_sim3: best model has {} inliers (need {MIN_SAMPLE}) after {num_trials} trials, max_error {}",
            best_support.num_inliers, options.max_error
        ))),
    }
}

/// Which branch of the retry schedule produced an alignment.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(tag = "method", rename_all = "snake_case")]
pub enum AlignMethod {
    /// [`robust_sim3`] succeeded with this threshold.
    Robust {
        /// The threshold that succeeded.
        max_error: f64,
    },
    /// Every robust attempt failed; plain [`umeyama`] on all pairs.
    PlainUmeyama,
    /// Everything failed; the identity is used.
    Identity,
}

/// Information about an [`align_with_retries`] call.
#[derive(Debug, Clone, PartialEq)]
pub struct AlignInfo {
    /// Branch used.
    pub method: AlignMethod,
    /// Thresholds tried with the robust estimator, in order.
    pub thresholds_tried: Vec<f64>,
    /// Inlier mask of the successful robust attempt (`None` for the fallbacks).
    pub inliers: Option<Vec<bool>>,
    /// Inlier count of the successful robust attempt (`None` for the fallbacks).
    pub num_inliers: Option<usize>,
}

/// Robust Sim(3) with the official retry schedule (`pipeline.md` §3.1): [`robust_sim3`] with
/// `max_error`, multiplied by 3 after each failure while the previous threshold was `<= 0.3`
/// (0.03, 0.09, 0.27, 0.81 with the default), then plain [`umeyama`] on all pairs, then the
/// identity. Never fails; `AlignInfo` says which branch was used. Frames and units as in
/// [`robust_sim3`].
pub fn align_with_retries<R: Rng + ?Sized>(
    src: &[Point3<f64>],
    tgt: &[Point3<f64>],
    max_error: f64,
    rng: &mut R,
) -> (Sim3, AlignInfo) {
    let mut thresholds_tried = Vec::new();
    let mut thr = max_error;
    loop {
        thresholds_tried.push(thr);
        match robust_sim3(src, tgt, &RobustSim3Options::with_max_error(thr), rng) {
            Ok(res) => {
                let info = AlignInfo {
                    method: AlignMethod::Robust { max_error: thr },
                    thresholds_tried,
                    num_inliers: Some(res.num_inliers),
                    inliers: Some(res.inliers),
                };
                return (res.sim3, info);
            }
            Err(e) => tracing::debug!("robust Sim(3) with max_error {thr} failed: {e}"),
        }
        // Retry only while the previous threshold was <= 0.3 (NaN stops).
        if !matches!(
            thr.partial_cmp(&RETRY_LAST_THRESHOLD),
            Some(std::cmp::Ordering::Less | std::cmp::Ordering::Equal)
        ) {
            break;
        }
        thr *= RETRY_FACTOR;
    }
    match umeyama(src, tgt) {
        Ok(s) => {
            tracing::warn!(
                "robust Sim(3) failed for every threshold {thresholds_tried:?}; using plain Umeyama"
            );
            (
                s,
                AlignInfo {
                    method: AlignMethod::PlainUmeyama,
                    thresholds_tried,
                    inliers: None,
                    num_inliers: None,
                },
            )
        }
        Err(e) => {
            tracing::warn!("Sim(3) alignment failed completely ({e}); using the identity");
            (
                Sim3::identity(),
                AlignInfo {
                    method: AlignMethod::Identity,
                    thresholds_tried,
                    inliers: None,
                    num_inliers: None,
                },
            )
        }
    }
}

#[cfg(test)]
mod tests;
