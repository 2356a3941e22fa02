//! Submanifold k=3 sparse-convolution neighbour tables (network.md §6) with the spconv CPU
//! duplicate-voxel rule (§6.3): rep(v) = lowest token index of voxel v; centre tap = the token
//! itself; taps f > 13 read rep(neighbour voxel); taps f < 13 add, to rep(v) only, the sum over all
//! tokens of the neighbour voxel. Neighbours are looked up within the same chunk only.

use rayon::prelude::*;

/// Number of taps of a 3x3x3 kernel.
pub const NUM_TAPS: usize = 27;
/// Index of the centre tap `(1, 1, 1)`.
pub const CENTER_TAP: usize = 13;

/// `(target, source)` pairs of one tap: `out[target[i]] += W_f · in[source[i]]`.
///
/// Pairs are sorted by ascending target (then ascending source). Targets are unique for the
/// centre tap and the taps `f > 13`; for taps `f < 13` a representative may receive several pairs
/// (one per token of a duplicated neighbour voxel), so use a scatter-add.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct TapPairs {
    /// Output token (row) of each pair.
    pub target: Vec<usize>,
    /// Input token (row) of each pair.
    pub source: Vec<usize>,
}

impl TapPairs {
    /// Number of pairs.
    pub fn len(&self) -> usize {
        self.target.len()
    }
    /// True when the tap has no pair (skip it).
    pub fn is_empty(&self) -> bool {
        self.target.is_empty()
    }
}

/// Neighbour tables of one level: 27 taps, index `f = 9 r0 + 3 r1 + r2`, offset
/// `(r0 - 1, r1 - 1, r2 - 1)` on the `(x, y, z)` voxel axes (input site = output site + offset).
/// The centre tap holds the identity pairs `(q, q)` for every token.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ConvTable {
    /// One entry per tap (27).
    pub taps: Vec<TapPairs>,
    /// True when some voxel holds more than one token (then taps `f < 13` may repeat targets).
    pub has_duplicates: bool,
}

/// Voxel offset `(dx, dy, dz)` of tap `f` (network.md §6.1).
pub fn tap_offset(f: usize) -> [i32; 3] {
    [
        (f / 9) as i32 - 1,
        ((f / 3) % 3) as i32 - 1,
        (f % 3) as i32 - 1,
    ]
}

/// Packs `(chunk, x, y, z)` into `chunk << 48 | x << 32 | y << 16 | z`; `None` outside `[0, 2^16)`.
/// Keys sort like `(chunk, x, y, z)` lexicographically.
fn voxel_key(chunk: usize, g: [i32; 3]) -> Option<u64> {
    let ok = |v: i32| (0..1 << 16).contains(&v);
    if !(ok(g[0]) && ok(g[1]) && ok(g[2]) && chunk < 1 << 16) {
        return None;
    }
    Some(((chunk as u64) << 48) | ((g[0] as u64) << 32) | ((g[1] as u64) << 16) | g[2] as u64)
}

/// Marker for "no voxel".
const NONE: u32 = u32::MAX;

/// Voxel set of a level: tokens grouped per `(chunk, voxel)`, voxels sorted by packed key.
struct Voxels {
    /// Voxel id of each token (`NONE` for a token outside the key range, never produced).
    voxel_of: Vec<u32>,
    /// Packed key of each voxel, strictly ascending.
    keys: Vec<u64>,
    /// CSR offsets (`len = voxels + 1`) into `members`.
    member_start: Vec<usize>,
    /// Token indices per voxel, ascending (the first one is the representative).
    members: Vec<usize>,
}

impl Voxels {
    fn build(grid: &[[i32; 3]], offsets: &[usize]) -> Voxels {
        let n = grid.len();
        let mut keyed: Vec<(u64, usize)> = Vec::with_capacity(n);
        let mut start = 0usize;
        for (b, &end) in offsets.iter().enumerate() {
            for (q, g) in grid.iter().enumerate().take(end.min(n)).skip(start) {
                if let Some(key) = voxel_key(b, *g) {
                    keyed.push((key, q));
                }
            }
            start = end;
        }
        // Sorting by (key, token) groups each voxel's tokens in ascending token order.
        keyed.par_sort_unstable();
        let mut voxel_of = vec![NONE; n];
        let mut keys: Vec<u64> = Vec::new();
        let mut member_start = Vec::new();
        let mut members = Vec::with_capacity(keyed.len());
        for &(key, q) in &keyed {
            if keys.last() != Some(&key) {
                keys.push(key);
                member_start.push(members.len());
            }
            if let Some(slot) = voxel_of.get_mut(q) {
                *slot = (keys.len() - 1) as u32;
            }
            members.push(q);
        }
        member_start.push(members.len());
        Voxels {
            voxel_of,
            keys,
            member_start,
            members,
        }
    }

