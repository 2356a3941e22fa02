//! Exact comparison of `ggpt_model::plan` against the official intermediates of the `ggpt_small`
//! fixture (network.md §13 steps 1-4), plus batched == per-chunk planning and a plain-Rust
//! reference convolution over the neighbour tables against the recorded xCPE convolutions.
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

use ggpt_model::plan::{
    BatchPlan, ChunkInput, FEAT_DIM, FEAT_NO_EMBED_DIM, NUM_ORDERS, NUM_TAPS, PlanConfig,
    TYPE_EMBED_DIM, plan_batch,
};
use safetensors::{Dtype, SafeTensors};

const FIXTURE_DIR: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../../shared/fixtures/ggpt_small"
);
const CHUNKS: [usize; 2] = [0, 1];

fn read(name: &str) -> Vec<u8> {
    let path = format!("{FIXTURE_DIR}/{name}");
    std::fs::read(&path).unwrap_or_else(|e| panic!("fixture {path} missing or unreadable: {e}"))
}

struct St<'a>(SafeTensors<'a>, &'static str);

impl St<'_> {
    fn raw(&self, key: &str, dtype: Dtype) -> (Vec<usize>, &[u8]) {
        let t = self
            .0
            .tensor(key)
            .unwrap_or_else(|e| panic!("{}: key {key}: {e}", self.1));
        assert_eq!(t.dtype(), dtype, "{}: key {key} dtype", self.1);
        (t.shape().to_vec(), t.data())
    }
    fn f32(&self, key: &str) -> (Vec<usize>, Vec<f32>) {
        let (s, d) = self.raw(key, Dtype::F32);
        (
            s,
            d.chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect(),
        )
    }
    fn i64(&self, key: &str) -> (Vec<usize>, Vec<i64>) {
        let (s, d) = self.raw(key, Dtype::I64);
        (
            s,
            d.chunks_exact(8)
                .map(|b| i64::from_le_bytes(b.try_into().unwrap()))
                .collect(),
        )
    }
    fn i32(&self, key: &str) -> (Vec<usize>, Vec<i32>) {
        let (s, d) = self.raw(key, Dtype::I32);
        (
            s,
            d.chunks_exact(4)
                .map(|b| i32::from_le_bytes(b.try_into().unwrap()))
                .collect(),
        )
    }
    fn bool(&self, key: &str) -> Vec<bool> {
        self.raw(key, Dtype::BOOL)
            .1
            .iter()
            .map(|&b| b != 0)
            .collect()
    }
}

fn triples(v: &[f32]) -> Vec<[f32; 3]> {
    v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
}

fn load_chunk(st: &St, c: usize) -> ChunkInput {
    ChunkInput {
        ff_pts: triples(&st.f32(&format!("chunk{c}/ff_pts")).1),
        ff_conf: st.f32(&format!("chunk{c}/ff_pts_conf")).1,
        geo_pts: triples(&st.f32(&format!("chunk{c}/geo_pts")).1),
        geo_msk: st.bool(&format!("chunk{c}/geo_msks")),
    }
}

fn as_i64(v: &[usize]) -> Vec<i64> {
    v.iter().map(|&x| x as i64).collect()
}

