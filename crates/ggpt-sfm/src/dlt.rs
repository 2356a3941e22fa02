//! Batched linear (DLT) triangulation of every multi-view track with its filters (`sfm.md` §9).
//!
//! Observations are ff pixels (pixel-centre convention), cameras `cam_from_world` (OpenCV) with
//! `K` in ff pixels; points come out in the cameras' world frame (the SfM frame). All geometry in
//! f64; tracks are processed in parallel (rayon) — results do not depend on the thread count.

use ggpt_core::Cameras;
use nalgebra::{Matrix3x4, Matrix4, Vector3, Vector4};
use rayon::prelude::*;

use crate::error::{Result, SfmError};
use crate::matches::Correspondences;

/// Homogeneous-coordinate filter `|X~_4| > 1e-10` (`sfm.md` §9.3 step 1).
pub const MIN_HOMOGENEOUS_W: f64 = 1e-10;
/// Cosine clamp of the triangulation angle (`sfm.md` §9.3 step 3).
pub const ANGLE_COS_CLAMP: f64 = 0.9999;

/// DLT filter thresholds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DltOptions {
    /// Mean reprojection error over the visible views must be `<` this (ff pixels).
    pub max_reproj_error: f64,
    /// Max pairwise triangulation angle must be `>` this (degrees).
    pub min_tri_angle_deg: f64,
    /// [project] optional cheirality test (point in front of every observing camera); off by
    /// default (official parity).
    pub cheirality: bool,
}

/// Why a track was kept or rejected (filters run in this order).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DltStatus {
    /// Passed every filter.
    Kept,
    /// `|X~_4| <= 1e-10` (or a non-finite solve).
    RejectW,
    /// Mean reprojection error not below the threshold (or non-finite).
    RejectReproj,
    /// Max triangulation angle not above the threshold (or non-finite).
    RejectAngle,
    /// Behind an observing camera (only with [`DltOptions::cheirality`]).
    RejectCheirality,
}

/// One triangulated track.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DltTrack {
    /// Track id `s * hw + k`.
    pub track: usize,
    /// Number of visible views.
    pub num_views: u32,
    /// `X~_{1:3} / X~_4` (world / SfM frame); meaningful when `status != RejectW`.
    pub point: [f64; 3],
    /// `X~_4` of the unit-norm eigenvector (sign arbitrary).
    pub w: f64,
    /// Mean reprojection error (ff pixels); NaN when not computed.
    pub reproj_mean: f64,
    /// Max pairwise ray angle over visible view pairs `a != b` (degrees); NaN when not computed.
    pub max_angle_deg: f64,
    /// Filter outcome.
    pub status: DltStatus,
}

/// Result of [`triangulate_tracks`]: one entry per track with at least two visible views, in
/// ascending track id.
#[derive(Debug, Clone, PartialEq)]
pub struct DltOutput {
    /// Triangulated tracks.
    pub tracks: Vec<DltTrack>,
}

impl DltOutput {
    /// Number of tracks passing each filter: (input, w, reprojection, angle, cheirality = kept).
    pub fn counts(&self) -> [usize; 5] {
        let total = self.tracks.len();
        let w = self.tracks.iter().filter(|t| t.status != DltStatus::RejectW).count();
        let r = self.tracks.iter().filter(|t| !matches!(t.status, DltStatus::RejectW | DltStatus::RejectReproj)).count();
        let a = self
            .tracks
            .iter()
            .filter(|t| matches!(t.status, DltStatus::Kept | DltStatus::RejectCheirality))
            .count();
        let k = self.tracks.iter().filter(|t| t.status == DltStatus::Kept).count();
        [total, w, r, a, k]
    }
}

/// Projection matrices `P_t = K_t [R_t | t_t]` of all views.
pub fn projection_matrices(cams: &Cameras) -> Vec<Matrix3x4<f64>> {
    cams.cam_from_world.iter().zip(&cams.intrinsics).map(|(e, k)| k * e).collect()
}