    fn members(&self, v: usize) -> &[usize] {
        match (self.member_start.get(v), self.member_start.get(v + 1)) {
            (Some(&a), Some(&b)) => self.members.get(a..b).unwrap_or(&[]),
            _ => &[],
        }
    }

    fn rep(&self, v: usize) -> Option<usize> {
        self.members(v).first().copied()
    }

    /// Neighbour voxel id of every voxel for offset `d` (same chunk; `NONE` if inactive), by a
    /// merge join: `key + delta(d)` is increasing along the sorted keys whenever it is valid.
    fn neighbours(&self, d: [i32; 3]) -> Vec<u32> {
        let delta = ((d[0] as i64) << 32) + ((d[1] as i64) << 16) + d[2] as i64;
        let inside = |key: u64, shift: u32, dd: i32| {
            let c = ((key >> shift) & 0xffff) as i32 + dd;
            (0..1 << 16).contains(&c)
        };
        let mut out = vec![NONE; self.keys.len()];
        let mut j = 0usize;
        for (i, &key) in self.keys.iter().enumerate() {
            if !(inside(key, 32, d[0]) && inside(key, 16, d[1]) && inside(key, 0, d[2])) {
                continue;
            }
            let target = (key as i64 + delta) as u64;
            while j < self.keys.len() && self.keys[j] < target {
                j += 1;
            }
            if self.keys.get(j) == Some(&target) {
                out[i] = j as u32;
            }
        }
        out
    }
}