/// Plain-Rust submanifold conv over the plan's tables: `out = bias + sum_f W_f in[source]` with the
/// KRSC weight `[C_out, 27, C_in]`.
fn reference_conv(
    plan_taps: &[ggpt_model::plan::TapPairs],
    input: &[f32],
    c_in: usize,
    weight: &[f32],
    bias: &[f32],
) -> Vec<f32> {
    let c_out = bias.len();
    let n = input.len() / c_in;
    let mut out: Vec<f32> = (0..n).flat_map(|_| bias.iter().copied()).collect();
    assert_eq!(plan_taps.len(), NUM_TAPS);
    for (f, tap) in plan_taps.iter().enumerate() {
        for (&t, &s) in tap.target.iter().zip(&tap.source) {
            for o in 0..c_out {
                let w = &weight[(o * NUM_TAPS + f) * c_in..(o * NUM_TAPS + f + 1) * c_in];
                let x = &input[s * c_in..(s + 1) * c_in];
                out[t * c_out + o] += w.iter().zip(x).map(|(a, b)| a * b).sum::<f32>();
            }
        }
    }
    out
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn check_chunk(plan: &BatchPlan, inter: &St, weights: &St, c: usize) {
    let k = |name: &str| format!("chunk{c}/{name}");
    let lv0 = &plan.levels[0];
    let n = plan.tokens.num_tokens;

    // §3.3 features (channels 16..218) and embeddings selection.
    let (shape, feat) = inter.f32(&k("input.feat"));
    assert_eq!(shape, [n, FEAT_DIM], "chunk{c} input.feat shape");
    let e_ff = weights.f32("ff_type_embed").1;
    let e_dlt = weights.f32("dlt_type_embed").1;
    let mut worst = 0.0f32;
    for j in 0..n {
        let row = &feat[j * FEAT_DIM..(j + 1) * FEAT_DIM];
        let emb = if plan.tokens.is_dlt[j] { &e_dlt } else { &e_ff };
        assert_eq!(
            &row[..TYPE_EMBED_DIM],
            &emb[..],
            "chunk{c} token {j}: type embedding / is_dlt"
        );
        let mine = &plan.tokens.feat_no_embed[j * FEAT_NO_EMBED_DIM..(j + 1) * FEAT_NO_EMBED_DIM];
        worst = worst.max(max_abs_diff(&row[TYPE_EMBED_DIM..], mine));
    }
    assert!(worst <= 1e-5, "chunk{c} input.feat max abs diff {worst}");
    let coord = inter.f32(&k("input.coord")).1;
    let mine: Vec<f32> = plan.tokens.coord.iter().flatten().copied().collect();
    assert!(max_abs_diff(&coord, &mine) <= 1e-5, "chunk{c} input.coord");

    // §3.4 grid.
    let grid0: Vec<i32> = lv0.grid.iter().flatten().copied().collect();
    assert_eq!(
        inter.i32(&k("input.grid_coord")).1,
        grid0,
        "chunk{c} input.grid_coord"
    );

    for (l, lv) in plan.levels.iter().enumerate() {
        let grid: Vec<i32> = lv.grid.iter().flatten().copied().collect();
        assert_eq!(
            inter.i32(&k(&format!("level{l}.grid_coord"))).1,
            grid,
            "chunk{c} level{l}.grid_coord"
        );
        assert_eq!(
            inter.i64(&k(&format!("level{l}.serialized_depth"))).1,
            [lv.depth[0] as i64],
            "chunk{c} level{l} depth"
        );
        let (shape, code) = inter.i64(&k(&format!("level{l}.serialized_code")));
        assert_eq!(shape, [NUM_ORDERS, lv.num_tokens]);
        let (_, order) = inter.i64(&k(&format!("level{l}.serialized_order")));
        for r in 0..NUM_ORDERS {
            let row = r * lv.num_tokens..(r + 1) * lv.num_tokens;
            let mine: Vec<i64> = lv.codes[r].iter().map(|&x| x as i64).collect();
            assert_eq!(
                code[row.clone()],
                mine[..],
                "chunk{c} level{l} code row {r}"
            );
            assert_eq!(
                order[row],
                as_i64(&lv.order[r])[..],
                "chunk{c} level{l} order row {r}"
            );
        }
        let t = lv.official_attn_tables();
        assert_eq!(
            inter.i64(&k(&format!("level{l}.attn_pad"))).1,
            as_i64(&t.pad),
            "chunk{c} level{l} attn_pad"
        );
        assert_eq!(
            inter.i64(&k(&format!("level{l}.attn_cu_seqlens"))).1,
            as_i64(&t.cu_seqlens),
            "chunk{c} level{l} attn_cu_seqlens"
        );
        assert_eq!(
            t.unpad,
            (0..lv.num_tokens).collect::<Vec<_>>(),
            "batch size 1: unpad is the identity"
        );
        if l >= 1 {
            let cluster = &plan.levels[l - 1]
                .pool_to_next
                .as_ref()
                .expect("pool map")
                .cluster;
            assert_eq!(
                inter.i64(&k(&format!("enc{l}.down.cluster"))).1,
                as_i64(cluster),
                "chunk{c} enc{l}.down.cluster"
            );
        }
    }

    // Recorded xCPE convolutions through the plan's neighbour tables (level 0 with duplicates,
    // level-0 decoder with the stale input, and a pooled level).
    for (blk, input, level, prefix) in [
        (
            "enc0.block0",
            "embedding.out",
            0usize,
            "backbone.backbone.enc.enc0.block0",
        ),
        (
            "dec0.block0",
            "dec0.up.proj_skip",
            0,
            "backbone.backbone.dec.dec0.block0",
        ),
        (
            "enc3.block2",
            "enc3.block1.out",
            3,
            "backbone.backbone.enc.enc3.block2",
        ),
    ] {
        let (ishape, x) = inter.f32(&k(input));
        let (wshape, w) = weights.f32(&format!("{prefix}.cpe.0.weight"));
        let b = weights.f32(&format!("{prefix}.cpe.0.bias")).1;
        assert_eq!(wshape[4], ishape[1]);
        let got = reference_conv(&plan.levels[level].conv.taps, &x, ishape[1], &w, &b);
        let expect = inter.f32(&k(&format!("{blk}.cpe_conv_out"))).1;
        let m = expect.iter().fold(1.0f32, |a, v| a.max(v.abs()));
        let d = max_abs_diff(&got, &expect);
        assert!(
            d <= 1e-5 * m,
            "chunk{c} {blk} conv max abs diff {d} (max {m})"
        );
    }
}

#[test]
fn plan_matches_official_intermediates() {
    let (ib, nb, wb) = (
        read("inputs.safetensors"),
        read("intermediates.safetensors"),
        read("weights.safetensors"),
    );
    let inputs = St(
        SafeTensors::deserialize(&ib).expect("inputs.safetensors"),
        "inputs.safetensors",
    );
    let inter = St(
        SafeTensors::deserialize(&nb).expect("intermediates.safetensors"),
        "intermediates.safetensors",
    );
    let weights = St(
        SafeTensors::deserialize(&wb).expect("weights.safetensors"),
        "weights.safetensors",
    );
    let cfg = PlanConfig::small();
    for c in CHUNKS {
        let plan = plan_batch(&[load_chunk(&inputs, c)], &cfg).expect("plan");
        let sizes: Vec<usize> = plan.levels.iter().map(|l| l.num_tokens).collect();
        let expect_sizes: [usize; 5] = if c == 0 {
            [2296, 1743, 1109, 753, 531]
        } else {
            [679, 592, 371, 163, 93]
        };
        assert_eq!(sizes, expect_sizes, "chunk{c} level sizes");
        check_chunk(&plan, &inter, &weights, c);
    }
}

/// Planning both chunks in one batch gives each chunk exactly its single-chunk tables, shifted by
/// the chunk's token offset at every level (network.md §4.1).
#[test]
fn batched_plan_equals_single_chunk_plans() {
    let ib = read("inputs.safetensors");
    let inputs = St(
        SafeTensors::deserialize(&ib).expect("inputs.safetensors"),
        "inputs.safetensors",
    );
    let cfg = PlanConfig::small();
    let chunks: Vec<ChunkInput> = CHUNKS.iter().map(|&c| load_chunk(&inputs, c)).collect();
    let singles: Vec<BatchPlan> = chunks
        .iter()
        .map(|c| plan_batch(std::slice::from_ref(c), &cfg).unwrap())
        .collect();
    for batch_order in [[0usize, 1], [1, 0]] {
        let batch: Vec<ChunkInput> = batch_order.iter().map(|&i| chunks[i].clone()).collect();
        let plan = plan_batch(&batch, &cfg).unwrap();
        assert_eq!(plan.layout.len(), 2);
        for (b, &ci) in batch_order.iter().enumerate() {
            let single = &singles[ci];
            let lay = plan.layout[b];
            assert_eq!(lay.num_dense, chunks[ci].ff_pts.len());
            let n0 = single.tokens.num_tokens;
            let fs = lay.token_start * FEAT_NO_EMBED_DIM;
            assert_eq!(
                plan.tokens.feat_no_embed[fs..fs + n0 * FEAT_NO_EMBED_DIM],
                single.tokens.feat_no_embed[..]
            );
            assert_eq!(
                plan.tokens.dlt_pixel[lay.dlt_start..lay.dlt_start + lay.num_dlt],
                single.tokens.dlt_pixel[..]
            );
            for (l, (lv, sl)) in plan.levels.iter().zip(&single.levels).enumerate() {
                let start = if b == 0 { 0 } else { lv.offsets[b - 1] };
                let n = sl.num_tokens;
                assert_eq!(lv.offsets[b] - start, n, "level {l} count");
                let shift = |v: &[usize]| v.iter().map(|&x| x + start).collect::<Vec<_>>();
                assert_eq!(lv.grid[start..start + n], sl.grid[..]);
                assert_eq!(lv.depth[b], sl.depth[0]);
                for r in 0..NUM_ORDERS {
                    assert_eq!(
                        lv.codes[r][start..start + n],
                        sl.codes[r][..],
                        "level {l} row {r}"
                    );
                    assert_eq!(
                        lv.order[r][start..start + n],
                        shift(&sl.order[r])[..],
                        "level {l} row {r}"
                    );
                    assert_eq!(
                        lv.inverse[r][start..start + n],
                        shift(&sl.inverse[r])[..],
                        "level {l} row {r}"
                    );
                }
                let wins: Vec<_> = lv
                    .windows
                    .iter()
                    .filter(|w| w.start >= start && w.start < start + n)
                    .map(|w| (w.start - start, w.len, w.owned_from - start, w.owned_len))
                    .collect();
                let swins: Vec<_> = sl
                    .windows
                    .iter()
                    .map(|w| (w.start, w.len, w.owned_from, w.owned_len))
                    .collect();
                assert_eq!(wins, swins, "level {l} windows");
                for f in 0..NUM_TAPS {
                    let pairs: Vec<(usize, usize)> = lv.conv.taps[f]
                        .target
                        .iter()
                        .zip(&lv.conv.taps[f].source)
                        .filter(|&(&t, _)| t >= start && t < start + n)
                        .map(|(&t, &s)| {
                            assert!(s >= start && s < start + n, "conv pair crosses chunks");
                            (t - start, s - start)
                        })
                        .collect();
                    let spairs: Vec<(usize, usize)> = sl.conv.taps[f]
                        .target
                        .iter()
                        .copied()
                        .zip(sl.conv.taps[f].source.iter().copied())
                        .collect();
                    assert_eq!(pairs, spairs, "level {l} tap {f}");
                }
                if let (Some(p), Some(sp)) = (&lv.pool_to_next, &sl.pool_to_next) {
                    let cstart = if b == 0 {
                        0
                    } else {
                        plan.levels[l + 1].offsets[b - 1]
                    };
                    let cl: Vec<usize> = p.cluster[start..start + n]
                        .iter()
                        .map(|&m| m - cstart)
                        .collect();
                    assert_eq!(cl, sp.cluster, "level {l} cluster");
                } else {
                    assert!(lv.pool_to_next.is_none() && sl.pool_to_next.is_none());
                }
            }
        }
    }
}
