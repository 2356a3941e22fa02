//! Host-side planning of one GGPT forward (pure Rust, no Burn types): guidance encoding and token
//! list (network.md §3), batching and serialization (§4), submanifold-conv neighbour tables (§6),
//! attention windows (§7), pooling / unpooling maps (§8, §9).
//!
//! Index conventions: every table uses *level-local global* token indices, i.e. the tokens of all
//! chunks of the batch concatenated (chunk 0 first); `offsets[b]` is the exclusive end of chunk `b`
//! (no leading zero). Everything is computed per chunk, so a chunk's tables in a batch equal its
//! single-chunk tables shifted by the chunk's offset (network.md §4.1, per-chunk depth).

pub mod conv;
pub mod encode;
pub mod pool;
pub mod serialize;
pub mod windows;

pub use conv::{CENTER_TAP, ConvTable, NUM_TAPS, TapPairs, build_conv_table, tap_offset};
pub use encode::{
    AsChunkView, ChunkInput, ChunkView, FEAT_DIM, FEAT_NO_EMBED_DIM, PE_DIM, TYPE_EMBED_DIM,
    TokenFeatures, encode_chunk, grid_coord, positional_encoding,
};
pub use pool::{PoolMap, Pooled, pool_level};
pub use serialize::{NUM_ORDERS, ORDERS, SerialOrder, curve_code, hilbert_code, z_order_code};
pub use windows::{OfficialAttnTables, Window, flash_windows, official_attn_tables};

use rayon::prelude::*;

/// Errors of planning (invalid chunk records or configuration).
#[derive(Debug, thiserror::Error)]
pub enum PlanError {
    /// A per-pixel array of a chunk does not have `K = ff_pts.len()` entries.
    #[error("chunk input length mismatch: `{field}` has {got} entries, `ff_pts` has {expected}")]
    LengthMismatch {
        /// Offending field name.
        field: &'static str,
        /// `ff_pts.len()`.
        expected: usize,
        /// The field's length.
        got: usize,
    },
    /// The chunk has no pixel.
    #[error("chunk input is empty (no pixels)")]
    EmptyChunk,
    /// A NaN or infinite value where the network reads it.
    #[error("non-finite value in `{field}` at pixel {index}")]
    NonFinite {
        /// Offending field name.
        field: &'static str,
        /// Pixel index within the chunk.
        index: usize,
    },
    /// `plan_batch` was called without chunks.
    #[error("no chunks to plan")]
    NoChunks,
    /// More chunks than the voxel key can address (2^16).
    #[error("too many chunks in one batch: {0} (at most 65536)")]
    TooManyChunks(usize),
    /// Invalid [`PlanConfig`].
    #[error("invalid plan config: {0}")]
    InvalidConfig(String),
    /// An error of one chunk of a batch.
    #[error("chunk {chunk}: {source}")]
    Chunk {
        /// Index of the chunk in the batch.
        chunk: usize,
        /// The chunk's error.
        #[source]
        source: Box<PlanError>,
    },
}

/// Planning configuration (network.md §1, §3.4, §7).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PlanConfig {
    /// Voxel grid resolution per axis (384).
    pub grid_resolution: u32,
    /// Attention patch size `P` per level `0..num_levels` (1024 released, 128 small).
    pub patch_size: Vec<usize>,
    /// Number of levels = encoder stages (5): `num_levels - 1` poolings.
    pub num_levels: usize,
}

impl PlanConfig {
    /// The released configuration: grid 384, 5 levels, patch 1024 everywhere (network.md §1.1).
    pub fn released() -> Self {
        Self {
            grid_resolution: encode::DEFAULT_GRID_RESOLUTION,
            patch_size: vec![1024; 5],
            num_levels: 5,
        }
    }
    /// The small fixture configuration: grid 384, 5 levels, patch 128 (network.md §1.2).
    pub fn small() -> Self {
        Self {
            grid_resolution: encode::DEFAULT_GRID_RESOLUTION,
            patch_size: vec![128; 5],
            num_levels: 5,
        }
    }
    /// Checks the configuration.
    pub fn validate(&self) -> Result<(), PlanError> {
        if self.num_levels == 0 {
            return Err(PlanError::InvalidConfig(
                "num_levels must be at least 1".into(),
            ));
        }
        if self.patch_size.len() != self.num_levels {
            return Err(PlanError::InvalidConfig(format!(
                "patch_size has {} entries, expected one per level ({})",
                self.patch_size.len(),
                self.num_levels
            )));
        }
        if self.patch_size.contains(&0) {
            return Err(PlanError::InvalidConfig(
                "patch sizes must be at least 1".into(),
            ));
        }
        if self.grid_resolution == 0 || self.grid_resolution > encode::MAX_GRID_RESOLUTION {
            return Err(PlanError::InvalidConfig(format!(
                "grid_resolution {} outside 1..={}",
                self.grid_resolution,
                encode::MAX_GRID_RESOLUTION
            )));
        }
        Ok(())
    }
}

