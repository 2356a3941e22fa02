//! Serialization (network.md §4): depth, Z-order and Hilbert curve codes, per-chunk stable
//! argsort and its inverse.

use rayon::prelude::*;

/// Number of serialization orders (rows of `code` / `order`), network.md §4.5.
pub const NUM_ORDERS: usize = 4;
/// Largest supported serialization depth (bits per axis): 3 x 16 = 48 code bits.
pub const MAX_DEPTH: u32 = 16;

/// The four serialization orders, in row order (network.md §4.5; shuffling disabled, §4.6).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SerialOrder {
    /// Z-order (Morton) of `(x, y, z)`.
    Z,
    /// Z-order of `(y, x, z)`.
    ZTrans,
    /// Hilbert of `(x, y, z)`.
    Hilbert,
    /// Hilbert of `(y, x, z)`.
    HilbertTrans,
}

/// Rows `z, z-trans, hilbert, hilbert-trans` in the order of `code[4, N]`.
pub const ORDERS: [SerialOrder; NUM_ORDERS] = [
    SerialOrder::Z,
    SerialOrder::ZTrans,
    SerialOrder::Hilbert,
    SerialOrder::HilbertTrans,
];

/// Number of significant bits of `v` (`bit_length(0) = 0`, `bit_length(383) = 9`).
pub fn bit_length(v: u32) -> u32 {
    u32::BITS - v.leading_zeros()
}

/// Serialization depth of a set of voxels (network.md §4.2, Pointcept v1.5.2):
/// `bit_length(max over tokens and axes of g)`; negative coordinates count as 0.
pub fn serialization_depth(grid: &[[i32; 3]]) -> u32 {
    let max = grid
        .iter()
        .flat_map(|g| g.iter())
        .copied()
        .max()
        .unwrap_or(0)
        .max(0);
    bit_length(max as u32)
}

/// Spreads the low 21 bits of `v` so that bit `i` lands at bit `3 i`.
fn spread3(v: u32) -> u64 {
    let mut x = (v as u64) & 0x1f_ffff;
    x = (x | (x << 32)) & 0x001f_0000_0000_ffff;
    x = (x | (x << 16)) & 0x001f_0000_ff00_00ff;
    x = (x | (x << 8)) & 0x100f_00f0_0f00_f00f;
    x = (x | (x << 4)) & 0x10c3_0c30_c30c_30c3;
    x = (x | (x << 2)) & 0x1249_2492_4924_9249;
    x
}

/// Mask of the low `depth` bits.
fn low_mask(depth: u32) -> u32 {
    if depth >= 32 {
        u32::MAX
    } else {
        (1u32 << depth) - 1
    }
}

/// Z-order (Morton) code (network.md §4.3): bit `i` of `x` -> code bit `3i+2`, `y` -> `3i+1`,
/// `z` -> `3i`, for `i < depth` (higher bits are masked off). Coordinates are voxel indices.
pub fn z_order_code(g: [u32; 3], depth: u32) -> u64 {
    let m = low_mask(depth.min(MAX_DEPTH));
    (spread3(g[0] & m) << 2) | (spread3(g[1] & m) << 1) | spread3(g[2] & m)
}

/// Hilbert code (network.md §4.4): Skilling's transpose form on `depth` bits per axis followed by
/// Gray decoding of the interleaved bits. Depends on `depth`. Coordinates are voxel indices.
pub fn hilbert_code(g: [u32; 3], depth: u32) -> u64 {
    let nb = depth.min(MAX_DEPTH);
    if nb == 0 {
        return 0;
    }
    let m = low_mask(nb);
    let mut x = [g[0] & m, g[1] & m, g[2] & m];
    // b = 0 is the MSB, i.e. bit position q = nb - 1 - b; "lower bits" = bits below q.
    for b in 0..nb {
        let q = nb - 1 - b;
        let lower = (1u32 << q) - 1;
        for d in 0..3 {
            if (x[d] >> q) & 1 == 1 {
                x[0] ^= lower;
            } else {
                let t = (x[0] ^ x[d]) & lower;
                x[0] ^= t;
                x[d] ^= t;
            }
        }
    }
    // Interleave MSB first: x, y, z -> the same layout as the Z-order code.
    let gray = (spread3(x[0]) << 2) | (spread3(x[1]) << 1) | spread3(x[2]);
    // Gray -> binary: prefix xor from the MSB.
    let mut bin = gray;
    let mut s = 1;
    while s < 64 {
        bin ^= bin >> s;
        s <<= 1;
    }
    bin
}

/// Curve code of one voxel for one order row at `depth` (no batch bits).
/// Negative coordinates (never produced by the grid) are treated as 0.
pub fn curve_code(order: SerialOrder, g: [i32; 3], depth: u32) -> u64 {
    let u = |v: i32| v.max(0) as u32;
    let (x, y, z) = (u(g[0]), u(g[1]), u(g[2]));
    match order {
        SerialOrder::Z => z_order_code([x, y, z], depth),
        SerialOrder::ZTrans => z_order_code([y, x, z], depth),
        SerialOrder::Hilbert => hilbert_code([x, y, z], depth),
        SerialOrder::HilbertTrans => hilbert_code([y, x, z], depth),
    }
}

