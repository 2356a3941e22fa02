//! Device-side form of a [`BatchPlan`]: every index table the forward needs, uploaded once.
//!
//! The host plan (`crate::plan`) holds plain integers; this module turns them into Int
//! tensors laid out for the building blocks:
//!
//! * sparse conv (network.md §6): an im2col index `[N * 27]` into the extended input
//!   `X_ext = [x; group sums; 0]` — a tap whose target receives several sources (negative taps
//!   on duplicated voxels, §6.3) points at the row holding their sum;
//! * attention (§7): per order row, the windows grouped by length with their gather index
//!   (`order[start..start + len]` per window) and a `take` index `[N]` giving, for every token,
//!   the row of the concatenated window outputs of the window that owns it;
//! * pooling (§8): the padded children table and the cluster (unpooling) index.

use std::collections::{BTreeMap, HashMap};

use burn::tensor::{Device, Int, Tensor};

use crate::config::{FEAT_NO_EMBED_DIM, GgptConfig, NUM_LEVELS};
use crate::error::{ModelError, Result};
use crate::ops::{float_tensor, index_tensor};
use crate::plan::{BatchPlan, ConvTable, LevelPlan, PoolMap, Window};

pub use crate::conv_layout::{ConvLayout, ConvTap, NUM_TAPS};

/// The neighbour tables of one level's submanifold convolution: one packed index list and its
/// layout ([`crate::conv_layout`]).
#[derive(Debug, Clone)]
pub struct ConvIndex {
    /// The packed tables (im2col, group members and ids, per-tap sources and targets).
    pub tables: Tensor<1, Int>,
    /// Where each table sits in `tables`, the taps, `N`, `G` and the occupancy.
    pub layout: ConvLayout,
}

/// Window groups of equal length of one order row.
#[derive(Debug, Clone)]
pub struct WindowGroup {
    /// `[windows * len]`: token index of every window slot, window-major.
    pub gather: Tensor<1, Int>,
    /// Number of windows.
    pub num_windows: usize,
    /// Tokens per window.
    pub len: usize,
}

/// Attention tables of one order row at one level.
#[derive(Debug, Clone)]
pub struct AttnIndex {
    /// Window groups, in the order their outputs are concatenated.
    pub groups: Vec<WindowGroup>,
    /// `[N]`: for every token, its row in the concatenated window outputs.
    pub take: Tensor<1, Int>,
}

/// Pooling tables from this level to the next coarser one.
#[derive(Debug, Clone)]
pub struct PoolIndex {
    /// `[num_coarse * width]` padded member table, row-major.
    pub children: Tensor<1, Int>,
    /// Children per coarse token (padded width).
    pub width: usize,
    /// Tokens of the coarser level.
    pub num_coarse: usize,
    /// `[N_l]` fine token -> coarse token (unpooling gather).
    pub cluster: Tensor<1, Int>,
}

/// All device tables of one level.
#[derive(Debug, Clone)]
pub struct PreparedLevel {
    /// Tokens of the level.
    pub num_tokens: usize,
    /// Sparse-conv tables.
    pub conv: ConvIndex,
    /// Attention tables for rows z, z-trans, hilbert, hilbert-trans.
    pub attn: Vec<AttnIndex>,
    /// Pooling to the next level (absent at the coarsest level).
    pub pool: Option<PoolIndex>,
}

/// Host-side per-chunk bookkeeping for scattering outputs back to pixels.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChunkSpan {
    /// First token of the chunk (level 0).
    pub start: usize,
    /// Number of dense tokens = pixels `K`.
    pub num_dense: usize,
    /// Pixel of each DLT token, in token order (token `start + num_dense + m`).
    pub dlt_pixel: Vec<usize>,
}

impl ChunkSpan {
    /// Total tokens of the chunk.
    pub fn num_tokens(&self) -> usize {
        self.num_dense + self.dlt_pixel.len()
    }
}

/// A whole batch ready for [`crate::Ggpt::forward`].
#[derive(Debug, Clone)]
pub struct PreparedBatch {
    /// Tokens `N` (level 0, all chunks).
    pub num_tokens: usize,
    /// `[N, 202]` guidance channels (without the type embedding).
    pub feat_no_embed: Tensor<2>,
    /// `[N]`: 0 for dense tokens (`e_ff`), 1 for DLT tokens (`e_dlt`).
    pub type_index: Tensor<1, Int>,
    /// `[N, 3]` token coordinates (normalised chunk coordinates).
    pub coord: Tensor<2>,
    /// Levels 0..=4.
    pub levels: Vec<PreparedLevel>,
    /// Per-chunk spans.
    pub chunks: Vec<ChunkSpan>,
}

