use super::*;
use nalgebra::{Rotation3, Unit};
use rand::SeedableRng;
use rand_pcg::Pcg64;

const SFM_SMALL: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../../shared/fixtures/sfm_small"
);

fn p(x: f64, y: f64, z: f64) -> Point3<f64> {
    Point3::new(x, y, z)
}

fn max_abs_diff(a: &Matrix3x4<f64>, b: &Matrix3x4<f64>) -> f64 {
    (a - b).abs().max()
}

fn random_sim3(rng: &mut Pcg64) -> Sim3 {
    let axis = Unit::new_normalize(Vector3::new(
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
    ));
    let angle = rng.random_range(-3.0..3.0);
    Sim3 {
        scale: rng.random_range(0.2..5.0),
        rotation: *Rotation3::from_axis_angle(&axis, angle).matrix(),
        translation: Vector3::new(
            rng.random_range(-5.0..5.0),
            rng.random_range(-5.0..5.0),
            rng.random_range(-5.0..5.0),
        ),
    }
}

fn random_points(rng: &mut Pcg64, n: usize, spread: f64) -> Vec<Point3<f64>> {
    (0..n)
        .map(|_| {
            p(
                rng.random_range(-spread..spread),
                rng.random_range(-spread..spread),
                rng.random_range(-spread..spread),
            )
        })
        .collect()
}

#[test]
fn spec_test_vector() {
    let src = [
        p(0., 0., 0.),
        p(1., 0., 0.),
        p(0., 1., 0.),
        p(0., 0., 1.),
        p(1., 1., 1.),
    ];
    let tgt = [
        p(1., 2., 3.),
        p(1., 4., 3.),
        p(-1., 2., 3.),
        p(1., 2., 5.),
        p(-1., 4., 5.),
    ];
    let s = umeyama(&src, &tgt).unwrap();
    assert!((s.scale - 2.0).abs() < 1e-12, "scale {}", s.scale);
    let r_want = Matrix3::new(0., -1., 0., 1., 0., 0., 0., 0., 1.);
    assert!(
        (s.rotation - r_want).abs().max() < 1e-12,
        "rotation {}",
        s.rotation
    );
    assert!(
        (s.translation - Vector3::new(1., 2., 3.)).abs().max() < 1e-12,
        "t {}",
        s.translation
    );
    // The robust estimator on exact data returns the same model with every pair an inlier.
    let mut rng = Pcg64::seed_from_u64(42);
    let r = robust_sim3(&src, &tgt, &RobustSim3Options::default(), &mut rng).unwrap();
    assert_eq!(r.num_inliers, 5);
    assert!(r.inliers.iter().all(|&b| b));
    assert!(max_abs_diff(&r.sim3.to_matrix3x4(), &s.to_matrix3x4()) < 1e-12);
    for (a, b) in src.iter().zip(tgt.iter()) {
        assert!((s.apply(a) - b).norm() < 1e-12);
    }
}

#[test]
fn trial_cap_is_twenty() {
    assert_eq!(compute_num_trials(80_000, 100_000, 0.99, 3.0), 20);
    // All inliers: one trial suffices; no inlier: unbounded.
    assert_eq!(compute_num_trials(10, 10, 0.99, 3.0), 1);
    assert_eq!(compute_num_trials(0, 10, 0.99, 3.0), usize::MAX);
    // Monotone: fewer inliers need more trials.
    assert!(compute_num_trials(500, 1000, 0.99, 3.0) > compute_num_trials(900, 1000, 0.99, 3.0));
}

#[test]
fn recovers_random_similarity() {
    let mut rng = Pcg64::seed_from_u64(7);
    for _ in 0..20 {
        let truth = random_sim3(&mut rng);
        let src = random_points(&mut rng, 50, 2.0);
        let tgt: Vec<_> = src.iter().map(|x| truth.apply(x)).collect();
        let est = umeyama(&src, &tgt).unwrap();
        assert!(max_abs_diff(&est.to_matrix3x4(), &truth.to_matrix3x4()) < 1e-9);
        assert!((est.scale - truth.scale).abs() < 1e-9);
        assert!((est.rotation.determinant() - 1.0).abs() < 1e-12);
        // Inverse and compose round-trip.
        let id = est.inverse().unwrap().compose(&est);
        assert!(max_abs_diff(&id.to_matrix3x4(), &Sim3::identity().to_matrix3x4()) < 1e-9);
    }
}

