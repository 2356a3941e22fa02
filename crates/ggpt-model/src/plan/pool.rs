//! Serialized pooling, stride 2 (network.md §8), and the unpooling map of the decoder (§9.1).

use super::serialize::NUM_ORDERS;

/// Pooling from level `l` (fine, `N_l` tokens) to level `l + 1` (coarse, `num_coarse` tokens).
///
/// Coarse token `m` is cluster `m`: the clusters (2x2x2 parent cells) are sorted ascending by
/// parent Z-code per chunk, chunks in order (network.md §8 step 3). A cluster has 1..8 members at
/// pooled levels, but can have MORE than 8 at level 0, where voxels hold duplicate tokens.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct PoolMap {
    /// `[N_l]`: fine token -> coarse token (fixture `enc{l+1}.down.cluster`); also the unpooling
    /// gather index of the decoder (`u = proj_skip + proj[cluster]`, network.md §9.1).
    pub cluster: Vec<usize>,
    /// Row-major `[num_coarse, children_width]`: the members (fine tokens) of each cluster in
    /// ascending token order, padded by repeating the cluster's first member (max-pool safe).
    pub children: Vec<usize>,
    /// Width of `children` = the largest cluster size (8 or less at pooled levels).
    pub children_width: usize,
    /// CSR offsets `[num_coarse + 1]` into `members`.
    pub member_start: Vec<usize>,
    /// Members of every cluster, ascending token order, concatenated (`[N_l]`).
    pub members: Vec<usize>,
    /// Number of coarse tokens `N_{l+1}`.
    pub num_coarse: usize,
}

impl PoolMap {
    /// Members (fine tokens) of coarse token `m`, ascending.
    pub fn members_of(&self, m: usize) -> &[usize] {
        match (self.member_start.get(m), self.member_start.get(m + 1)) {
            (Some(&a), Some(&b)) => self.members.get(a..b).unwrap_or(&[]),
            _ => &[],
        }
    }
}

/// Everything of the coarse level that follows from pooling.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Pooled {
    /// The fine -> coarse map.
    pub map: PoolMap,
    /// Coarse voxel coordinates `g >> s` (any member; all agree).
    pub grid: Vec<[i32; 3]>,
    /// Coarse codes per row: the members' codes `>> 3 s` (network.md §8 step 6).
    pub codes: [Vec<u64>; NUM_ORDERS],
    /// Coarse per-chunk exclusive ends.
    pub offsets: Vec<usize>,
    /// Coarse per-chunk depth `depth - s`.
    pub depths: Vec<u32>,
}

/// Pools one level (network.md §8). Inputs: the level's voxel `grid`, its four code rows, the
/// Z-order row's sorted order `order_z` (per-chunk stable argsort of `codes[0]`), the per-chunk
/// exclusive ends and depths. Per chunk the pooling shift is `s = 1`, or 0 if the depth is 0
/// (the official `pooling_depth > depth -> 0` rule).
pub fn pool_level(
    grid: &[[i32; 3]],
    codes: &[Vec<u64>; NUM_ORDERS],
    order_z: &[usize],
    offsets: &[usize],
    depths: &[u32],
) -> Pooled {
    let n = grid.len();
    let mut cluster = vec![0usize; n];
    let mut heads: Vec<usize> = Vec::new();
    let mut counts: Vec<usize> = Vec::new();
    let mut new_offsets = Vec::with_capacity(offsets.len());
    let mut new_depths = Vec::with_capacity(offsets.len());
    let mut shifts = Vec::with_capacity(offsets.len());
    let mut start = 0usize;
    for (b, &end) in offsets.iter().enumerate() {
        let depth = depths.get(b).copied().unwrap_or(0);
        let s = u32::from(depth >= 1);
        let mut prev: Option<u64> = None;
        for &q in order_z.get(start..end).unwrap_or(&[]) {
            let parent = codes[0].get(q).copied().unwrap_or(0) >> (3 * s);
            if prev != Some(parent) {
                heads.push(q);
                counts.push(0);
                prev = Some(parent);
            }
            if let (Some(c), Some(slot)) = (counts.last_mut(), cluster.get_mut(q)) {
                *c += 1;
                *slot = heads.len() - 1;
            }
        }
        new_offsets.push(heads.len());
        new_depths.push(depth - s);
        shifts.push(s);
        start = end;
    }
    let m_total = heads.len();
    let mut member_start = Vec::with_capacity(m_total + 1);
    member_start.push(0);
    let mut acc = 0;
    for c in &counts {
        acc += c;
        member_start.push(acc);
    }
    let mut fill = member_start.clone();
    let mut members = vec![0usize; acc];
    for (q, &m) in cluster.iter().enumerate() {
        if let Some(slot) = fill.get_mut(m) {
            if let Some(dst) = members.get_mut(*slot) {
                *dst = q;
            }
            *slot += 1;
        }
    }
    let width = counts.iter().copied().max().unwrap_or(1).max(1);
    let mut children = Vec::with_capacity(m_total * width);
    for m in 0..m_total {
        let mem = members
            .get(member_start[m]..member_start[m + 1])
            .unwrap_or(&[]);
        let first = mem.first().copied().unwrap_or(0);
        children.extend_from_slice(mem);
        children.extend(std::iter::repeat_n(first, width - mem.len()));
    }
    // Per-coarse-token shift (chunk of its head).
    let mut shift_of = vec![0u32; m_total];
    let mut cstart = 0;
    for (&cend, &s) in new_offsets.iter().zip(&shifts) {
        if let Some(r) = shift_of.get_mut(cstart..cend) {
            r.fill(s);
        }
        cstart = cend;
    }
    let grid_c: Vec<[i32; 3]> = heads
        .iter()
        .zip(&shift_of)
        .map(|(&q, &s)| {
            grid.get(q)
                .map_or([0; 3], |g| [g[0] >> s, g[1] >> s, g[2] >> s])
        })
        .collect();
    let codes_c = std::array::from_fn(|r| {
        heads
            .iter()
            .zip(&shift_of)
            .map(|(&q, &s)| codes[r].get(q).copied().unwrap_or(0) >> (3 * s))
            .collect()
    });
    Pooled {
        map: PoolMap {
            cluster,
            children,
            children_width: width,
            member_start,
            members,
            num_coarse: m_total,
        },
        grid: grid_c,
        codes: codes_c,
        offsets: new_offsets,
        depths: new_depths,
    }
}

