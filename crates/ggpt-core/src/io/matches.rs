//! Dense matches `matches/<matcher>.safetensors` <-> [`MatchSet`] (`formats.md` §5.2, layout of
//! `sfm.md` §2.1).
//!
//! Tensors: `pred_matches` F32 `[N, N, h*w, 2]` (`[t, s, k]` = location `(x, y)` in view `t`, ff
//! pixels, pixel-centre convention, of pixel `k` of view `s`), `pred_scores` F32 `[N, N, h*w]`,
//! optional `pred_cycle_error` F32 `[N, N, h*w]` and `rank_scores` F32 `[N, h*w]`. Metadata:
//! `matcher`, `height`, `width` (decimal strings) and `coords` = `ff-pixel-center` (default) or
//! `normalized-edge` (RoMa: `u ∈ [-1, 1]` spans the image edges; converted on read with
//! `x = (u_x + 1) / 2 * w - 0.5`, `sfm.md` §2.3; only `pred_matches` is converted).

use std::collections::HashMap;
use std::path::Path;

use crate::io::atomic::write_bytes_atomic;
use crate::io::st::{StFile, StWriter, check_finite_f32};
use crate::{CoreError, MatchSet, Result};

/// `coords` metadata value of ff-pixel, pixel-centre coordinates (default).
pub const COORDS_FF_PIXEL_CENTER: &str = "ff-pixel-center";
/// `coords` metadata value of RoMa-style normalised coordinates (`-1`/`+1` = image edges).
pub const COORDS_NORMALIZED_EDGE: &str = "normalized-edge";

/// Matches read from one file together with the resolution recorded in its metadata.
#[derive(Debug, Clone, PartialEq)]
pub struct MatchFile {
    /// The matches (ff pixels, pixel-centre convention).
    pub set: MatchSet,
    /// Number of views `N` (from the tensor shapes).
    pub n: usize,
    /// ff height from the metadata.
    pub h: usize,
    /// ff width from the metadata.
    pub w: usize,
}

/// Writes `set` for `n` views of `h x w` pixels with `coords = ff-pixel-center` (atomic).
/// `set.pred_matches` must be in ff pixels (pixel-centre convention).
pub fn write_matches(path: &Path, set: &MatchSet, n: usize, h: usize, w: usize) -> Result<()> {
    let bytes = encode_matches(path, set, n, h, w)?;
    write_bytes_atomic(path, &bytes)
}

/// Serialises `set` to safetensors bytes (see [`write_matches`]).
pub fn encode_matches(
    path: &Path,
    set: &MatchSet,
    n: usize,
    h: usize,
    w: usize,
) -> Result<Vec<u8>> {
    let hw = h * w;
    let check = |key: &str, len: usize, want: usize| -> Result<()> {
        if len != want {
            return Err(CoreError::format(
                path,
                key,
                format!("{len} values, expected {want} for N={n} h={h} w={w}"),
            ));
        }
        Ok(())
    };
    check("pred_matches", set.pred_matches.len(), n * n * hw * 2)?;
    check("pred_scores", set.pred_scores.len(), n * n * hw)?;
    let mut st = StWriter::new();
    st.f32("pred_matches", &[n, n, hw, 2], &set.pred_matches);
    st.f32("pred_scores", &[n, n, hw], &set.pred_scores);
    if let Some(c) = &set.pred_cycle_error {
        check("pred_cycle_error", c.len(), n * n * hw)?;
        st.f32("pred_cycle_error", &[n, n, hw], c);
    }
    if let Some(r) = &set.rank_scores {
        check("rank_scores", r.len(), n * hw)?;
        st.f32("rank_scores", &[n, hw], r);
    }
    let meta = HashMap::from([
        ("matcher".to_string(), set.matcher.clone()),
        ("height".to_string(), h.to_string()),
        ("width".to_string(), w.to_string()),
        ("coords".to_string(), COORDS_FF_PIXEL_CENTER.to_string()),
    ]);
    st.finish(path, Some(meta))
}

/// Reads a matches file, converts `normalized-edge` coordinates to ff pixels and applies the
/// diagonal convention of `sfm.md` §2.1 (`pred_matches[s, s, k]` = pixel centre of `k`, score 1,
/// cycle error 0). When the metadata has no `matcher`, the file stem is the matcher name.
pub fn read_matches(path: &Path) -> Result<MatchFile> {
    let mut m = read_matches_raw(path)?;
    apply_diagonal(&mut m);
    Ok(m)
}