impl PreparedBatch {
    /// Uploads `plan` to `device`, checking its consistency with `cfg` (patch size is the
    /// caller's business: it is baked into the plan's windows).
    pub fn new(plan: &BatchPlan, _cfg: &GgptConfig, device: &Device) -> Result<Self> {
        let tokens = &plan.tokens;
        let n = tokens.num_tokens;
        if plan.levels.len() != NUM_LEVELS {
            return Err(ModelError::Plan(format!(
                "{} levels, expected {NUM_LEVELS}",
                plan.levels.len()
            )));
        }
        if tokens.feat_no_embed.len() != n * FEAT_NO_EMBED_DIM
            || tokens.is_dlt.len() != n
            || tokens.coord.len() != n
        {
            return Err(ModelError::Plan(format!(
                "token features inconsistent: N = {n}, feat {} (want {}), is_dlt {}, coord {}",
                tokens.feat_no_embed.len(),
                n * FEAT_NO_EMBED_DIM,
                tokens.is_dlt.len(),
                tokens.coord.len()
            )));
        }
        let chunks = chunk_spans(plan)?;
        let feat_no_embed =
            float_tensor(tokens.feat_no_embed.clone(), [n, FEAT_NO_EMBED_DIM], device);
        let types: Vec<usize> = tokens.is_dlt.iter().map(|&d| usize::from(d)).collect();
        let type_index = index_tensor(&types, device);
        let coord_flat: Vec<f32> = tokens
            .coord
            .iter()
            .flat_map(|c| c.iter().copied())
            .collect();
        let coord = float_tensor(coord_flat, [n, 3], device);
        let mut levels = Vec::with_capacity(NUM_LEVELS);
        for (l, level) in plan.levels.iter().enumerate() {
            let expected = if l == 0 {
                Some(n)
            } else {
                plan.levels[l - 1]
                    .pool_to_next
                    .as_ref()
                    .map(|p| p.num_coarse)
            };
            if expected != Some(level.num_tokens) {
                return Err(ModelError::Plan(format!(
                    "level {l} has {} tokens, previous level pools to {expected:?}",
                    level.num_tokens
                )));
            }
            if l + 1 < NUM_LEVELS && level.pool_to_next.is_none() {
                return Err(ModelError::Plan(format!("level {l} has no pooling map")));
            }
            levels.push(prepare_level(l, level, device)?);
        }
        Ok(Self {
            num_tokens: n,
            feat_no_embed,
            type_index,
            coord,
            levels,
            chunks,
        })
    }
}

/// Per-chunk spans from the plan's layout, checked against the token list.
fn chunk_spans(plan: &BatchPlan) -> Result<Vec<ChunkSpan>> {
    let tokens = &plan.tokens;
    let mut spans = Vec::with_capacity(plan.layout.len());
    let mut expected_start = 0usize;
    for (b, lay) in plan.layout.iter().enumerate() {
        let end = lay.token_start + lay.num_dense + lay.num_dlt;
        if lay.token_start != expected_start
            || end > tokens.num_tokens
            || plan.offsets.get(b) != Some(&end)
        {
            return Err(ModelError::Plan(format!(
                "chunk {b}: layout {lay:?} inconsistent with offsets"
            )));
        }
        let dlt_pixel = tokens
            .dlt_pixel
            .get(lay.dlt_start..lay.dlt_start + lay.num_dlt)
            .ok_or_else(|| ModelError::Plan(format!("chunk {b}: dlt_pixel too short")))?
            .to_vec();
        if let Some(&bad) = dlt_pixel.iter().find(|&&p| p >= lay.num_dense) {
            return Err(ModelError::Plan(format!(
                "chunk {b}: DLT pixel {bad} >= {} pixels",
                lay.num_dense
            )));
        }
        spans.push(ChunkSpan {
            start: lay.token_start,
            num_dense: lay.num_dense,
            dlt_pixel,
        });
        expected_start = end;
    }
    if expected_start != tokens.num_tokens {
        return Err(ModelError::Plan(format!(
            "chunks cover {expected_start} of {} tokens",
            tokens.num_tokens
        )));
    }
    Ok(spans)
}

fn prepare_level(l: usize, level: &LevelPlan, device: &Device) -> Result<PreparedLevel> {
    let n = level.num_tokens;
    let conv = conv_index(l, n, &level.conv, device)?;
    let mut attn = Vec::with_capacity(4);
    for r in 0..4 {
        attn.push(attn_index(
            l,
            r,
            n,
            &level.order[r],
            &level.windows,
            device,
        )?);
    }
    let pool = match &level.pool_to_next {
        Some(p) => Some(pool_index(l, n, p, device)?),
        None => None,
    };
    Ok(PreparedLevel {
        num_tokens: n,
        conv,
        attn,
        pool,
    })
}

