//! Guidance encoding (network.md §3): sinusoidal positional encoding, the 218-channel token
//! features (without the 16 learnable type-embedding channels), the token list and the voxel grid.

use rayon::prelude::*;

use super::PlanError;

/// Number of sinusoidal frequencies per axis (network.md §3.1, `sinusoidal_dim / 2`).
pub const PE_NUM_FREQS: usize = 16;
/// Width of `PE(p)`: 3 raw coordinates + 3 axes x (16 sines + 16 cosines) = 99 (network.md §3.1).
pub const PE_DIM: usize = 3 + 3 * 2 * PE_NUM_FREQS;
/// Width of a learnable type embedding (network.md §3.2); these channels are NOT produced here.
pub const TYPE_EMBED_DIM: usize = 16;
/// Full input feature width of the network (network.md §3.3).
pub const FEAT_DIM: usize = 218;
/// Width of [`TokenFeatures::feat_no_embed`]: channels `16..218` of network.md §3.3.
pub const FEAT_NO_EMBED_DIM: usize = FEAT_DIM - TYPE_EMBED_DIM;
/// Offset (within `feat_no_embed`) of the raw feed-forward confidence (full channel 115).
const CONF_COL: usize = PE_DIM;
/// Offset (within `feat_no_embed`) of `PE(geo_pts)` of a dense token (full channel 116).
const GEO_PE_COL: usize = PE_DIM + 1;
/// Offset (within `feat_no_embed`) of `ff_pts - geo_pts` of a dense token (full channel 215).
const OFFSET_COL: usize = GEO_PE_COL + PE_DIM;
/// Default voxel grid resolution per axis (network.md §3.4).
pub const DEFAULT_GRID_RESOLUTION: u32 = 384;
/// Largest supported grid resolution: voxel coordinates must fit 16 bits (serialization depth <= 16).
pub const MAX_GRID_RESOLUTION: u32 = 1 << 16;

/// The per-pixel network input of one chunk (network.md §2), defined Burn-free in
/// `ggpt_core::chunk_input`; the planner borrows it through [`AsChunkView`].
pub use ggpt_core::chunk_input::{AsChunkView, ChunkInput, ChunkView};

/// Token features of one chunk (or of a concatenated batch, see [`super::BatchPlan`]).
///
/// Token list (network.md §3.3): the `num_dense` dense tokens in pixel order, then one DLT token
/// per masked pixel in pixel order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TokenFeatures {
    /// Number of tokens `N`.
    pub num_tokens: usize,
    /// Row-major `[N, 202]`: channels `16..218` of network.md §3.3 (the caller prepends the
    /// learnable `e_ff` / `e_dlt` embedding, chosen by [`TokenFeatures::is_dlt`]).
    pub feat_no_embed: Vec<f32>,
    /// `[N]`: true for DLT tokens (use `e_dlt`), false for dense tokens (use `e_ff`).
    pub is_dlt: Vec<bool>,
    /// `[N]` token coordinate in normalised chunk coordinates: `ff_pts` (dense) or `geo_pts` (DLT).
    pub coord: Vec<[f32; 3]>,
    /// Number of dense tokens (= pixels `K`; for a concatenated batch the sum over chunks).
    pub num_dense: usize,
    /// For DLT token `m` (token `num_dense + m` of its chunk): its chunk-local pixel index
    /// (for a concatenated batch: the chunks' lists concatenated, see [`super::ChunkLayout`]).
    pub dlt_pixel: Vec<usize>,
}

impl TokenFeatures {
    /// Number of DLT tokens.
    pub fn num_dlt(&self) -> usize {
        self.dlt_pixel.len()
    }
}

/// The 16 `f32` PE frequencies `w_k = 1 / 100^(k/16)` (network.md §3.1), computed in `f32`.
pub fn pe_frequencies() -> [f32; PE_NUM_FREQS] {
    let mut w = [0.0f32; PE_NUM_FREQS];
    for (k, wk) in w.iter_mut().enumerate() {
        *wk = 1.0f32 / 100.0f32.powf(k as f32 / PE_NUM_FREQS as f32);
    }
    w
}