#[test]
fn reflection_is_never_returned() {
    // Target = mirrored source: the best proper rotation must still have det +1.
    let mut rng = Pcg64::seed_from_u64(3);
    let src = random_points(&mut rng, 30, 1.0);
    let tgt: Vec<_> = src.iter().map(|x| p(-x.x, x.y, x.z)).collect();
    let s = umeyama(&src, &tgt).unwrap();
    assert!((s.rotation.determinant() - 1.0).abs() < 1e-12);
    assert!(
        (s.rotation.transpose() * s.rotation - Matrix3::identity())
            .abs()
            .max()
            < 1e-12
    );
    assert!(
        s.scale > 0.0 && s.scale < 1.0,
        "a reflection cannot be fitted exactly: scale {}",
        s.scale
    );
    // Planar source mirrored across its own plane: a rotation by 180° fits exactly.
    let planar: Vec<_> = src.iter().map(|x| p(x.x, x.y, 0.0)).collect();
    let mirrored: Vec<_> = planar.iter().map(|x| p(x.x, -x.y, 0.0)).collect();
    let s = umeyama(&planar, &mirrored).unwrap();
    assert!((s.rotation.determinant() - 1.0).abs() < 1e-12);
    assert!((s.scale - 1.0).abs() < 1e-9, "scale {}", s.scale);
    for (a, b) in planar.iter().zip(mirrored.iter()) {
        assert!((s.apply(a) - b).norm() < 1e-9);
    }
}

#[test]
fn robust_to_thirty_percent_outliers() {
    let mut rng = Pcg64::seed_from_u64(11);
    for round in 0..5 {
        let truth = random_sim3(&mut rng);
        let n = 1000;
        let src = random_points(&mut rng, n, 1.0);
        let mut tgt: Vec<_> = src.iter().map(|x| truth.apply(x)).collect();
        let mut is_outlier = vec![false; n];
        for i in 0..n {
            if rng.random_bool(0.3) {
                is_outlier[i] = true;
                tgt[i] += Vector3::new(
                    rng.random_range(1.0..3.0),
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-3.0..3.0),
                );
            }
        }
        let res = robust_sim3(&src, &tgt, &RobustSim3Options::default(), &mut rng).unwrap();
        assert!(
            max_abs_diff(&res.sim3.to_matrix3x4(), &truth.to_matrix3x4()) < 1e-9,
            "round {round}"
        );
        let want: Vec<bool> = is_outlier.iter().map(|o| !o).collect();
        assert_eq!(res.inliers, want, "round {round}");
        assert_eq!(res.num_inliers, want.iter().filter(|b| **b).count());
        assert!(res.num_trials <= 20);
        // Plain Umeyama is pulled away by the outliers.
        let plain = umeyama(&src, &tgt).unwrap();
        assert!(max_abs_diff(&plain.to_matrix3x4(), &truth.to_matrix3x4()) > 1e-2);
    }
}

#[test]
fn noisy_inliers_use_local_optimisation() {
    let mut rng = Pcg64::seed_from_u64(5);
    let truth = random_sim3(&mut rng);
    let n = 2000;
    let src = random_points(&mut rng, n, 1.0);
    let tgt: Vec<_> = src
        .iter()
        .map(|x| {
            let noise = Vector3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            ) * 0.005;
            truth.apply(x) + noise
        })
        .collect();
    let res = robust_sim3(
        &src,
        &tgt,
        &RobustSim3Options::with_max_error(0.03 * truth.scale),
        &mut rng,
    )
    .unwrap();
    assert!(res.num_local_refits >= 1);
    assert!(res.num_inliers > n * 95 / 100, "{}", res.num_inliers);
    assert!(
        max_abs_diff(&res.sim3.to_matrix3x4(), &truth.to_matrix3x4())
            < 2e-3 * truth.scale.max(1.0) * 5.0
    );
}

