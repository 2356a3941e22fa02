//! I/O throughput of the project formats at a realistic size (run with
//! `cargo bench -p ggpt-core --bench io`). Prints a table; no assertions.

use std::time::Instant;

use ggpt_core::io::{infer_folder, official, ply, scene_dir};
use ggpt_core::{Cameras, Dims, FeedForward, GroundTruth, MatchSet, Scene, SfmResult};
use nalgebra::{Matrix3, Matrix3x4};

fn scene(n: usize, h: usize, w: usize) -> Scene {
    let d = Dims { n, h, w };
    let px = d.pixels();
    let f = |len: usize, s: u32| {
        (0..len)
            .map(|i| ((i as u32).wrapping_mul(2654435761) ^ s) as f32 / u32::MAX as f32)
            .collect::<Vec<f32>>()
    };
    let cams = || Cameras {
        cam_from_world: vec![Matrix3x4::identity(); n],
        intrinsics: vec![
            Matrix3::new(
                400.0,
                0.0,
                (w as f64 - 1.0) / 2.0,
                0.0,
                400.0,
                (h as f64 - 1.0) / 2.0,
                0.0,
                0.0,
                1.0
            );
            n
        ],
    };
    let pairs = n * n * h * w;
    Scene {
        name: "bench".into(),
        dims: d,
        images: f(3 * px, 1),
        gt: Some(GroundTruth {
            points: f(3 * px, 2),
            mask: vec![true; px],
            depth: Some(f(px, 3)),
            cameras: cams(),
        }),
        ff: Some(FeedForward {
            points: f(3 * px, 4),
            conf: f(px, 5),
            cameras: cams(),
        }),
        sfm: Some(SfmResult {
            points: f(3 * px, 6),
            mask: vec![false; px],
            cameras: cams(),
            camera_success: true,
            points_success: true,
        }),
        matches: vec![MatchSet {
            matcher: "m".into(),
            pred_matches: f(2 * pairs, 7),
            pred_scores: f(pairs, 8),
            pred_cycle_error: Some(f(pairs, 9)),
            rank_scores: None,
        }],
    }
}

fn dir_bytes(p: &std::path::Path) -> u64 {
    std::fs::read_dir(p)
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .map(|e| {
                    if e.path().is_dir() {
                        dir_bytes(&e.path())
                    } else {
                        e.metadata().map(|m| m.len()).unwrap_or(0)
                    }
                })
                .sum()
        })
        .unwrap_or(0)
}

fn row(what: &str, bytes: u64, secs: f64) {
    println!(
        "| {what:<38} | {:>9.1} | {:>8.3} | {:>8.0} |",
        bytes as f64 / 1e6,
        secs,
        bytes as f64 / 1e6 / secs
    );
}

fn main() {
    let (n, h, w) = (8, 392, 518);
    let s = scene(n, h, w);
    let tmp = tempfile::tempdir().expect("tempdir");
    println!("scene N={n} h={h} w={w}, 1 matcher with cycle error\n");
    println!("| operation                              |    MB     |    s     |   MB/s   |");
    println!("|----------------------------------------|-----------|----------|----------|");
    let d = tmp.path().join("scene");
    let t = Instant::now();
    scene_dir::write_scene(&d, &s).expect("write_scene");
    let (secs, bytes) = (t.elapsed().as_secs_f64(), dir_bytes(&d));
    row("scene_dir::write_scene", bytes, secs);
    let t = Instant::now();
    let back = ggpt_core::io::read_scene(&d).expect("read_scene");
    row(
        "scene_dir::read_scene (validated)",
        bytes,
        t.elapsed().as_secs_f64(),
    );
    assert!(back == s, "round trip differs");
    let f = tmp.path().join("folder");
    let t = Instant::now();
    infer_folder::write_infer_folder(&f, &s).expect("write_infer_folder");
    let (secs, bytes) = (t.elapsed().as_secs_f64(), dir_bytes(&f));
    row("infer_folder::write (npz deflate)", bytes, secs);
    let t = Instant::now();
    ggpt_core::io::read_scene(&f).expect("read folder");
    row("read_scene (§5.1 folder)", bytes, t.elapsed().as_secs_f64());
    let o = tmp.path().join("official.safetensors");
    let t = Instant::now();
    official::write_official_safetensors(&o, &s).expect("official");
    row(
        "official::write_official_safetensors",
        std::fs::metadata(&o).map(|m| m.len()).unwrap_or(0),
        t.elapsed().as_secs_f64(),
    );
    let ff = s.ff.as_ref().expect("ff");
    let cloud = ply::PlyCloud {
        points: ff
            .points
            .chunks_exact(3)
            .map(|p| [p[0], p[1], p[2]])
            .collect(),
        colors: vec![[1, 2, 3]; n * h * w],
        confidence: Some(ff.conf.clone()),
    };
    let p = tmp.path().join("c.ply");
    let t = Instant::now();
    ply::write_ply(&p, &cloud).expect("write_ply");
    let bytes = std::fs::metadata(&p).map(|m| m.len()).unwrap_or(0);
    row("ply::write_ply (binary)", bytes, t.elapsed().as_secs_f64());
    let t = Instant::now();
    ply::read_ply(&p).expect("read_ply");
    row("ply::read_ply (binary)", bytes, t.elapsed().as_secs_f64());
}