/// The host im2col index of [`conv_index_host`] (the parts of a [`ConvIndex`], in its order).
pub type ConvIndexHost = (Vec<usize>, Vec<usize>, Vec<usize>, usize);

/// The host attention index of [`attn_index_host`]: the gather groups
/// `(token order, window length, windows)` and the scatter-back table.
pub type AttnIndexHost = (Vec<(Vec<usize>, usize, usize)>, Vec<usize>);

/// Builds the im2col index of network.md §6 (see [`ConvIndex`]).
pub fn conv_index_host(n: usize, table: &ConvTable) -> std::result::Result<ConvIndexHost, String> {
    if table.taps.len() != NUM_TAPS {
        return Err(format!(
            "{} conv taps, expected {NUM_TAPS}",
            table.taps.len()
        ));
    }
    // Placeholder for "no neighbour": fixed up to the zero row once G is known.
    const NONE: usize = usize::MAX;
    let mut im2col = vec![NONE; n * NUM_TAPS];
    let mut groups: HashMap<Vec<usize>, usize> = HashMap::new();
    let mut members = Vec::new();
    let mut ids = Vec::new();
    let mut group_slots: Vec<(usize, usize)> = Vec::new(); // (slot, group)
    for (f, tap) in table.taps.iter().enumerate() {
        if tap.target.len() != tap.source.len() {
            return Err(format!(
                "tap {f}: {} targets but {} sources",
                tap.target.len(),
                tap.source.len()
            ));
        }
        // Pairs sorted by (target, source): runs of equal targets are the duplicate groups.
        let mut pairs: Vec<(usize, usize)> = Vec::with_capacity(tap.target.len());
        for (&t, &s) in tap.target.iter().zip(&tap.source) {
            if t >= n || s >= n {
                return Err(format!("tap {f}: pair ({t}, {s}) out of range {n}"));
            }
            pairs.push((t, s));
        }
        if !pairs.is_sorted() {
            pairs.sort_unstable();
        }
        let mut i = 0;
        while i < pairs.len() {
            let t = pairs[i].0;
            let mut j = i + 1;
            while j < pairs.len() && pairs[j].0 == t {
                j += 1;
            }
            let slot = t * NUM_TAPS + f;
            if j == i + 1 {
                im2col[slot] = pairs[i].1;
            } else {
                let sources: Vec<usize> = pairs[i..j].iter().map(|&(_, s)| s).collect();
                let next = groups.len();
                let g = *groups.entry(sources.clone()).or_insert_with(|| {
                    for &s in &sources {
                        members.push(s);
                        ids.push(next);
                    }
                    next
                });
                group_slots.push((slot, g));
            }
            i = j;
        }
    }
    let num_groups = groups.len();
    for (slot, g) in group_slots {
        im2col[slot] = n + g;
    }
    let zero_row = n + num_groups;
    for v in &mut im2col {
        if *v == NONE {
            *v = zero_row;
        }
    }
    Ok((im2col, members, ids, num_groups))
}

fn conv_index(l: usize, n: usize, table: &ConvTable, device: &Device) -> Result<ConvIndex> {
    let (im2col, members, ids, num_groups) =
        conv_index_host(n, table).map_err(|e| ModelError::Plan(format!("level {l}: {e}")))?;
    let (packed, layout) = crate::conv_layout::pack(n, &im2col, &members, &ids, num_groups);
    Ok(ConvIndex {
        tables: index_tensor(&packed, device),
        layout,
    })
}

/// Host form of [`AttnIndex`]: `(groups as (gather, windows, len), take)`.
pub fn attn_index_host(
    n: usize,
    order: &[usize],
    windows: &[Window],
) -> std::result::Result<AttnIndexHost, String> {
    if order.len() != n {
        return Err(format!("order has {} entries for {n} tokens", order.len()));
    }
    let mut by_len: BTreeMap<usize, Vec<&Window>> = BTreeMap::new();
    for w in windows {
        if w.len == 0
            || w.start + w.len > n
            || w.owned_from < w.start
            || w.owned_from + w.owned_len > w.start + w.len
        {
            return Err(format!("invalid window {w:?} for {n} tokens"));
        }
        by_len.entry(w.len).or_default().push(w);
    }
    const NONE: usize = usize::MAX;
    let mut take = vec![NONE; n];
    let mut groups = Vec::with_capacity(by_len.len());
    let mut base = 0usize;
    // Largest windows first (the full windows), then the short ones.
    for (&len, ws) in by_len.iter().rev() {
        let mut gather = Vec::with_capacity(ws.len() * len);
        for w in ws {
            gather.extend_from_slice(&order[w.start..w.start + w.len]);
            let owned = &order[w.owned_from..w.owned_from + w.owned_len];
            for (p, &token) in (w.owned_from..).zip(owned) {
                if take[token] != NONE {
                    return Err(format!("token {token} owned by two windows"));
                }
                take[token] = base + (p - w.start);
            }
            base += len;
        }
        groups.push((gather, ws.len(), len));
    }
    if let Some(t) = take.iter().position(|&v| v == NONE) {
        return Err(format!("token {t} is owned by no window"));
    }
    Ok((groups, take))
}