#[test]
fn degenerate_inputs_fail() {
    let two = [p(0., 0., 0.), p(1., 0., 0.)];
    assert!(umeyama(&two, &two).is_err());
    let same = [p(1., 1., 1.); 5];
    assert!(umeyama(&same, &same).is_err());
    let a = [p(0., 0., 0.), p(1., 0., 0.), p(0., 1., 0.)];
    assert!(umeyama(&a, &a[..2]).is_err());
    let nan = [p(0., 0., 0.), p(1., f64::NAN, 0.), p(0., 1., 0.)];
    assert!(umeyama(&nan, &a).is_err());
    assert!(umeyama(&a, &nan).is_err());
    let mut rng = Pcg64::seed_from_u64(1);
    assert!(robust_sim3(&two, &two, &RobustSim3Options::default(), &mut rng).is_err());
    assert!(robust_sim3(&same, &same, &RobustSim3Options::default(), &mut rng).is_err());
    assert!(robust_sim3(&a, &a[..2], &RobustSim3Options::default(), &mut rng).is_err());
    assert!(
        Sim3 {
            scale: 0.0,
            ..Sim3::identity()
        }
        .inverse()
        .is_err()
    );
}

#[test]
fn retry_schedule_branches() {
    let mut rng = Pcg64::seed_from_u64(2);
    // Exact data: first threshold succeeds.
    let truth = random_sim3(&mut rng);
    let src = random_points(&mut rng, 100, 1.0);
    let tgt: Vec<_> = src.iter().map(|x| truth.apply(x)).collect();
    let (s, info) = align_with_retries(&src, &tgt, 0.03, &mut rng);
    assert_eq!(info.method, AlignMethod::Robust { max_error: 0.03 });
    assert_eq!(info.thresholds_tried, vec![0.03]);
    assert_eq!(info.num_inliers, Some(100));
    assert!(max_abs_diff(&s.to_matrix3x4(), &truth.to_matrix3x4()) < 1e-9);

    // Unrelated, widely spread points: every robust threshold fails, plain Umeyama is used.
    let src = random_points(&mut rng, 60, 100.0);
    let tgt = random_points(&mut rng, 60, 100.0);
    let (s, info) = align_with_retries(&src, &tgt, 0.03, &mut rng);
    assert_eq!(info.method, AlignMethod::PlainUmeyama);
    let tried = info.thresholds_tried;
    assert_eq!(tried.len(), 4);
    for (t, want) in tried.iter().zip([0.03, 0.09, 0.27, 0.81]) {
        assert!((t - want).abs() < 1e-12, "{tried:?}");
    }
    assert_eq!(s, umeyama(&src, &tgt).unwrap());

    // Too few points: identity.
    let (s, info) = align_with_retries(&src[..2], &tgt[..2], 0.03, &mut rng);
    assert_eq!(info.method, AlignMethod::Identity);
    assert_eq!(s, Sim3::identity());
}

#[test]
fn noise_needs_a_larger_threshold() {
    // Inlier noise ~0.2: the 0.03 and 0.09 thresholds keep < 3 inliers, a later one succeeds.
    let mut rng = Pcg64::seed_from_u64(9);
    let src = random_points(&mut rng, 8, 1.0);
    let tgt: Vec<_> = src
        .iter()
        .map(|x| {
            x + Vector3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            ) * 0.4
        })
        .collect();
    let (_, info) = align_with_retries(&src, &tgt, 0.03, &mut rng);
    match info.method {
        AlignMethod::Robust { max_error } => assert!(max_error > 0.03 + 1e-12, "{info:?}"),
        m => panic!("unexpected {m:?}"),
    }
    assert!(info.thresholds_tried.len() >= 2);
}

// ---- sfm_small fixture -------------------------------------------------------------------------

struct Fixture {
    ff_points: Vec<f32>,
    dlt_points: Vec<f32>,
    ff_mask: Vec<bool>,
    inlier_mask: Vec<bool>,
    tgt_from_src: Matrix3x4<f64>,
    sim3d_mat_f32: Matrix3x4<f32>,
    ff_aligned: Vec<f32>,
}

fn read_bytes(path: &str) -> Vec<u8> {
    std::fs::read(path).unwrap_or_else(|e| panic!("fixture {path} missing or unreadable: {e}"))
}

fn tensor<'a>(
    st: &'a safetensors::SafeTensors<'a>,
    file: &str,
    key: &str,
) -> safetensors::tensor::TensorView<'a> {
    st.tensor(key)
        .unwrap_or_else(|e| panic!("{file}: tensor {key}: {e}"))
}