#[cfg(test)]
mod tests {
    use super::super::serialize::{compute_codes, orders_and_inverses, serialization_depth};
    use super::*;

    #[test]
    fn pooling_small_example() {
        // Chunk 0: tokens 0, 2 share parent (0,0,0); token 1 in parent (1,0,0) duplicate voxel with 3.
        // Chunk 1: tokens 4..6.
        let grid = [
            [0, 0, 0],
            [2, 0, 0],
            [1, 1, 1],
            [2, 0, 0],
            [7, 7, 7],
            [6, 6, 6],
            [0, 0, 1],
        ];
        let offsets = [4, 7];
        let depths = vec![
            serialization_depth(&grid[..4]),
            serialization_depth(&grid[4..]),
        ];
        assert_eq!(depths, [2, 3]);
        let codes = compute_codes(&grid, &offsets, &depths);
        let (orders, _) = orders_and_inverses(&codes, &offsets);
        let p = pool_level(&grid, &codes, &orders[0], &offsets, &depths);
        assert_eq!(p.map.cluster, [0, 1, 0, 1, 3, 3, 2]);
        assert_eq!(p.map.num_coarse, 4);
        assert_eq!(p.offsets, [2, 4]);
        assert_eq!(p.depths, [1, 2]);
        assert_eq!(p.grid, [[0, 0, 0], [1, 0, 0], [0, 0, 0], [3, 3, 3]]);
        assert_eq!(p.map.children_width, 2);
        assert_eq!(p.map.children, [0, 2, 1, 3, 6, 6, 4, 5]);
        assert_eq!(p.map.members_of(3), [4, 5]);
        for r in 0..NUM_ORDERS {
            let recomputed = compute_codes(&p.grid, &p.offsets, &p.depths);
            assert_eq!(p.codes[r], recomputed[r], "row {r}");
        }
    }

    #[test]
    fn more_than_eight_members_at_level_zero() {
        let grid: Vec<[i32; 3]> = (0..12).map(|i| [i % 2, (i / 2) % 2, 0]).collect();
        let offsets = [12];
        let depths = [1];
        let codes = compute_codes(&grid, &offsets, &depths);
        let (orders, _) = orders_and_inverses(&codes, &offsets);
        let p = pool_level(&grid, &codes, &orders[0], &offsets, &depths);
        assert_eq!(p.map.num_coarse, 1);
        assert_eq!(p.map.children_width, 12);
        assert_eq!(p.map.children, (0..12).collect::<Vec<_>>());
        assert_eq!(p.depths, [0]);
        // Depth 0: the shift is 0 and the single voxel stays.
        let p2 = pool_level(&p.grid, &p.codes, &[0], &p.offsets, &p.depths);
        assert_eq!(p2.map.cluster, [0]);
        assert_eq!(p2.depths, [0]);
        assert_eq!(p2.grid, [[0, 0, 0]]);
    }
}