/// Accumulates `A_t^T A_t` of one observation into `m` (upper triangle is enough, full kept).
#[inline]
fn accumulate(m: &mut Matrix4<f64>, p: &Matrix3x4<f64>, u: f64, v: f64) {
    let r1 = Vector4::new(u * p[(2, 0)] - p[(0, 0)], u * p[(2, 1)] - p[(0, 1)], u * p[(2, 2)] - p[(0, 2)], u * p[(2, 3)] - p[(0, 3)]);
    let r2 = Vector4::new(v * p[(2, 0)] - p[(1, 0)], v * p[(2, 1)] - p[(1, 1)], v * p[(2, 2)] - p[(1, 2)], v * p[(2, 3)] - p[(1, 3)]);
    for a in 0..4 {
        for b in a..4 {
            m[(a, b)] += r1[a] * r1[b] + r2[a] * r2[b];
        }
    }
}

/// Smallest-eigenvalue unit eigenvector of a symmetric 4x4 matrix given by its upper triangle.
#[inline]
fn smallest_eigenvector(mut m: Matrix4<f64>) -> Vector4<f64> {
    for a in 0..4 {
        for b in 0..a {
            m[(a, b)] = m[(b, a)];
        }
    }
    let eig = m.symmetric_eigen();
    let mut best = 0;
    for i in 1..4 {
        if eig.eigenvalues[i] < eig.eigenvalues[best] {
            best = i;
        }
    }
    eig.eigenvectors.column(best).into_owned()
}

/// Linear triangulation (`sfm.md` §9.2) of one track from `(P_t, (u, v))` observations:
/// the unit-norm eigenvector `X~` of the smallest eigenvalue of `Σ A_t^T A_t`.
pub fn triangulate_homogeneous(obs: &[(Matrix3x4<f64>, [f64; 2])]) -> Vector4<f64> {
    let mut m = Matrix4::zeros();
    for (p, uv) in obs {
        accumulate(&mut m, p, uv[0], uv[1]);
    }
    smallest_eigenvector(m)
}

/// Triangulates every track `j = s hw + k` with `Σ_t vis[t, j] >= 2` (`sfm.md` §9):
/// * `corr`: correspondences (observation of `j` in view `t` = `matches[t, s, k]`);
/// * `vis`: `[N, N hw]` DLT visibility after the epipolar filter (diagonal true);
/// * `cams`: BA cameras (SfM frame).
pub fn triangulate_tracks(corr: &Correspondences, vis: &[bool], cams: &Cameras, opts: &DltOptions) -> Result<DltOutput> {
    corr.validate()?;
    let n = corr.dims.n;
    let hw = corr.dims.hw();
    let nt = n * hw;
    if vis.len() != n * nt {
        return Err(SfmError::Shape(format!("DLT: visibility of {} entries, expected {}", vis.len(), n * nt)));
    }
    if cams.len() != n || cams.intrinsics.len() != n {
        return Err(SfmError::Shape(format!("DLT: {} cameras for {n} views", cams.len())));
    }
    if !cams.is_finite() {
        return Err(SfmError::Invalid("DLT: non-finite camera entry".into()));
    }
    let ps = projection_matrices(cams);
    let centers: Vec<Vector3<f64>> = (0..n).map(|t| cams.center(t).coords).collect();
    let rots: Vec<_> = (0..n).map(|t| (cams.rotation(t), cams.translation(t))).collect();
    let opts = *opts;
    let matches = &corr.matches;
    let tracks: Vec<DltTrack> = (0..nt)
        .into_par_iter()
        .with_min_len(4096)
        .map_init(
            || (Vec::<(usize, f64, f64)>::with_capacity(n), Vec::<Vector3<f64>>::with_capacity(n)),
            |(obs, dirs), j| {
                obs.clear();
                for t in 0..n {
                    if vis[t * nt + j] {
                        let i = 2 * (t * nt + j);
                        obs.push((t, matches[i] as f64, matches[i + 1] as f64));
                    }
                }
                if obs.len() < 2 {
                    return None;
                }
                Some(solve_track(j, obs, dirs, &ps, &centers, &rots, &opts))
            },
        )
        .filter_map(|t| t)
        .collect();
    Ok(DltOutput { tracks })
}