fn f32s(st: &safetensors::SafeTensors<'_>, file: &str, key: &str) -> Vec<f32> {
    let t = tensor(st, file, key);
    assert_eq!(t.dtype(), safetensors::Dtype::F32, "{file}: {key}");
    t.data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

fn f64s(st: &safetensors::SafeTensors<'_>, file: &str, key: &str) -> Vec<f64> {
    let t = tensor(st, file, key);
    assert_eq!(t.dtype(), safetensors::Dtype::F64, "{file}: {key}");
    t.data()
        .chunks_exact(8)
        .map(|b| f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]))
        .collect()
}

fn bools(st: &safetensors::SafeTensors<'_>, file: &str, key: &str) -> Vec<bool> {
    let t = tensor(st, file, key);
    assert_eq!(t.dtype(), safetensors::Dtype::BOOL, "{file}: {key}");
    t.data().iter().map(|b| *b != 0).collect()
}

fn load_fixture() -> Fixture {
    let inputs_path = format!("{SFM_SMALL}/inputs.safetensors");
    let steps_path = format!("{SFM_SMALL}/steps.safetensors");
    let inputs_bytes = read_bytes(&inputs_path);
    let steps_bytes = read_bytes(&steps_path);
    let inputs = safetensors::SafeTensors::deserialize(&inputs_bytes).unwrap();
    let steps = safetensors::SafeTensors::deserialize(&steps_bytes).unwrap();
    let m64 = f64s(&steps, &steps_path, "sim3/ff_tgt_from_src_f64");
    let m32 = f32s(&steps, &steps_path, "sim3/ff_sim3d_mat");
    Fixture {
        ff_points: f32s(&inputs, &inputs_path, "ff/points"),
        dlt_points: f32s(&steps, &steps_path, "scatter/points"),
        ff_mask: bools(&steps, &steps_path, "sim3/ff_mask"),
        inlier_mask: bools(&steps, &steps_path, "sim3/ff_inlier_mask"),
        tgt_from_src: Matrix3x4::from_row_slice(&m64),
        sim3d_mat_f32: Matrix3x4::from_row_slice(&m32),
        ff_aligned: f32s(&steps, &steps_path, "sim3/ff_aligned"),
    }
}

fn masked_pairs(fx: &Fixture) -> (Vec<Point3<f64>>, Vec<Point3<f64>>) {
    let mut src = Vec::new();
    let mut tgt = Vec::new();
    for (i, &m) in fx.ff_mask.iter().enumerate() {
        if m {
            let a = &fx.ff_points[3 * i..3 * i + 3];
            let b = &fx.dlt_points[3 * i..3 * i + 3];
            src.push(p(a[0] as f64, a[1] as f64, a[2] as f64));
            tgt.push(p(b[0] as f64, b[1] as f64, b[2] as f64));
        }
    }
    (src, tgt)
}

/// Official inlier count of the ff -> DLT alignment on `sfm_small` (fixture README, "Sim(3)").
const OFFICIAL_INLIERS: usize = 5608;
/// Inlier-count window. Seven official runs gave 5590..5639 (5608 recorded). Our estimator
/// (same algorithm, different random draws) lands in two modes on this scene: ~5607-5628
/// (the official transform's mode, within 1e-3 of it) and ~5638-5660 (a higher-support optimum).
/// The window is the official range widened by 30 on each side.
const INLIER_RANGE: (usize, usize) = (5590 - 30, 5639 + 30);
/// Matrix-entry tolerance to the official transform for a run in the official mode (fixture
/// README: repeated official runs spread by up to 1.9e-3).
const MATRIX_TOLERANCE: f64 = 2e-3;
/// Matrix-entry bound for any run: the higher-support mode lies 2.2e-3..6e-3 from the official
/// transform (40 seeds measured), i.e. ~3x the official run-to-run spread.
const MATRIX_BOUND: f64 = 7.5e-3;