/// Where chunk `b`'s tokens live in the concatenated level-0 token list of a [`BatchPlan`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ChunkLayout {
    /// First token of the chunk (its dense token of pixel 0).
    pub token_start: usize,
    /// Number of dense tokens = pixels `K` (tokens `token_start..token_start + K`).
    pub num_dense: usize,
    /// Number of DLT tokens (they follow the dense tokens).
    pub num_dlt: usize,
    /// Start of the chunk's entries in the concatenated `tokens.dlt_pixel`.
    pub dlt_start: usize,
}

/// Serialization, windows, neighbour tables and pooling of one level of a batch.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LevelPlan {
    /// Number of tokens `N_l` of the level (all chunks).
    pub num_tokens: usize,
    /// Per-chunk exclusive end of the level's tokens.
    pub offsets: Vec<usize>,
    /// `[N_l]` voxel coordinates `(x, y, z)` (level 0: §3.4; level l: `g_{l-1} >> 1`).
    pub grid: Vec<[i32; 3]>,
    /// Per-chunk serialization depth of this level (level-0 depth minus poolings).
    pub depth: Vec<u32>,
    /// Curve codes per row `z, z-trans, hilbert, hilbert-trans` (no batch bits; equal to the
    /// official keys for a single chunk).
    pub codes: [Vec<u64>; NUM_ORDERS],
    /// Per row: sorted position -> token index (stable per chunk; ties by token index).
    pub order: [Vec<usize>; NUM_ORDERS],
    /// Per row: token index -> sorted position.
    pub inverse: [Vec<usize>; NUM_ORDERS],
    /// Flash window partition in sorted-position space (shared by the four rows), §7.2.
    pub windows: Vec<Window>,
    /// Patch size used for `windows`.
    pub patch_size: usize,
    /// Submanifold k=3 neighbour pairs with the duplicate rule (§6).
    pub conv: ConvTable,
    /// Pooling to level `l + 1` (None at the last level).
    pub pool_to_next: Option<PoolMap>,
}

impl LevelPlan {
    /// Per-chunk token counts of the level.
    pub fn counts(&self) -> Vec<usize> {
        counts_from_offsets(&self.offsets)
    }
    /// Token range of chunk `b` at this level (empty if `b` is out of range).
    pub fn chunk_range(&self, b: usize) -> std::ops::Range<usize> {
        let start = if b == 0 {
            0
        } else {
            self.offsets.get(b - 1).copied().unwrap_or(0)
        };
        start..self.offsets.get(b).copied().unwrap_or(start)
    }
    /// The official padding tables of this level (network.md §7.3).
    pub fn official_attn_tables(&self) -> OfficialAttnTables {
        official_attn_tables(&self.counts(), self.patch_size)
    }
}

/// Per-chunk counts from exclusive ends.
pub fn counts_from_offsets(offsets: &[usize]) -> Vec<usize> {
    let mut prev = 0;
    offsets
        .iter()
        .map(|&e| {
            let n = e.saturating_sub(prev);
            prev = e;
            n
        })
        .collect()
}

/// The plan of one forward over `B` chunks.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BatchPlan {
    /// Per-chunk exclusive end of the level-0 tokens.
    pub offsets: Vec<usize>,
    /// Per-chunk location of the tokens in `tokens`.
    pub layout: Vec<ChunkLayout>,
    /// One plan per level `0..num_levels`.
    pub levels: Vec<LevelPlan>,
    /// Level-0 token features of all chunks concatenated (`num_dense` = total dense tokens,
    /// `dlt_pixel` = the chunks' chunk-local pixel lists concatenated, see `layout`).
    pub tokens: TokenFeatures,
}

/// Plans level `l` given its voxels, codes, offsets and depths.
fn plan_level(
    grid: Vec<[i32; 3]>,
    codes: [Vec<u64>; NUM_ORDERS],
    offsets: Vec<usize>,
    depth: Vec<u32>,
    patch_size: usize,
) -> LevelPlan {
    let (order, inverse) = serialize::orders_and_inverses(&codes, &offsets);
    let windows = flash_windows(&offsets, patch_size);
    let conv = build_conv_table(&grid, &offsets);
    LevelPlan {
        num_tokens: grid.len(),
        offsets,
        grid,
        depth,
        codes,
        order,
        inverse,
        windows,
        patch_size,
        conv,
        pool_to_next: None,
    }
}