/// Writes `PE(p)` (99 values, network.md §3.1) into `out[..99]`; `p` in normalised chunk coordinates.
/// Layout: `p_x, p_y, p_z`, then per axis 16 sines followed by 16 cosines.
///
/// `out` must hold at least [`PE_DIM`] values (only the first 99 are written).
pub fn positional_encoding_into(p: [f32; 3], freqs: &[f32; PE_NUM_FREQS], out: &mut [f32]) {
    let Some(out) = out.get_mut(..PE_DIM) else {
        return;
    };
    out[..3].copy_from_slice(&p);
    for (a, &pa) in p.iter().enumerate() {
        let base = 3 + 2 * PE_NUM_FREQS * a;
        let (sins, coss) = out[base..base + 2 * PE_NUM_FREQS].split_at_mut(PE_NUM_FREQS);
        for ((s, c), &w) in sins.iter_mut().zip(coss.iter_mut()).zip(freqs.iter()) {
            let (sv, cv) = (pa * w).sin_cos();
            *s = sv;
            *c = cv;
        }
    }
}

/// `PE(p)` as an owned array (network.md §3.1); `p` in normalised chunk coordinates.
pub fn positional_encoding(p: [f32; 3]) -> [f32; PE_DIM] {
    let mut out = [0.0f32; PE_DIM];
    positional_encoding_into(p, &pe_frequencies(), &mut out);
    out
}

/// Voxel coordinate of one axis value (network.md §3.4), evaluated in `f32` in the spec's order:
/// `clamp(floor(((clamp(c, -1, 1) + 1) / 2) * res), 0, res - 1)`. `c` in normalised chunk units.
pub fn grid_axis(c: f32, resolution: u32) -> i32 {
    let v = ((c.clamp(-1.0, 1.0) + 1.0) / 2.0) * resolution as f32;
    let max = resolution.saturating_sub(1) as i32;
    (v.floor() as i32).clamp(0, max)
}

/// Voxel coordinate `(x, y, z)` of a token coordinate (network.md §3.4); `c` in normalised chunk units.
pub fn grid_coord(c: [f32; 3], resolution: u32) -> [i32; 3] {
    [
        grid_axis(c[0], resolution),
        grid_axis(c[1], resolution),
        grid_axis(c[2], resolution),
    ]
}

/// Checks lengths, emptiness and finiteness of a chunk (network.md §2).
fn validate(chunk: ChunkView<'_>) -> Result<(), PlanError> {
    let k = chunk.ff_pts.len();
    for (field, got) in [
        ("ff_conf", chunk.ff_conf.len()),
        ("geo_pts", chunk.geo_pts.len()),
        ("geo_msk", chunk.geo_msk.len()),
    ] {
        if got != k {
            return Err(PlanError::LengthMismatch {
                field,
                expected: k,
                got,
            });
        }
    }
    if k == 0 {
        return Err(PlanError::EmptyChunk);
    }
    if let Some(index) = chunk
        .ff_pts
        .iter()
        .position(|p| !p.iter().all(|v| v.is_finite()))
    {
        return Err(PlanError::NonFinite {
            field: "ff_pts",
            index,
        });
    }
    if let Some(index) = chunk.ff_conf.iter().position(|v| !v.is_finite()) {
        return Err(PlanError::NonFinite {
            field: "ff_conf",
            index,
        });
    }
    if let Some(index) = chunk
        .geo_pts
        .iter()
        .zip(chunk.geo_msk)
        .position(|(p, &m)| m && !p.iter().all(|v| v.is_finite()))
    {
        return Err(PlanError::NonFinite {
            field: "geo_pts",
            index,
        });
    }
    Ok(())
}