#[test]
fn sfm_small_robust_sim3_matches_official() {
    let fx = load_fixture();
    let (src, tgt) = masked_pairs(&fx);
    assert_eq!(src.len(), 7794);
    assert_eq!(fx.inlier_mask.len(), 7794);
    // The official inlier mask is `residual <= max_error^2` under the official transform.
    let m3 = fx.tgt_from_src.fixed_view::<3, 3>(0, 0).into_owned();
    let scale = m3.determinant().cbrt();
    let official = Sim3 {
        scale,
        rotation: m3 / scale,
        translation: fx.tgt_from_src.column(3).into_owned(),
    };
    let official_inliers: Vec<bool> = src
        .iter()
        .zip(tgt.iter())
        .map(|(a, b)| (official.apply(a) - b).norm_squared() <= 0.03 * 0.03)
        .collect();
    assert_eq!(official_inliers, fx.inlier_mask);
    assert_eq!(
        official_inliers.iter().filter(|b| **b).count(),
        OFFICIAL_INLIERS
    );

    let mut within_tolerance = 0;
    let seeds = 0u64..10;
    let num_seeds = seeds.end as usize;
    for seed in seeds {
        let mut rng = Pcg64::seed_from_u64(seed);
        let res = robust_sim3(&src, &tgt, &RobustSim3Options::default(), &mut rng).unwrap();
        let diff = max_abs_diff(&res.sim3.to_matrix3x4(), &fx.tgt_from_src);
        assert!(
            diff < MATRIX_BOUND,
            "seed {seed}: max |delta matrix| {diff}"
        );
        if diff < MATRIX_TOLERANCE {
            within_tolerance += 1;
        }
        assert!(
            (INLIER_RANGE.0..=INLIER_RANGE.1).contains(&res.num_inliers),
            "seed {seed}: {} inliers vs official {OFFICIAL_INLIERS}",
            res.num_inliers
        );
        assert_eq!(res.inliers.iter().filter(|b| **b).count(), res.num_inliers);
        assert_eq!(
            res.num_trials, 20,
            "dynamic stopping needs ~30 trials at a 72% inlier ratio"
        );
    }
    assert!(
        within_tolerance * 3 >= num_seeds,
        "only {within_tolerance}/{num_seeds} seeds within {MATRIX_TOLERANCE}"
    );
}

#[test]
fn sfm_small_f32_application_is_bit_exact() {
    let fx = load_fixture();
    // The official f32 matrix is the f64 estimate cast to f32.
    assert_eq!(fx.tgt_from_src.map(|v| v as f32), fx.sim3d_mat_f32);
    let mut pts = fx.ff_points.clone();
    apply_matrix_f32(&fx.sim3d_mat_f32, &mut pts);
    assert_eq!(pts.len(), fx.ff_aligned.len());
    let mismatches = pts
        .iter()
        .zip(fx.ff_aligned.iter())
        .filter(|(a, b)| a.to_bits() != b.to_bits())
        .count();
    assert_eq!(
        mismatches, 0,
        "f32 application differs from sim3/ff_aligned"
    );
}

#[test]
fn rank_deficient_samples_are_rejected_like_colmap() {
    // Source points on the plane z = 0 through the origin: every uncentred 3-sample (and the
    // whole set) has rank 2, so COLMAP's estimator yields no model; plain Umeyama (centred) works.
    let mut rng = Pcg64::seed_from_u64(8);
    let truth = random_sim3(&mut rng);
    let src: Vec<_> = random_points(&mut rng, 50, 1.0)
        .into_iter()
        .map(|q| p(q.x, q.y, 0.0))
        .collect();
    let tgt: Vec<_> = src.iter().map(|x| truth.apply(x)).collect();
    assert!(robust_sim3(&src, &tgt, &RobustSim3Options::default(), &mut rng).is_err());
    let (s, info) = align_with_retries(&src, &tgt, 0.03, &mut rng);
    assert_eq!(info.method, AlignMethod::PlainUmeyama);
    assert!(max_abs_diff(&s.to_matrix3x4(), &truth.to_matrix3x4()) < 1e-9);
    // Shifted off the origin the same plane is fine (uncentred rank 3).
    let src2: Vec<_> = src.iter().map(|q| p(q.x, q.y, 1.0)).collect();
    let tgt2: Vec<_> = src2.iter().map(|x| truth.apply(x)).collect();
    let r = robust_sim3(&src2, &tgt2, &RobustSim3Options::default(), &mut rng).unwrap();
    assert_eq!(r.num_inliers, 50);
    assert!(full_rank(&src2, &(0..50).collect::<Vec<_>>()));
    assert!(!full_rank(&src, &(0..50).collect::<Vec<_>>()));
}