/// Plans one forward over `chunks` (network.md §3-§8): encodes every chunk, concatenates the
/// token lists, and builds every level's serialization, windows, neighbour tables and pooling.
/// Points are in normalised chunk coordinates (see [`ChunkInput`]). The chunks are borrowed
/// ([`AsChunkView`]: `&[ChunkInput]`, `&[&ChunkInput]`, chunk records, training chunks), never
/// copied.
pub fn plan_batch<C: AsChunkView>(chunks: &[C], cfg: &PlanConfig) -> Result<BatchPlan, PlanError> {
    cfg.validate()?;
    if chunks.is_empty() {
        return Err(PlanError::NoChunks);
    }
    if chunks.len() > 1 << 16 {
        return Err(PlanError::TooManyChunks(chunks.len()));
    }
    let encoded: Vec<TokenFeatures> = chunks
        .iter()
        .enumerate()
        .map(|(b, c)| {
            encode_chunk(c).map_err(|e| PlanError::Chunk {
                chunk: b,
                source: Box::new(e),
            })
        })
        .collect::<Result<_, _>>()?;
    let mut offsets = Vec::with_capacity(encoded.len());
    let mut layout = Vec::with_capacity(encoded.len());
    let (mut tok, mut dlt) = (0usize, 0usize);
    for t in &encoded {
        layout.push(ChunkLayout {
            token_start: tok,
            num_dense: t.num_dense,
            num_dlt: t.num_dlt(),
            dlt_start: dlt,
        });
        tok += t.num_tokens;
        dlt += t.num_dlt();
        offsets.push(tok);
    }
    let tokens = concat_tokens(encoded);
    let res = cfg.grid_resolution;
    let grid: Vec<[i32; 3]> = tokens
        .coord
        .par_iter()
        .map(|&c| grid_coord(c, res))
        .collect();
    let mut depth = Vec::with_capacity(offsets.len());
    let mut start = 0;
    for &end in &offsets {
        depth.push(serialize::serialization_depth(
            grid.get(start..end).unwrap_or(&[]),
        ));
        start = end;
    }
    let codes = serialize::compute_codes(&grid, &offsets, &depth);
    let mut levels: Vec<LevelPlan> = Vec::with_capacity(cfg.num_levels);
    let mut current = plan_level(grid, codes, offsets.clone(), depth, cfg.patch_size[0]);
    for l in 1..cfg.num_levels {
        let pooled = pool_level(
            &current.grid,
            &current.codes,
            &current.order[0],
            &current.offsets,
            &current.depth,
        );
        let next = plan_level(
            pooled.grid,
            pooled.codes,
            pooled.offsets,
            pooled.depths,
            cfg.patch_size[l],
        );
        current.pool_to_next = Some(pooled.map);
        levels.push(std::mem::replace(&mut current, next));
    }
    levels.push(current);
    Ok(BatchPlan {
        offsets,
        layout,
        levels,
        tokens,
    })
}