/// Full official key `(batch << (3 depth)) | curve_code` (network.md §4.5), for comparison with
/// batched official tables. The plan itself sorts each chunk separately and stores curve codes.
pub fn batched_key(batch: u64, curve: u64, depth: u32) -> u64 {
    (batch << (3 * depth)) | curve
}

/// Curve codes of all tokens for the four rows, chunk `b` (tokens `offsets[b-1]..offsets[b]`)
/// encoded at `depths[b]`. `offsets` are exclusive ends (no leading zero).
pub fn compute_codes(
    grid: &[[i32; 3]],
    offsets: &[usize],
    depths: &[u32],
) -> [Vec<u64>; NUM_ORDERS] {
    let mut chunk_depth = vec![0u32; grid.len()];
    let mut start = 0;
    for (&end, &d) in offsets.iter().zip(depths) {
        if let Some(s) = chunk_depth.get_mut(start..end) {
            s.fill(d);
        }
        start = end;
    }
    ORDERS.map(|o| {
        grid.par_iter()
            .zip(chunk_depth.par_iter())
            .map(|(&g, &d)| curve_code(o, g, d))
            .collect()
    })
}

/// Stable argsort of `codes` within each chunk (ties by ascending token index, network.md §4.5):
/// returns global token indices; positions `offsets[b-1]..offsets[b]` hold chunk `b`'s tokens.
pub fn chunked_stable_argsort(codes: &[u64], offsets: &[usize]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..codes.len()).collect();
    let mut rest: &mut [usize] = &mut order;
    let mut start = 0;
    for &end in offsets {
        let len = end.saturating_sub(start).min(rest.len());
        let (head, tail) = std::mem::take(&mut rest).split_at_mut(len);
        head.sort_unstable_by_key(|&i| (codes.get(i).copied().unwrap_or(u64::MAX), i));
        rest = tail;
        start = end;
    }
    order
}

/// Inverse permutation: `inverse[order[j]] = j` (token index -> sorted position).
pub fn invert(order: &[usize]) -> Vec<usize> {
    let mut inv = vec![0usize; order.len()];
    for (j, &t) in order.iter().enumerate() {
        if let Some(slot) = inv.get_mut(t) {
            *slot = j;
        }
    }
    inv
}

/// Orders and inverses of the four rows (per chunk stable argsort).
pub fn orders_and_inverses(
    codes: &[Vec<u64>; NUM_ORDERS],
    offsets: &[usize],
) -> ([Vec<usize>; NUM_ORDERS], [Vec<usize>; NUM_ORDERS]) {
    let mut out: Vec<(Vec<usize>, Vec<usize>)> = codes
        .par_iter()
        .map(|c| {
            let o = chunked_stable_argsort(c, offsets);
            let i = invert(&o);
            (o, i)
        })
        .collect();
    let mut orders: [Vec<usize>; NUM_ORDERS] = Default::default();
    let mut inverses: [Vec<usize>; NUM_ORDERS] = Default::default();
    for (r, (o, i)) in out.drain(..).enumerate() {
        orders[r] = o;
        inverses[r] = i;
    }
    (orders, inverses)
}

#[cfg(test)]
mod tests {
    use super::*;

    const VOXELS: [[i32; 3]; 10] = [
        [0, 0, 0],
        [1, 0, 0],
        [0, 1, 0],
        [0, 0, 1],
        [1, 1, 1],
        [2, 3, 1],
        [5, 2, 7],
        [7, 7, 7],
        [3, 6, 2],
        [6, 1, 4],
    ];

    fn codes(order: SerialOrder, depth: u32) -> Vec<u64> {
        VOXELS
            .iter()
            .map(|&g| curve_code(order, g, depth))
            .collect()
    }

    #[test]
    fn bit_length_values() {
        assert_eq!(bit_length(0), 0);
        assert_eq!(bit_length(383), 9);
        assert_eq!(bit_length(255), 8);
        assert_eq!(bit_length(256), 9);
        assert_eq!(serialization_depth(&[[3, 383, 0], [1, 2, 3]]), 9);
        assert_eq!(serialization_depth(&[]), 0);
    }