/// Builds the token list and the 202 non-embedding feature channels of one chunk (network.md §3.3).
///
/// Masking is by selection: channels of a missing guidance point are written as zeros, never
/// multiplied, so garbage in unused `geo_pts` rows cannot leak.
///
/// Errors: length mismatch, empty chunk, non-finite `ff_pts` / `ff_conf`, non-finite `geo_pts`
/// where `geo_msk` is true.
///
/// `chunk` is anything that lends the four per-pixel arrays ([`ChunkInput`], a chunk record, a
/// training chunk, a reference to one): nothing is copied.
pub fn encode_chunk<C: AsChunkView + ?Sized>(chunk: &C) -> Result<TokenFeatures, PlanError> {
    let chunk = chunk.chunk_view();
    validate(chunk)?;
    let k = chunk.ff_pts.len();
    let dlt_pixel: Vec<usize> = chunk
        .geo_msk
        .iter()
        .enumerate()
        .filter_map(|(i, &m)| m.then_some(i))
        .collect();
    let n = k + dlt_pixel.len();
    let freqs = pe_frequencies();
    let mut feat = vec![0.0f32; n * FEAT_NO_EMBED_DIM];
    let (dense_rows, dlt_rows) = feat.split_at_mut(k * FEAT_NO_EMBED_DIM);
    dense_rows
        .par_chunks_mut(FEAT_NO_EMBED_DIM)
        .zip(chunk.ff_pts.par_iter())
        .zip(chunk.ff_conf.par_iter())
        .zip(chunk.geo_pts.par_iter().zip(chunk.geo_msk.par_iter()))
        .for_each(|(((row, &ff), &conf), (&geo, &msk))| {
            positional_encoding_into(ff, &freqs, &mut row[..PE_DIM]);
            row[CONF_COL] = conf;
            if msk {
                positional_encoding_into(geo, &freqs, &mut row[GEO_PE_COL..GEO_PE_COL + PE_DIM]);
                for a in 0..3 {
                    row[OFFSET_COL + a] = ff[a] - geo[a];
                }
            }
        });
    dlt_rows
        .par_chunks_mut(FEAT_NO_EMBED_DIM)
        .zip(dlt_pixel.par_iter())
        .for_each(|(row, &i)| {
            if let Some(&geo) = chunk.geo_pts.get(i) {
                positional_encoding_into(geo, &freqs, &mut row[..PE_DIM]);
            }
        });
    let mut coord = Vec::with_capacity(n);
    coord.extend_from_slice(chunk.ff_pts);
    coord.extend(
        dlt_pixel
            .iter()
            .filter_map(|&i| chunk.geo_pts.get(i).copied()),
    );
    let mut is_dlt = vec![false; k];
    is_dlt.resize(n, true);
    Ok(TokenFeatures {
        num_tokens: n,
        feat_no_embed: feat,
        is_dlt,
        coord,
        num_dense: k,
        dlt_pixel,
    })
}

#[cfg(test)]
#[allow(clippy::excessive_precision)] // spec values as printed
mod tests {
    use super::*;

    /// The official f32 values as printed in network.md §3.1.
    #[allow(clippy::excessive_precision)]
    const OFFICIAL_FREQS: [f32; 16] = [
        1.0,
        0.749894202,
        0.562341332,
        0.421696514,
        0.316227764,
        0.237137362,
        0.177827939,
        0.133352146,
        0.100000001,
        0.0749894157,
        0.0562341288,
        0.0421696492,
        0.0316227786,
        0.0237137359,
        0.0177827943,
        0.0133352149,
    ];

    #[test]
    fn frequencies_match_official_f32_values() {
        let w = pe_frequencies();
        for (a, b) in w.iter().zip(OFFICIAL_FREQS.iter()) {
            assert!((a - b).abs() <= f32::EPSILON * b, "{a} vs {b}");
        }
    }

    #[test]
    fn pe_test_vector() {
        let pe = positional_encoding([0.5, -0.25, 1.0]);
        let expect: [(usize, f32); 18] = [
            (0, 0.5),
            (1, -0.25),
            (2, 1.0),
            (3, 0.47942555),
            (4, 0.36622331),
            (5, 0.27748054),
            (19, 0.87758255),
            (20, 0.93052697),
            (21, 0.96073127),
            (35, -0.24740396),
            (36, -0.18637732),
            (37, -0.1401227),
            (67, 0.84147096),
            (68, 0.68156135),
            (69, 0.53316844),
            (96, 0.99971884),
            (97, 0.99984187),
            (98, 0.99991107),
        ];
        for (c, v) in expect {
            assert!((pe[c] - v).abs() < 1e-6, "channel {c}: {} vs {v}", pe[c]);
        }
    }

    #[test]
    fn grid_test_vector() {
        let cs = [
            -1.3f32, -1.0, -0.9999, -0.5, 0.0, 0.3, 0.99739581, 0.9974, 1.0, 1.25,
        ];
        let gs = [0, 0, 0, 96, 192, 249, 383, 383, 383, 383];
        for (c, g) in cs.iter().zip(gs.iter()) {
            assert_eq!(grid_axis(*c, 384), *g, "coord {c}");
        }
        assert_eq!(
            grid_coord([-0.41561896, -0.06558654, -0.00726834], 384),
            [112, 179, 190]
        );
    }

