//! The neighbour tables of `ggpt_model::plan::build_conv_table` against spconv 2.3.8 CPU with
//! duplicate voxels (network.md §6.4, fixture `spconv_duplicates`): a plain-Rust reference
//! convolution over the tables must reproduce spconv's outputs, and the pair sets must equal
//! spconv's raw pair tables.
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

use std::collections::BTreeSet;

use ggpt_model::plan::{CENTER_TAP, ConvTable, NUM_TAPS, build_conv_table};
use safetensors::{Dtype, SafeTensors};

const FIXTURE: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../../shared/fixtures/spconv_duplicates/spconv_duplicates.safetensors"
);

fn tensor<'a>(st: &'a SafeTensors, key: &str, dtype: Dtype) -> (Vec<usize>, &'a [u8]) {
    let t = st
        .tensor(key)
        .unwrap_or_else(|e| panic!("{FIXTURE}: key {key}: {e}"));
    assert_eq!(t.dtype(), dtype, "{key} dtype");
    (t.shape().to_vec(), t.data())
}

fn f32s(st: &SafeTensors, key: &str) -> (Vec<usize>, Vec<f32>) {
    let (s, d) = tensor(st, key, Dtype::F32);
    (
        s,
        d.chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect(),
    )
}

fn i32s(st: &SafeTensors, key: &str) -> (Vec<usize>, Vec<i32>) {
    let (s, d) = tensor(st, key, Dtype::I32);
    (
        s,
        d.chunks_exact(4)
            .map(|b| i32::from_le_bytes(b.try_into().unwrap()))
            .collect(),
    )
}

/// Grid and per-chunk exclusive ends from spconv's `[P, 4]` (batch, x, y, z) indices.
fn grid_and_offsets(indices: &[i32]) -> (Vec<[i32; 3]>, Vec<usize>) {
    let rows: Vec<&[i32]> = indices.chunks_exact(4).collect();
    let mut offsets = Vec::new();
    for (q, r) in rows.iter().enumerate() {
        let b = r[0] as usize;
        assert!(
            b + 1 >= offsets.len(),
            "points must be grouped by batch index"
        );
        while offsets.len() <= b {
            offsets.push(q);
        }
    }
    offsets.remove(0);
    offsets.push(rows.len());
    (rows.iter().map(|r| [r[1], r[2], r[3]]).collect(), offsets)
}

/// `out = bias + sum_f W_f in[source]` over the tables (KRSC weight `[C_out, 27, C_in]`), f32 loops.
fn reference_conv(
    table: &ConvTable,
    input: &[f32],
    c_in: usize,
    weight: &[f32],
    bias: &[f32],
) -> Vec<f32> {
    let c_out = bias.len();
    let n = input.len() / c_in;
    let mut out: Vec<f32> = (0..n).flat_map(|_| bias.iter().copied()).collect();
    for (f, tap) in table.taps.iter().enumerate() {
        for (&t, &s) in tap.target.iter().zip(&tap.source) {
            for o in 0..c_out {
                let w = &weight[(o * NUM_TAPS + f) * c_in..(o * NUM_TAPS + f + 1) * c_in];
                out[t * c_out + o] += w
                    .iter()
                    .zip(&input[s * c_in..(s + 1) * c_in])
                    .map(|(a, b)| a * b)
                    .sum::<f32>();
            }
        }
    }
    out
}

#[test]
fn reference_conv_over_tables_matches_spconv() {
    let bytes = std::fs::read(FIXTURE).unwrap_or_else(|e| panic!("fixture {FIXTURE} missing: {e}"));
    let st = SafeTensors::deserialize(&bytes).expect("parse spconv_duplicates.safetensors");
    for case in ["handmade", "random", "unique"] {
        let (_, idx) = i32s(&st, &format!("{case}.indices"));
        let (grid, offsets) = grid_and_offsets(&idx);
        let table = build_conv_table(&grid, &offsets);
        assert_eq!(table.has_duplicates, case != "unique", "{case}");
        let (fshape, x) = f32s(&st, &format!("{case}.features"));
        let (_, w) = f32s(&st, &format!("{case}.weight"));
        let (_, b) = f32s(&st, &format!("{case}.bias"));
        let got = reference_conv(&table, &x, fshape[1], &w, &b);
        for key in ["output", "rule_output"] {
            let (_, expect) = f32s(&st, &format!("{case}.{key}"));
            let m = expect.iter().fold(1.0f32, |a, v| a.max(v.abs()));
            let d = got
                .iter()
                .zip(&expect)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            assert_eq!(got.len(), expect.len());
            assert!(d <= 1e-5 * m, "{case}.{key}: max abs diff {d} (max {m})");
        }
    }
}

/// spconv's raw tables: row 0 input index, row 1 output index, tap f > 13 uses the count of tap
/// 26 - f. As sets of (output, input) pairs they must equal ours for every tap.
#[test]
fn pair_sets_match_spconv_raw_tables() {
    let bytes = std::fs::read(FIXTURE).unwrap_or_else(|e| panic!("fixture {FIXTURE} missing: {e}"));
    let st = SafeTensors::deserialize(&bytes).expect("parse spconv_duplicates.safetensors");
    for case in ["handmade", "random", "unique"] {
        let (_, idx) = i32s(&st, &format!("{case}.indices"));
        let (grid, offsets) = grid_and_offsets(&idx);
        let table = build_conv_table(&grid, &offsets);
        let (pshape, pairs) = i32s(&st, &format!("{case}.indice_pairs"));
        let (_, num) = i32s(&st, &format!("{case}.indice_pair_num"));
        let p = pshape[2];
        for f in 0..NUM_TAPS {
            let count = if f > CENTER_TAP {
                num[NUM_TAPS - 1 - f]
            } else {
                num[f]
            } as usize;
            let theirs: BTreeSet<(usize, usize)> = (0..count)
                .map(|i| {
                    (
                        pairs[(NUM_TAPS + f) * p + i] as usize,
                        pairs[f * p + i] as usize,
                    )
                })
                .collect();
            let ours: BTreeSet<(usize, usize)> = table.taps[f]
                .target
                .iter()
                .copied()
                .zip(table.taps[f].source.iter().copied())
                .collect();
            assert_eq!(
                ours.len(),
                table.taps[f].len(),
                "{case} tap {f}: duplicate pairs"
            );
            if f == CENTER_TAP && theirs.len() != ours.len() {
                // spconv may list the centre tap per voxel only; the rule fixes it to the identity.
                assert!(ours.iter().all(|&(a, b)| a == b), "{case} centre tap");
                continue;
            }
            assert_eq!(ours, theirs, "{case} tap {f}");
        }
    }
}