/// Like [`read_matches`] but keeps the diagonal entries as stored (lossless; used by the
/// project scene directory).
pub fn read_matches_raw(path: &Path) -> Result<MatchFile> {
    let f = StFile::open(path)?;
    let meta_usize = |key: &str| -> Result<usize> {
        let s = f
            .metadata()
            .get(key)
            .ok_or_else(|| f.err(key, "missing __metadata__ entry"))?;
        s.trim()
            .parse::<usize>()
            .map_err(|_| f.err(key, format!("metadata '{s}' is not a non-negative integer")))
    };
    let h = meta_usize("height")?;
    let w = meta_usize("width")?;
    let hw = h * w;
    let shape = f.shape("pred_matches")?.to_vec();
    let n = match shape.as_slice() {
        [a, b, k, 2] if a == b && *k == hw => *a,
        _ => {
            return Err(f.err(
                "pred_matches",
                format!("shape {shape:?} is not [N, N, h*w={hw}, 2] (h={h}, w={w} from metadata)"),
            ));
        }
    };
    let mut pred_matches = f.f32("pred_matches", &[n, n, hw, 2])?;
    let pred_scores = f.f32_finite("pred_scores", &[n, n, hw])?;
    let pred_cycle_error = optional(&f, "pred_cycle_error", &[n, n, hw])?;
    let rank_scores = optional(&f, "rank_scores", &[n, hw])?;
    if let Some(r) = &rank_scores {
        check_finite_f32(f.path(), "rank_scores", r)?;
    }
    let coords = f
        .metadata()
        .get("coords")
        .map(String::as_str)
        .unwrap_or(COORDS_FF_PIXEL_CENTER);
    match coords {
        COORDS_FF_PIXEL_CENTER => {}
        COORDS_NORMALIZED_EDGE => normalized_edge_to_pixels(&mut pred_matches, h, w),
        other => return Err(f.err("coords", format!("unknown coords '{other}' (expected {COORDS_FF_PIXEL_CENTER} or {COORDS_NORMALIZED_EDGE})"))),
    }
    let matcher = match f.metadata().get("matcher") {
        Some(m) => m.clone(),
        None => path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default(),
    };
    let set = MatchSet {
        matcher,
        pred_matches,
        pred_scores,
        pred_cycle_error,
        rank_scores,
    };
    Ok(MatchFile { set, n, h, w })
}

fn optional(f: &StFile, key: &str, shape: &[usize]) -> Result<Option<Vec<f32>>> {
    if f.has(key) {
        Ok(Some(f.f32(key, shape)?))
    } else {
        Ok(None)
    }
}

/// RoMa normalised coordinates (`-1`, `+1` = image edges) to ff pixels, in place:
/// `x = (u_x + 1) / 2 * w - 0.5`, `y = (u_y + 1) / 2 * h - 0.5` (`sfm.md` §2.3).
pub fn normalized_edge_to_pixels(xy: &mut [f32], h: usize, w: usize) {
    let (wf, hf) = (w as f32, h as f32);
    for p in xy.chunks_exact_mut(2) {
        p[0] = (p[0] + 1.0) / 2.0 * wf - 0.5;
        p[1] = (p[1] + 1.0) / 2.0 * hf - 0.5;
    }
}

/// Overwrites the `t = s` entries with the identity convention of `sfm.md` §2.1.
pub fn apply_diagonal(m: &mut MatchFile) {
    let (n, w, hw) = (m.n, m.w, m.h * m.w);
    for s in 0..n {
        let base = (s * n + s) * hw;
        for k in 0..hw {
            if let Some(p) = m
                .set
                .pred_matches
                .get_mut(2 * (base + k)..2 * (base + k) + 2)
            {
                p[0] = (k % w) as f32;
                p[1] = (k / w) as f32;
            }
            if let Some(v) = m.set.pred_scores.get_mut(base + k) {
                *v = 1.0;
            }
            if let Some(v) = m
                .set
                .pred_cycle_error
                .as_mut()
                .and_then(|c| c.get_mut(base + k))
            {
                *v = 0.0;
            }
        }
    }
}

/// Matcher names become file names: `[A-Za-z0-9._+-]`, 1..=128 chars, not starting with `.`.
pub(crate) fn check_matcher_name(dir: &Path, name: &str) -> Result<()> {
    let ok = !name.is_empty()
        && name.len() <= 128
        && !name.starts_with('.')
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-' | '+'));
    if ok {
        Ok(())
    } else {
        Err(CoreError::format(
            dir,
            "matchers",
            format!(
                "matcher name '{name}' is not usable as a file name (allowed: A-Z a-z 0-9 . _ - +, not starting with '.')"
            ),
        ))
    }
}