fn attn_index(
    l: usize,
    r: usize,
    n: usize,
    order: &[usize],
    windows: &[Window],
    device: &Device,
) -> Result<AttnIndex> {
    let (groups, take) = attn_index_host(n, order, windows)
        .map_err(|e| ModelError::Plan(format!("level {l} row {r}: {e}")))?;
    let groups = groups
        .into_iter()
        .map(|(gather, num_windows, len)| WindowGroup {
            gather: index_tensor(&gather, device),
            num_windows,
            len,
        })
        .collect();
    Ok(AttnIndex {
        groups,
        take: index_tensor(&take, device),
    })
}

fn pool_index(l: usize, n: usize, p: &PoolMap, device: &Device) -> Result<PoolIndex> {
    let err = |m: String| ModelError::Plan(format!("level {l} pooling: {m}"));
    if p.cluster.len() != n {
        return Err(err(format!(
            "cluster has {} entries for {n} tokens",
            p.cluster.len()
        )));
    }
    if p.children_width == 0 || p.children.len() != p.num_coarse * p.children_width {
        return Err(err(format!(
            "children table has {} entries, expected {} x {}",
            p.children.len(),
            p.num_coarse,
            p.children_width
        )));
    }
    if p.children.iter().any(|&c| c >= n) || p.cluster.iter().any(|&c| c >= p.num_coarse) {
        return Err(err("index out of range".into()));
    }
    Ok(PoolIndex {
        children: index_tensor(&p.children, device),
        width: p.children_width,
        num_coarse: p.num_coarse,
        cluster: index_tensor(&p.cluster, device),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plan::TapPairs;

    #[test]
    fn im2col_groups_duplicate_sources() {
        // 3 tokens; tap 0: token 0 receives tokens 1 and 2 (a duplicated voxel); tap 26: 1 <- 0.
        let mut taps = vec![
            TapPairs {
                target: vec![],
                source: vec![]
            };
            NUM_TAPS
        ];
        taps[0] = TapPairs {
            target: vec![0, 0],
            source: vec![2, 1],
        };
        taps[13] = TapPairs {
            target: vec![0, 1, 2],
            source: vec![0, 1, 2],
        };
        taps[26] = TapPairs {
            target: vec![1],
            source: vec![0],
        };
        let table = ConvTable {
            taps,
            has_duplicates: true,
        };
        let (im2col, members, ids, g) = conv_index_host(3, &table).expect("valid");
        assert_eq!(g, 1);
        assert_eq!(members, vec![1, 2]);
        assert_eq!(ids, vec![0, 0]);
        assert_eq!(im2col[0], 3); // group row
        assert_eq!(im2col[13], 0);
        assert_eq!(im2col[27 + 26], 0);
        assert_eq!(im2col[27], 4); // zero row
        assert_eq!(im2col[2 * 27 + 13], 2);
    }

    #[test]
    fn windows_take_first_owner() {
        // n = 5, P = 4: windows [0,4) owning 0..4 and [1,5) owning 4.
        let order = vec![4, 3, 2, 1, 0];
        let windows = vec![
            Window {
                start: 0,
                len: 4,
                owned_from: 0,
                owned_len: 4,
            },
            Window {
                start: 1,
                len: 4,
                owned_from: 4,
                owned_len: 1,
            },
        ];
        let (groups, take) = attn_index_host(5, &order, &windows).expect("valid");
        assert_eq!(groups.len(), 1);
        assert_eq!(groups[0].0, vec![4, 3, 2, 1, 3, 2, 1, 0]);
        // token 0 sits at sorted position 4 -> window 1, slot 3 -> row 7
        assert_eq!(take, vec![7, 3, 2, 1, 0]);
        let bad = vec![Window {
            start: 0,
            len: 4,
            owned_from: 0,
            owned_len: 4,
        }];
        assert!(
            attn_index_host(5, &order, &bad)
                .unwrap_err()
                .contains("owned by no window")
        );
    }
}
