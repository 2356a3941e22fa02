//! Chunk records in safetensors (the `ggpt-infer chunk` file format).
//!
//! Input: for `c = 0, 1, ...` (until `chunk{c}/ff_pts` is absent):
//! `chunk{c}/ff_pts` `[K, 3]` f32, `chunk{c}/ff_pts_conf` `[K]` f32 (raw confidence),
//! `chunk{c}/geo_pts` `[K, 3]` f32, `chunk{c}/geo_msks` `[K]` bool (u8 / i32 / f32 0/1 accepted).
//! Points in normalised chunk coordinates (network.md §2).
//!
//! Output: `chunk{c}/ff_pts_out` `[K, 3]`, `ff_pts_conf_out` `[K]`, `geo_pts_out` `[K, 3]`,
//! `geo_pts_conf_out` `[K]`, `tokens_xyz_out` `[N, 3]`, `tokens_conf_out` `[N]`, all f32
//! (network.md §10).

use std::path::Path;

use ggpt_core::io::st::StWriter;
use safetensors::{Dtype, SafeTensors};

use crate::error::{ModelError, Result};
use crate::model::ChunkOutput;
use crate::plan::ChunkInput;

fn err(origin: &Path, message: String) -> ModelError {
    ModelError::ChunkInput {
        path: origin.to_path_buf(),
        message,
    }
}

/// Reads tensor `name` as f32 values with its shape (f32 only).
pub fn read_f32(st: &SafeTensors<'_>, name: &str, origin: &Path) -> Result<(Vec<usize>, Vec<f32>)> {
    let view = st
        .tensor(name)
        .map_err(|e| err(origin, format!("{name}: {e}")))?;
    if view.dtype() != Dtype::F32 {
        return Err(err(
            origin,
            format!("{name}: expected F32, found {:?}", view.dtype()),
        ));
    }
    let values = view
        .data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    Ok((view.shape().to_vec(), values))
}

/// Reads a mask tensor as bools (BOOL, U8, I32, I64 or F32 holding 0/1).
pub fn read_mask(
    st: &SafeTensors<'_>,
    name: &str,
    origin: &Path,
) -> Result<(Vec<usize>, Vec<bool>)> {
    let view = st
        .tensor(name)
        .map_err(|e| err(origin, format!("{name}: {e}")))?;
    let values = ggpt_core::io::st::mask_values(view.dtype(), view.data()).ok_or_else(|| {
        err(
            origin,
            format!("{name}: unsupported mask dtype {:?}", view.dtype()),
        )
    })?;
    Ok((view.shape().to_vec(), values))
}

fn points(
    shape: &[usize],
    values: Vec<f32>,
    name: &str,
    k: Option<usize>,
    origin: &Path,
) -> Result<Vec<[f32; 3]>> {
    if shape.len() != 2 || shape[1] != 3 || k.is_some_and(|k| shape[0] != k) {
        return Err(err(
            origin,
            format!("{name}: shape {shape:?}, expected [K, 3]"),
        ));
    }
    Ok(values.chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect())
}

/// Parses every `chunk{c}/...` record of a safetensors file's bytes.
pub fn chunk_inputs_from_bytes(bytes: &[u8], origin: &Path) -> Result<Vec<ChunkInput>> {
    let st = SafeTensors::deserialize(bytes)
        .map_err(|e| err(origin, format!("invalid safetensors: {e}")))?;
    let mut chunks = Vec::new();
    for c in 0.. {
        let prefix = format!("chunk{c}/");
        if st.tensor(&format!("{prefix}ff_pts")).is_err() {
            break;
        }
        let (s, v) = read_f32(&st, &format!("{prefix}ff_pts"), origin)?;
        let ff_pts = points(&s, v, &format!("{prefix}ff_pts"), None, origin)?;
        let k = ff_pts.len();
        let (s, ff_conf) = read_f32(&st, &format!("{prefix}ff_pts_conf"), origin)?;
        if s != [k] {
            return Err(err(
                origin,
                format!("{prefix}ff_pts_conf: shape {s:?}, expected [{k}]"),
            ));
        }
        let (s, v) = read_f32(&st, &format!("{prefix}geo_pts"), origin)?;
        let geo_pts = points(&s, v, &format!("{prefix}geo_pts"), Some(k), origin)?;
        let (s, geo_msk) = read_mask(&st, &format!("{prefix}geo_msks"), origin)?;
        if s != [k] {
            return Err(err(
                origin,
                format!("{prefix}geo_msks: shape {s:?}, expected [{k}]"),
            ));
        }
        chunks.push(ChunkInput {
            ff_pts,
            ff_conf,
            geo_pts,
            geo_msk,
        });
    }
    if chunks.is_empty() {
        return Err(err(origin, "no chunk0/ff_pts tensor".into()));
    }
    Ok(chunks)
}

/// Reads a chunk-input safetensors file.
pub fn read_chunk_inputs(path: &Path) -> Result<Vec<ChunkInput>> {
    let bytes = std::fs::read(path).map_err(|e| err(path, format!("cannot read: {e}")))?;
    chunk_inputs_from_bytes(&bytes, path)
}

/// Serialises per-chunk outputs as safetensors bytes (names in the module docs).
pub fn chunk_outputs_to_bytes(outputs: &[ChunkOutput]) -> Result<Vec<u8>> {
    let mut w = StWriter::new();
    let flat = |v: &[[f32; 3]]| v.iter().flatten().copied().collect::<Vec<f32>>();
    for (c, o) in outputs.iter().enumerate() {
        let k = o.ff_pts_out.len();
        let n = o.tokens_conf_out.len();
        w.f32(
            &format!("chunk{c}/ff_pts_out"),
            &[k, 3],
            &flat(&o.ff_pts_out),
        );
        w.f32(
            &format!("chunk{c}/ff_pts_conf_out"),
            &[k],
            &o.ff_pts_conf_out,
        );
        w.f32(
            &format!("chunk{c}/geo_pts_out"),
            &[k, 3],
            &flat(&o.geo_pts_out),
        );
        w.f32(
            &format!("chunk{c}/geo_pts_conf_out"),
            &[k],
            &o.geo_pts_conf_out,
        );
        w.f32(
            &format!("chunk{c}/tokens_xyz_out"),
            &[n, 3],
            &flat(&o.tokens_xyz_out),
        );
        w.f32(
            &format!("chunk{c}/tokens_conf_out"),
            &[n],
            &o.tokens_conf_out,
        );
    }
    w.finish(Path::new("<outputs>"), None)
        .map_err(|e| ModelError::CheckpointWrite {
            path: "<outputs>".into(),
            message: e.to_string(),
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outputs_roundtrip_and_inputs_validate() {
        let out = ChunkOutput {
            ff_pts_out: vec![[1.0, 2.0, 3.0]],
            ff_pts_conf_out: vec![2.0],
            geo_pts_out: vec![[0.0; 3]],
            geo_pts_conf_out: vec![0.0],
            tokens_xyz_out: vec![[1.0, 2.0, 3.0]],
            tokens_conf_out: vec![2.0],
        };
        let bytes = chunk_outputs_to_bytes(&[out]).expect("serialises");
        let st = SafeTensors::deserialize(&bytes).expect("valid");
        let (s, v) = read_f32(&st, "chunk0/ff_pts_out", Path::new("x")).expect("present");
        assert_eq!((s, v), (vec![1, 3], vec![1.0, 2.0, 3.0]));
        // outputs are not inputs: no chunk0/ff_pts
        assert!(chunk_inputs_from_bytes(&bytes, Path::new("x")).is_err());
    }
}