/// Triangulates and filters one track from its observations `(view, u, v)` (ff pixels).
/// The negated comparisons are deliberate: a NaN value must reject the track.
#[allow(clippy::neg_cmp_op_on_partial_ord)]
fn solve_track(
    j: usize,
    obs: &[(usize, f64, f64)],
    dirs: &mut Vec<Vector3<f64>>,
    ps: &[Matrix3x4<f64>],
    centers: &[Vector3<f64>],
    rots: &[(nalgebra::Matrix3<f64>, Vector3<f64>)],
    opts: &DltOptions,
) -> DltTrack {
    let mut m = Matrix4::zeros();
    for &(t, u, v) in obs {
        accumulate(&mut m, &ps[t], u, v);
    }
    let count = obs.len();
    let mut tr = DltTrack {
        track: j,
        num_views: count as u32,
        point: [f64::NAN; 3],
        w: f64::NAN,
        reproj_mean: f64::NAN,
        max_angle_deg: f64::NAN,
        status: DltStatus::RejectW,
    };
    let xh = smallest_eigenvector(m);
    tr.w = xh[3];
    if !(xh[3].abs() > MIN_HOMOGENEOUS_W) {
        return tr;
    }
    let x = Vector3::new(xh[0] / xh[3], xh[1] / xh[3], xh[2] / xh[3]);
    tr.point = [x[0], x[1], x[2]];
    // mean reprojection error over the visible views
    let mut sum = 0.0;
    for &(t, u, v) in obs {
        let p = &ps[t];
        let px = p[(0, 0)] * x[0] + p[(0, 1)] * x[1] + p[(0, 2)] * x[2] + p[(0, 3)];
        let py = p[(1, 0)] * x[0] + p[(1, 1)] * x[1] + p[(1, 2)] * x[2] + p[(1, 3)];
        let pz = p[(2, 0)] * x[0] + p[(2, 1)] * x[1] + p[(2, 2)] * x[2] + p[(2, 3)];
        let dx = px / pz - u;
        let dy = py / pz - v;
        sum += (dx * dx + dy * dy).sqrt();
    }
    tr.reproj_mean = sum / count as f64;
    if !(tr.reproj_mean < opts.max_reproj_error) {
        tr.status = DltStatus::RejectReproj;
        return tr;
    }
    // max pairwise ray angle over pairs a != b = arccos of the smallest cosine
    dirs.clear();
    dirs.extend(obs.iter().map(|&(t, _, _)| (x - centers[t]).normalize()));
    let mut min_cos = f64::INFINITY;
    let mut nan = false;
    for a in 0..dirs.len() {
        for b in (a + 1)..dirs.len() {
            let c = dirs[a].dot(&dirs[b]);
            if c.is_nan() {
                nan = true;
            } else if c < min_cos {
                min_cos = c;
            }
        }
    }
    tr.max_angle_deg = if nan { f64::NAN } else { min_cos.clamp(-ANGLE_COS_CLAMP, ANGLE_COS_CLAMP).acos().to_degrees() };
    if !(tr.max_angle_deg > opts.min_tri_angle_deg) {
        tr.status = DltStatus::RejectAngle;
        return tr;
    }
    if opts.cheirality && obs.iter().any(|&(t, _, _)| (rots[t].0 * x + rots[t].1).z <= 0.0) {
        tr.status = DltStatus::RejectCheirality;
        return tr;
    }
    tr.status = DltStatus::Kept;
    tr
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;
    use ggpt_core::Dims;
    use nalgebra::Matrix3;

    fn spec_cams() -> Cameras {
        let k = Matrix3::new(500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0);
        let mut c1 = Matrix3x4::identity();
        c1[(0, 3)] = -1.0;
        Cameras { cam_from_world: vec![Matrix3x4::identity(), c1], intrinsics: vec![k, k] }
    }

    fn two_view_corr(u0: [f32; 2], u1: [f32; 2]) -> (Correspondences, Vec<bool>) {
        // N = 2, h = 1, w = 1: the single track of view 0 observed at u0 (its own pixel would be
        // (0,0): overwrite the diagonal entry directly, as if the image were large).
        let dims = Dims { n: 2, h: 1, w: 1 };
        let mut matches = vec![0f32; 8];
        matches[0] = u0[0];
        matches[1] = u0[1];
        // [t=1, s=0]
        matches[4] = u1[0];
        matches[5] = u1[1];
        let corr = Correspondences { dims, matches, scores: vec![1.0; 4], cycle: vec![0.0; 4] };
        // vis[t, j]: j = 0 (view 0 track) visible in both; j = 1 (view 1 track) only in view 1.
        let vis = vec![true, false, true, true];
        (corr, vis)
    }

    /// Test vector of `sfm.md` §9.
    #[test]
    fn spec_test_vector_exact() {
        let cams = spec_cams();
        let (corr, vis) = two_view_corr([340.0, 250.0], [240.0, 250.0]);
        let opts = DltOptions { max_reproj_error: 4.0, min_tri_angle_deg: 3.0, cheirality: false };
        let out = triangulate_tracks(&corr, &vis, &cams, &opts).unwrap();
        assert_eq!(out.tracks.len(), 1);
        let t = out.tracks[0];
        assert_eq!(t.status, DltStatus::Kept);
        let want = [0.2, 0.1, 5.0];
        for a in 0..3 {
            assert!((t.point[a] - want[a]).abs() < 1e-9, "{:?}", t.point);
        }
        assert!(t.reproj_mean < 1e-6);
        assert!((t.max_angle_deg - 11.3786).abs() < 1e-4, "{}", t.max_angle_deg);
        // angle threshold above the angle rejects
        let o2 = triangulate_tracks(&corr, &vis, &cams, &DltOptions { min_tri_angle_deg: 12.0, ..opts }).unwrap();
        assert_eq!(o2.tracks[0].status, DltStatus::RejectAngle);
        assert_eq!(o2.counts(), [1, 1, 1, 0, 0]);
    }

    #[test]
    fn spec_test_vector_noisy() {
        let cams = spec_cams();
        let (corr, vis) = two_view_corr([340.3, 249.8], [239.9, 250.4]);
        let opts = DltOptions { max_reproj_error: 4.0, min_tri_angle_deg: 3.0, cheirality: false };
        let t = triangulate_tracks(&corr, &vis, &cams, &opts).unwrap().tracks[0];
        let want = [0.202192, 0.100597, 4.980072];
        for a in 0..3 {
            assert!((t.point[a] - want[a]).abs() < 2e-6, "{:?}", t.point);
        }
        assert!((t.reproj_mean - 0.30).abs() < 0.01, "{}", t.reproj_mean);
        // reprojection threshold below the error rejects
        let o = triangulate_tracks(&corr, &vis, &cams, &DltOptions { max_reproj_error: 0.2, ..opts }).unwrap();
        assert_eq!(o.tracks[0].status, DltStatus::RejectReproj);
    }

    #[test]
    fn cheirality_option_and_outlier() {
        let cams = spec_cams();
        // a point behind both cameras: X = (0.2, 0.1, -5) projects to (300, 230) and (400, 230)
        let (corr, vis) = two_view_corr([300.0, 230.0], [400.0, 230.0]);
        let opts = DltOptions { max_reproj_error: 4.0, min_tri_angle_deg: 3.0, cheirality: false };
        let t = triangulate_tracks(&corr, &vis, &cams, &opts).unwrap().tracks[0];
        assert_eq!(t.status, DltStatus::Kept);
        assert!(t.point[2] < 0.0);
        let t = triangulate_tracks(&corr, &vis, &cams, &DltOptions { cheirality: true, ..opts }).unwrap().tracks[0];
        assert_eq!(t.status, DltStatus::RejectCheirality);
        // inconsistent rows (a 30 px vertical disagreement) fail the reprojection filter
        let (corr, vis) = two_view_corr([340.0, 250.0], [240.0, 280.0]);
        let t = triangulate_tracks(&corr, &vis, &cams, &opts).unwrap().tracks[0];
        assert_eq!(t.status, DltStatus::RejectReproj);
    }
}