    #[test]
    fn spec_test_vectors_depth3_and_4() {
        let z = [0, 4, 2, 1, 7, 51, 349, 511, 188, 354];
        let zt = [0, 2, 4, 1, 7, 53, 235, 511, 314, 212];
        let h3 = [0, 1, 7, 3, 5, 22, 406, 365, 223, 445];
        let ht3 = [0, 7, 1, 3, 5, 20, 178, 365, 461, 159];
        let h4 = [0, 7, 3, 1, 5, 48, 306, 365, 111, 287];
        let ht4 = [0, 3, 7, 1, 5, 50, 388, 365, 217, 427];
        assert_eq!(codes(SerialOrder::Z, 3), z);
        assert_eq!(codes(SerialOrder::ZTrans, 3), zt);
        assert_eq!(codes(SerialOrder::Hilbert, 3), h3);
        assert_eq!(codes(SerialOrder::HilbertTrans, 3), ht3);
        assert_eq!(codes(SerialOrder::Z, 4), z);
        assert_eq!(codes(SerialOrder::ZTrans, 4), zt);
        assert_eq!(codes(SerialOrder::Hilbert, 4), h4);
        assert_eq!(codes(SerialOrder::HilbertTrans, 4), ht4);
        // Depth 9 equals depth 3 for all four rows (as in the spec table).
        assert_eq!(codes(SerialOrder::Z, 9), z);
        assert_eq!(codes(SerialOrder::ZTrans, 9), zt);
        assert_eq!(codes(SerialOrder::Hilbert, 9), h3);
        assert_eq!(codes(SerialOrder::HilbertTrans, 9), ht3);
    }

    #[test]
    fn batched_keys_order_and_inverse() {
        let batch = [0u64, 0, 0, 0, 0, 0, 1, 1, 1, 1];
        let zk: Vec<u64> = codes(SerialOrder::Z, 3)
            .iter()
            .zip(batch)
            .map(|(&c, b)| batched_key(b, c, 3))
            .collect();
        assert_eq!(zk, [0, 4, 2, 1, 7, 51, 861, 1023, 700, 866]);
        let hk: Vec<u64> = codes(SerialOrder::Hilbert, 3)
            .iter()
            .zip(batch)
            .map(|(&c, b)| batched_key(b, c, 3))
            .collect();
        assert_eq!(hk, [0, 1, 7, 3, 5, 22, 918, 877, 735, 957]);
        // Sorting per chunk (curve codes only) equals sorting the batched keys.
        let h = codes(SerialOrder::Hilbert, 3);
        let order = chunked_stable_argsort(&h, &[6, 10]);
        assert_eq!(order, [0, 1, 3, 4, 2, 5, 8, 7, 6, 9]);
        assert_eq!(invert(&order), [0, 1, 4, 2, 3, 5, 8, 7, 6, 9]);
    }

    #[test]
    fn fixture_chunk1_vectors() {
        let cases: [([i32; 3], u32, [u64; 4]); 5] = [
            ([112, 179, 190], 9, [7598682, 11268716, 13410293, 10262355]),
            ([115, 176, 190], 9, [7598700, 11268698, 13410275, 10262391]),
            ([169, 228, 192], 9, [15665284, 16188674, 12142291, 11669217]),
            ([4, 6, 14], 5, [984, 1000, 3650, 3668]),
            ([23, 23, 20], 5, [29174, 29174, 20818, 20818]),
        ];
        for (g, d, expect) in cases {
            let got = ORDERS.map(|o| curve_code(o, g, d));
            assert_eq!(got, expect, "voxel {g:?} depth {d}");
        }
        assert_eq!(
            curve_code(SerialOrder::Hilbert, [100, 37, 250], 8),
            2_790_203
        );
        assert_eq!(
            curve_code(SerialOrder::Hilbert, [100, 37, 250], 9),
            16_449_211
        );
        assert_eq!(curve_code(SerialOrder::Z, [383, 0, 383], 9), 85_384_045);
        assert_eq!(
            curve_code(SerialOrder::Hilbert, [383, 0, 383], 9),
            110_849_462
        );
        for d in [8, 9] {
            assert_eq!(curve_code(SerialOrder::Z, [192, 192, 192], d), 16_515_072);
            assert_eq!(
                curve_code(SerialOrder::Hilbert, [192, 192, 192], d),
                11_796_480
            );
        }
    }

    #[test]
    fn pooling_shift_property() {
        // hilbert(g >> 1, depth - 1) == hilbert(g, depth) >> 3, and the same for Z-order.
        let mut s = 12345u64;
        for _ in 0..2000 {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let g = [
                (s >> 20) as i32 & 511,
                (s >> 30) as i32 & 511,
                (s >> 40) as i32 & 511,
            ];
            let half = [g[0] >> 1, g[1] >> 1, g[2] >> 1];
            for o in ORDERS {
                assert_eq!(
                    curve_code(o, half, 8),
                    curve_code(o, g, 9) >> 3,
                    "{o:?} {g:?}"
                );
            }
        }
    }

    #[test]
    fn stable_ties_by_token_index() {
        let codes = [5u64, 3, 5, 3, 1, 5];
        assert_eq!(chunked_stable_argsort(&codes, &[6]), [4, 1, 3, 0, 2, 5]);
        // Two chunks never mix.
        assert_eq!(chunked_stable_argsort(&codes, &[3, 6]), [1, 0, 2, 4, 3, 5]);
    }
}