    fn tiny_chunk() -> ChunkInput {
        ChunkInput {
            ff_pts: vec![[0.1, 0.2, 0.3], [-0.5, 0.0, 0.9], [0.0, 0.0, 0.0]],
            ff_conf: vec![1.5, 2.0, 3.0],
            geo_pts: vec![
                [f32::NAN, f32::INFINITY, 7.0],
                [-0.4, 0.1, 0.8],
                [0.2, -0.2, 0.0],
            ],
            geo_msk: vec![false, true, true],
        }
    }

    #[test]
    fn token_list_layout_and_masking_by_selection() {
        let chunk = tiny_chunk();
        let t = encode_chunk(&chunk).unwrap();
        assert_eq!(t.num_tokens, 5);
        assert_eq!(t.num_dense, 3);
        assert_eq!(t.dlt_pixel, vec![1, 2]);
        assert_eq!(t.is_dlt, vec![false, false, false, true, true]);
        assert_eq!(t.coord[3], [-0.4, 0.1, 0.8]);
        assert_eq!(t.coord[4], [0.2, -0.2, 0.0]);
        assert_eq!(t.feat_no_embed.len(), 5 * FEAT_NO_EMBED_DIM);
        assert!(t.feat_no_embed.iter().all(|v| v.is_finite()));
        let row = |j: usize| &t.feat_no_embed[j * FEAT_NO_EMBED_DIM..(j + 1) * FEAT_NO_EMBED_DIM];
        // Dense token 0: no guidance -> 102 literal zeros.
        assert_eq!(&row(0)[..PE_DIM], &positional_encoding([0.1, 0.2, 0.3])[..]);
        assert_eq!(row(0)[CONF_COL], 1.5);
        assert!(row(0)[GEO_PE_COL..].iter().all(|&v| v == 0.0));
        // Dense token 1: guidance PE and dense-minus-DLT offset.
        assert_eq!(
            &row(1)[GEO_PE_COL..GEO_PE_COL + PE_DIM],
            &positional_encoding([-0.4, 0.1, 0.8])[..]
        );
        assert_eq!(row(1)[OFFSET_COL], -0.5f32 - -0.4f32);
        assert_eq!(row(1)[OFFSET_COL + 2], 0.9f32 - 0.8f32);
        // DLT token of pixel 2: PE(geo) then 103 zeros.
        assert_eq!(
            &row(4)[..PE_DIM],
            &positional_encoding([0.2, -0.2, 0.0])[..]
        );
        assert!(row(4)[PE_DIM..].iter().all(|&v| v == 0.0));
    }

    #[test]
    fn validation_errors() {
        let mut c = tiny_chunk();
        c.ff_conf.pop();
        assert!(matches!(
            encode_chunk(&c),
            Err(PlanError::LengthMismatch {
                field: "ff_conf",
                ..
            })
        ));
        let mut c = tiny_chunk();
        c.geo_msk.push(true);
        assert!(matches!(
            encode_chunk(&c),
            Err(PlanError::LengthMismatch {
                field: "geo_msk",
                ..
            })
        ));
        assert!(matches!(
            encode_chunk(&ChunkInput::default()),
            Err(PlanError::EmptyChunk)
        ));
        let mut c = tiny_chunk();
        c.ff_pts[2][1] = f32::NAN;
        assert!(matches!(
            encode_chunk(&c),
            Err(PlanError::NonFinite {
                field: "ff_pts",
                index: 2
            })
        ));
        let mut c = tiny_chunk();
        c.ff_conf[1] = f32::INFINITY;
        assert!(matches!(
            encode_chunk(&c),
            Err(PlanError::NonFinite {
                field: "ff_conf",
                index: 1
            })
        ));
        let mut c = tiny_chunk();
        c.geo_pts[1][0] = f32::NEG_INFINITY;
        assert!(matches!(
            encode_chunk(&c),
            Err(PlanError::NonFinite {
                field: "geo_pts",
                index: 1
            })
        ));
    }

    #[test]
    fn chunk_without_dlt_pixels_has_dense_tokens_only() {
        let mut c = tiny_chunk();
        c.geo_msk = vec![false; 3];
        let t = encode_chunk(&c).unwrap();
        assert_eq!(t.num_tokens, 3);
        assert!(t.dlt_pixel.is_empty());
        assert!(t.is_dlt.iter().all(|&d| !d));
    }
}