/// Builds the 27 neighbour-pair tables of one level (network.md §6.3) from the voxel coordinate
/// of every token and the per-chunk exclusive end `offsets`. Tokens are level-local indices.
pub fn build_conv_table(grid: &[[i32; 3]], offsets: &[usize]) -> ConvTable {
    let vox = Voxels::build(grid, offsets);
    let has_duplicates = vox.keys.len() < vox.members.len();
    // Neighbour maps of the 13 positive taps; a negative tap is the inverse relation of its
    // mirrored positive tap (v + d = u  <=>  u - d = v).
    let positive: Vec<Vec<u32>> = (CENTER_TAP + 1..NUM_TAPS)
        .into_par_iter()
        .map(|f| vox.neighbours(tap_offset(f)))
        .collect();
    let neighbour_map = |f: usize| -> Vec<u32> {
        if f > CENTER_TAP {
            positive
                .get(f - CENTER_TAP - 1)
                .cloned()
                .unwrap_or_default()
        } else {
            let mut inv = vec![NONE; vox.keys.len()];
            if let Some(pos) = positive.get(NUM_TAPS - 1 - f - CENTER_TAP - 1) {
                for (v, &u) in pos.iter().enumerate() {
                    if let Some(slot) = inv.get_mut(u as usize) {
                        *slot = v as u32;
                    }
                }
            }
            inv
        }
    };
    let taps: Vec<TapPairs> = (0..NUM_TAPS)
        .into_par_iter()
        .map(|f| {
            if f == CENTER_TAP {
                let id: Vec<usize> = (0..grid.len()).collect();
                return TapPairs {
                    target: id.clone(),
                    source: id,
                };
            }
            let nb = neighbour_map(f);
            // Exact pair count first (avoids re-allocations on large levels).
            let count: usize = vox
                .voxel_of
                .iter()
                .enumerate()
                .map(|(q, &v)| match nb.get(v as usize) {
                    Some(&u) if u != NONE && f > CENTER_TAP => 1,
                    Some(&u) if u != NONE && vox.rep(v as usize) == Some(q) => {
                        vox.members(u as usize).len()
                    }
                    _ => 0,
                })
                .sum();
            let mut pairs = TapPairs {
                target: Vec::with_capacity(count),
                source: Vec::with_capacity(count),
            };
            for (q, &v) in vox.voxel_of.iter().enumerate() {
                let Some(&u) = nb.get(v as usize) else {
                    continue;
                };
                if u == NONE {
                    continue;
                }
                if f > CENTER_TAP {
                    // Every token reads the representative of the neighbour voxel.
                    if let Some(rep) = vox.rep(u as usize) {
                        pairs.target.push(q);
                        pairs.source.push(rep);
                    }
                } else if vox.rep(v as usize) == Some(q) {
                    // Only representatives receive, summed over all tokens of the neighbour voxel.
                    for &j in vox.members(u as usize) {
                        pairs.target.push(q);
                        pairs.source.push(j);
                    }
                }
            }
            pairs
        })
        .collect();
    ConvTable {
        taps,
        has_duplicates,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tap_offsets() {
        assert_eq!(tap_offset(0), [-1, -1, -1]);
        assert_eq!(tap_offset(CENTER_TAP), [0, 0, 0]);
        assert_eq!(tap_offset(14), [0, 0, 1]);
        assert_eq!(tap_offset(22), [1, 0, 0]);
        assert_eq!(tap_offset(25), [1, 1, 0]);
        assert_eq!(tap_offset(26), [1, 1, 1]);
        // f < 13 <=> lexicographically negative offset.
        for f in 0..NUM_TAPS {
            let d = tap_offset(f);
            assert_eq!(f < CENTER_TAP, d < [0, 0, 0], "tap {f}");
        }
    }

    /// The `handmade` case of network.md §6.4 written as pairs.
    #[test]
    fn handmade_pairs() {
        let a = [2, 2, 2];
        let b = [2, 2, 3];
        let c = [2, 1, 2];
        let d = [3, 2, 2];
        let grid = [a, b, a, c, b, d, a];
        let t = build_conv_table(&grid, &[7]);
        assert!(t.has_duplicates);
        let tap = |d: [i32; 3]| (9 * (d[0] + 1) + 3 * (d[1] + 1) + d[2] + 1) as usize;
        let pairs = |d: [i32; 3]| {
            let p = &t.taps[tap(d)];
            p.target
                .iter()
                .copied()
                .zip(p.source.iter().copied())
                .collect::<Vec<_>>()
        };
        assert_eq!(pairs([0, 0, 0]), (0..7).map(|q| (q, q)).collect::<Vec<_>>());
        assert_eq!(pairs([0, 0, 1]), [(0, 1), (2, 1), (6, 1)]);
        assert_eq!(pairs([1, 0, 0]), [(0, 5), (2, 5), (6, 5)]);
        assert_eq!(pairs([0, -1, 0]), [(0, 3)]);
        assert_eq!(pairs([1, 0, -1]), [(1, 5), (4, 5)]);
        assert_eq!(pairs([0, 0, -1]), [(1, 0), (1, 2), (1, 6)]);
        assert_eq!(pairs([0, -1, -1]), [(1, 3)]);
        assert_eq!(pairs([0, 1, 0]), [(3, 0)]);
        assert_eq!(pairs([0, 1, 1]), [(3, 1)]);
        assert_eq!(pairs([1, 1, 0]), [(3, 5)]);
        assert_eq!(pairs([-1, 0, 0]), [(5, 0), (5, 2), (5, 6)]);
        assert_eq!(pairs([-1, 0, 1]), [(5, 1), (5, 4)]);
        assert_eq!(pairs([-1, -1, 0]), [(5, 3)]);
        let total: usize = t.taps.iter().map(|p| p.len()).sum();
        assert_eq!(total, 7 + 3 + 3 + 1 + 2 + 3 + 1 + 1 + 1 + 1 + 3 + 2 + 1);
    }

    #[test]
    fn chunks_never_connect() {
        let grid = [[5, 5, 5], [5, 5, 6], [5, 5, 5]];
        let t = build_conv_table(&grid, &[1, 3]);
        // Token 0 (chunk 0) and token 1 (chunk 1) are neighbours in space but not in the table.
        for (f, p) in t.taps.iter().enumerate() {
            for (&a, &b) in p.target.iter().zip(&p.source) {
                assert_eq!(a == 0, b == 0, "tap {f} connects chunks: ({a}, {b})");
            }
        }
        // Token 2 is alone in its chunk's voxel (5,5,5): it reads token 1 through tap (0,0,1).
        assert_eq!(t.taps[14].target, [2]);
        assert_eq!(t.taps[14].source, [1]);
        assert!(!t.has_duplicates);
    }

    #[test]
    fn border_voxels_have_no_negative_neighbours() {
        let grid = [[0, 0, 0], [0, 0, 1], [65535, 65535, 65535]];
        let t = build_conv_table(&grid, &[3]);
        assert_eq!(t.taps[12].target, [1]);
        assert_eq!(t.taps[12].source, [0]);
        assert_eq!(t.taps[14].target, [0]);
        let total: usize = t.taps.iter().map(|p| p.len()).sum();
        assert_eq!(total, 3 + 2);
    }
}