/// Concatenates per-chunk token features (chunk 0 first).
fn concat_tokens(mut parts: Vec<TokenFeatures>) -> TokenFeatures {
    if parts.len() == 1
        && let Some(t) = parts.pop()
    {
        return t;
    }
    let n: usize = parts.iter().map(|t| t.num_tokens).sum();
    let mut out = TokenFeatures {
        num_tokens: n,
        feat_no_embed: Vec::with_capacity(n * FEAT_NO_EMBED_DIM),
        is_dlt: Vec::with_capacity(n),
        coord: Vec::with_capacity(n),
        num_dense: 0,
        dlt_pixel: Vec::new(),
    };
    for t in parts {
        out.feat_no_embed.extend_from_slice(&t.feat_no_embed);
        out.is_dlt.extend_from_slice(&t.is_dlt);
        out.coord.extend_from_slice(&t.coord);
        out.num_dense += t.num_dense;
        out.dlt_pixel.extend_from_slice(&t.dlt_pixel);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn synthetic_chunk(k: usize, seed: u64) -> ChunkInput {
        let mut s = seed;
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.4 - 1.2
        };
        let mut c = ChunkInput::default();
        for i in 0..k {
            let p = [next() * 0.3, next() * 0.3, next() * 0.3];
            c.ff_pts.push(p);
            c.ff_conf.push(1.0 + next().abs());
            c.geo_pts.push([p[0] + 0.001 * next(), p[1], p[2]]);
            c.geo_msk.push(i % 3 == 0);
        }
        c
    }

    #[test]
    fn config_validation() {
        assert!(PlanConfig::released().validate().is_ok());
        let mut c = PlanConfig::small();
        c.patch_size.pop();
        assert!(matches!(c.validate(), Err(PlanError::InvalidConfig(_))));
        let mut c = PlanConfig::small();
        c.patch_size[2] = 0;
        assert!(c.validate().is_err());
        let mut c = PlanConfig::small();
        c.grid_resolution = 0;
        assert!(c.validate().is_err());
        assert!(matches!(
            plan_batch::<ChunkInput>(&[], &PlanConfig::small()),
            Err(PlanError::NoChunks)
        ));
        let bad = ChunkInput::default();
        let good = synthetic_chunk(10, 1);
        let err = plan_batch(&[good, bad], &PlanConfig::small()).unwrap_err();
        assert!(matches!(err, PlanError::Chunk { chunk: 1, .. }), "{err}");
    }

    #[test]
    fn plan_invariants() {
        let chunks = [synthetic_chunk(700, 3), synthetic_chunk(90, 4)];
        let cfg = PlanConfig {
            grid_resolution: 384,
            patch_size: vec![64, 64, 32, 32, 16],
            num_levels: 5,
        };
        let plan = plan_batch(&chunks, &cfg).unwrap();
        assert_eq!(plan.levels.len(), 5);
        assert_eq!(plan.offsets, [700 + 234, 700 + 234 + 90 + 30]);
        for (l, lv) in plan.levels.iter().enumerate() {
            assert_eq!(lv.num_tokens, *lv.offsets.last().unwrap());
            for r in 0..NUM_ORDERS {
                for (j, &t) in lv.order[r].iter().enumerate() {
                    assert_eq!(lv.inverse[r][t], j);
                }
            }
            assert_eq!(lv.conv.taps.len(), NUM_TAPS);
            if l + 1 < plan.levels.len() {
                let p = lv.pool_to_next.as_ref().unwrap();
                assert_eq!(p.cluster.len(), lv.num_tokens);
                assert_eq!(p.num_coarse, plan.levels[l + 1].num_tokens);
                // Coarse codes equal codes recomputed from the coarse grid at depth - 1.
                let next = &plan.levels[l + 1];
                let re = serialize::compute_codes(&next.grid, &next.offsets, &next.depth);
                assert_eq!(re, next.codes);
                if l > 0 {
                    assert!(p.children_width <= 8);
                    assert!(!lv.conv.has_duplicates);
                }
            } else {
                assert!(lv.pool_to_next.is_none());
            }
        }
    }

    /// Chunks with different depths (8 and 9) planned together equal their single plans.
    #[test]
    fn batched_equals_single_with_different_depths() {
        let mut a = synthetic_chunk(500, 7);
        for p in a.ff_pts.iter_mut().chain(a.geo_pts.iter_mut()) {
            *p = [p[0] * 0.5 - 0.4, p[1] * 0.5 - 0.4, p[2] * 0.5 - 0.4];
        }
        let b = synthetic_chunk(300, 8);
        let cfg = PlanConfig {
            grid_resolution: 384,
            patch_size: vec![64, 32, 32, 16, 16],
            num_levels: 5,
        };
        let pa = plan_batch(std::slice::from_ref(&a), &cfg).unwrap();
        let pb = plan_batch(std::slice::from_ref(&b), &cfg).unwrap();
        assert_eq!(pa.levels[0].depth, [8]);
        assert_eq!(pb.levels[0].depth, [9]);
        let both = plan_batch(&[a, b], &cfg).unwrap();
        for (l, lv) in both.levels.iter().enumerate() {
            assert_eq!(lv.depth, [pa.levels[l].depth[0], pb.levels[l].depth[0]]);
            for (ci, single) in [(0usize, &pa), (1, &pb)] {
                let r = lv.chunk_range(ci);
                let sl = &single.levels[l];
                assert_eq!(r.len(), sl.num_tokens);
                assert_eq!(lv.grid[r.clone()], sl.grid[..]);
                for row in 0..NUM_ORDERS {
                    assert_eq!(lv.codes[row][r.clone()], sl.codes[row][..]);
                    let shifted: Vec<usize> = sl.order[row].iter().map(|&t| t + r.start).collect();
                    assert_eq!(lv.order[row][r.clone()], shifted[..]);
                }
            }
        }
    }
}
