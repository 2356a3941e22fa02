//! Shared helpers of the io integration tests.
#![allow(dead_code)]

pub mod torch;

use std::path::PathBuf;

use ggpt_core::{Cameras, Dims, FeedForward, GroundTruth, MatchSet, Scene, SfmResult};
use nalgebra::{Matrix3, Matrix3x4};

/// Path of a file of the official-format fixture (fails loudly when missing).
pub fn fixture(name: &str) -> PathBuf {
    let p = PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../../shared/fixtures/official_format/synth_room_s0"
    ))
    .join(name);
    assert!(p.exists(), "fixture missing: {}", p.display());
    p
}

/// The fixture directory itself.
pub fn fixture_dir() -> PathBuf {
    let p = PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../../shared/fixtures/official_format/synth_room_s0"
    ));
    assert!(p.is_dir(), "fixture missing: {}", p.display());
    p
}

/// Deterministic pseudo-random f32 in [0, 1) from an index (no rand dependency needed).
pub fn hashf(i: usize, salt: u32) -> f32 {
    let mut x = (i as u32).wrapping_mul(2654435761) ^ salt.wrapping_mul(40503);
    x ^= x >> 13;
    x = x.wrapping_mul(0x5bd1e995);
    x ^= x >> 15;
    (x >> 8) as f32 / (1u32 << 24) as f32
}

fn cams(n: usize, salt: u32, h: usize, w: usize) -> Cameras {
    Cameras {
        cam_from_world: (0..n)
            .map(|i| {
                let mut m = Matrix3x4::identity();
                m[(0, 3)] = hashf(i, salt) as f64 * 0.1 + 1e-17;
                m[(1, 3)] = -(i as f64) / 3.0;
                m[(2, 3)] = std::f64::consts::PI;
                m
            })
            .collect(),
        intrinsics: (0..n)
            .map(|i| {
                Matrix3::new(
                    50.0 + i as f64 / 7.0,
                    0.0,
                    (w as f64 - 1.0) / 2.0,
                    0.0,
                    51.0,
                    (h as f64 - 1.0) / 2.0,
                    0.0,
                    0.0,
                    1.0,
                )
            })
            .collect(),
    }
}

/// A small scene with every part present (N views of h x w).
pub fn full_scene(n: usize, h: usize, w: usize) -> Scene {
    let d = Dims { n, h, w };
    let px = d.pixels();
    let f = |len: usize, salt: u32| {
        (0..len)
            .map(|i| hashf(i, salt) * 2.0 - 1.0)
            .collect::<Vec<f32>>()
    };
    let b = |len: usize, salt: u32| {
        (0..len)
            .map(|i| hashf(i, salt) > 0.5)
            .collect::<Vec<bool>>()
    };
    let pairs = n * n * h * w;
    Scene {
        name: "unit scene".into(),
        dims: d,
        images: (0..3 * px).map(|i| hashf(i, 1)).collect(),
        gt: Some(GroundTruth {
            points: f(3 * px, 2),
            mask: b(px, 3),
            depth: Some(f(px, 4)),
            cameras: cams(n, 5, h, w),
        }),
        ff: Some(FeedForward {
            points: f(3 * px, 6),
            conf: f(px, 7).iter().map(|c| 1.0 + c.abs()).collect(),
            cameras: cams(n, 8, h, w),
        }),
        sfm: Some(SfmResult {
            points: f(3 * px, 9),
            mask: b(px, 10),
            cameras: cams(n, 11, h, w),
            camera_success: true,
            points_success: false,
        }),
        matches: vec![
            MatchSet {
                matcher: "romav2-base".into(),
                pred_matches: f(2 * pairs, 12),
                pred_scores: f(pairs, 13),
                pred_cycle_error: Some(f(pairs, 14)),
                rank_scores: None,
            },
            MatchSet {
                matcher: "synthetic_b".into(),
                pred_matches: f(2 * pairs, 15),
                pred_scores: f(pairs, 16),
                pred_cycle_error: None,
                rank_scores: Some(f(n * h * w, 17)),
            },
        ],
    }
}
