//! `matches/<matcher>.safetensors` (formats.md §5.2).
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

mod common;

use std::collections::HashMap;

use common::full_scene;
use ggpt_core::io::matches::{read_matches, read_matches_raw, write_matches};
use ggpt_core::io::st::StWriter;

#[test]
fn roundtrip_raw_and_diagonal_convention() {
    let dir = tempfile::tempdir().unwrap();
    let s = full_scene(3, 2, 5);
    let p = dir.path().join("m.safetensors");
    for m in &s.matches {
        write_matches(&p, m, 3, 2, 5).unwrap();
        let raw = read_matches_raw(&p).unwrap();
        assert_eq!((raw.n, raw.h, raw.w), (3, 2, 5));
        assert_eq!(&raw.set, m);
        let f = read_matches(&p).unwrap();
        let hw = 10;
        for sv in 0..3 {
            for t in 0..3 {
                for k in 0..hw {
                    let i = (t * 3 + sv) * hw + k;
                    if t == sv {
                        assert_eq!(
                            &f.set.pred_matches[2 * i..2 * i + 2],
                            &[(k % 5) as f32, (k / 5) as f32]
                        );
                        assert_eq!(f.set.pred_scores[i], 1.0);
                        if let Some(c) = &f.set.pred_cycle_error {
                            assert_eq!(c[i], 0.0);
                        }
                    } else {
                        assert_eq!(
                            &f.set.pred_matches[2 * i..2 * i + 2],
                            &m.pred_matches[2 * i..2 * i + 2]
                        );
                        assert_eq!(f.set.pred_scores[i], m.pred_scores[i]);
                    }
                }
            }
        }
    }
}

fn write_raw(p: &std::path::Path, matches: &[f32], n: usize, hw: usize, meta: &[(&str, &str)]) {
    let mut w = StWriter::new();
    w.f32("pred_matches", &[n, n, hw, 2], matches);
    w.f32("pred_scores", &[n, n, hw], &vec![0.5; n * n * hw]);
    let meta: HashMap<String, String> = meta
        .iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect();
    std::fs::write(p, w.finish(p, Some(meta)).unwrap()).unwrap();
}

#[test]
fn normalized_edge_conversion() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("roma.safetensors");
    // h = 2, w = 4: u = -1 -> x = -0.5 (left edge), u = 1 -> x = 3.5 (right edge), 0 -> 1.5.
    let mut m = vec![0.0f32; 2 * 2 * 8 * 2];
    let i = 2 * 8; // [t=1, s=0, k=0] = (t * N + s) * hw
    m[2 * i..2 * i + 2].copy_from_slice(&[-1.0, 1.0]);
    m[2 * (i + 1)..2 * (i + 1) + 2].copy_from_slice(&[0.0, 0.0]);
    write_raw(
        &p,
        &m,
        2,
        8,
        &[
            ("height", "2"),
            ("width", "4"),
            ("coords", "normalized-edge"),
            ("matcher", "romav2-base"),
        ],
    );
    let f = read_matches(&p).unwrap();
    assert_eq!(f.set.matcher, "romav2-base");
    assert_eq!(
        &f.set.pred_matches[2 * i..2 * i + 4],
        &[-0.5, 1.5, 1.5, 0.5]
    );
}

#[test]
fn rejects_bad_files() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("bad.safetensors");
    let m = vec![0.0f32; 2 * 2 * 8 * 2];
    write_raw(&p, &m, 2, 8, &[("height", "3"), ("width", "4")]);
    let e = read_matches(&p).unwrap_err().to_string();
    assert!(
        e.contains("bad.safetensors") && e.contains("[pred_matches]") && e.contains("h*w=12"),
        "{e}"
    );
    write_raw(&p, &m, 2, 8, &[("width", "4")]);
    let e = read_matches(&p).unwrap_err().to_string();
    assert!(e.contains("[height]"), "{e}");
    write_raw(
        &p,
        &m,
        2,
        8,
        &[("height", "2"), ("width", "4"), ("coords", "weird")],
    );
    let e = read_matches(&p).unwrap_err().to_string();
    assert!(e.contains("[coords]") && e.contains("weird"), "{e}");
    // Name falls back to the file stem.
    write_raw(&p, &m, 2, 8, &[("height", "2"), ("width", "4")]);
    assert_eq!(read_matches(&p).unwrap().set.matcher, "bad");
    // NaN score.
    let mut w = StWriter::new();
    w.f32("pred_matches", &[2, 2, 8, 2], &m);
    let mut sc = vec![0.5f32; 32];
    sc[3] = f32::NAN;
    w.f32("pred_scores", &[2, 2, 8], &sc);
    let meta = HashMap::from([
        ("height".to_string(), "2".to_string()),
        ("width".to_string(), "4".to_string()),
    ]);
    std::fs::write(&p, w.finish(&p, Some(meta)).unwrap()).unwrap();
    let e = read_matches(&p).unwrap_err().to_string();
    assert!(
        e.contains("[pred_scores]") && e.contains("non-finite"),
        "{e}"
    );
    // Writer checks lengths.
    let s = full_scene(2, 3, 4);
    assert!(
        write_matches(&p, &s.matches[0], 2, 3, 5)
            .unwrap_err()
            .to_string()
            .contains("[pred_matches]")
    );
}
