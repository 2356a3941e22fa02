//! Chunk sets: the on-disk format of curated training chunks (`docs/training.md`).
//!
//! A chunk set is a directory:
//!
//! ```text
//! manifest.json                   format, scenes (name, split, dims, metres per SfM unit), shards
//! train-00000.safetensors ...     shards of the training split
//! val-00000.safetensors ...       shards of the validation split (held-out scenes)
//! ```
//!
//! Every shard is a safetensors file holding `C` chunks with `T` tokens (pixels) in total:
//!
//! | tensor | dtype | shape | meaning |
//! |---|---|---|---|
//! | `offsets` | I64 | `[C + 1]` | chunk `i` owns pixel rows `offsets[i]..offsets[i+1]` |
//! | `scene` | I64 | `[C]` | index into the manifest's `scenes` |
//! | `center` | F32 | `[C, 3]` | chunk centre `c` (SfM frame, scene units) |
//! | `radius` | F64 | `[C]` | chunk half-size `r` (scene units) |
//! | `pixel` | I64 | `[T]` | flat pixel index `(n h + y) w + x` (view id = `pixel / (h w)`) |
//! | `ff_pts` | F32 | `[T, 3]` | `(X_d - c) / r` (aligned dense points, chunk frame) |
//! | `ff_pts_conf` | F32 | `[T]` | raw feed-forward confidence |
//! | `geo_pts` | F32 | `[T, 3]` | `(X_s - c) / r`, 0 where `geo_msks` is 0 |
//! | `geo_msks` | U8 | `[T]` | pixel has a DLT point |
//! | `gt_pts` | F32 | `[T, 3]` | `(X_gt - c) / r` (GT Sim(3)-aligned to the SfM frame), 0 where invalid |
//! | `gt_msks` | U8 | `[T]` | valid GT |
//!
//! The manifest records each shard's byte size and CRC-32; [`ChunkSet::load_split`] checks
//! both and the tensor shapes, and fails with an error naming the shard: corrupt data is never
//! skipped silently. Shards are read whole into memory (training sets of this project fit).

use std::path::{Path, PathBuf};

use ggpt_core::CoreError;
use ggpt_core::chunk_input::{AsChunkView, ChunkInput, ChunkView};
use ggpt_core::io::st::{Dtype, StFile, StWriter};
use serde::{Deserialize, Serialize};

use crate::error::{Result, TrainError, io_err};

/// Format name written into the manifest.
pub const FORMAT_NAME: &str = "ggpt-chunkset";
/// Format version.
pub const FORMAT_VERSION: u32 = 1;
/// Manifest file name inside a chunk-set directory.
pub const MANIFEST: &str = "manifest.json";

/// Dataset split of a scene.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Split {
    /// Training scenes.
    Train,
    /// Held-out validation scenes.
    Val,
}

impl Split {
    /// `train` / `val`.
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Val => "val",
        }
    }
}

/// One training chunk with ground truth (normalised chunk coordinates, `pipeline.md` §6).
///
/// The network input is a [`ChunkInput`] (the same struct a scene chunk record holds; its fields
/// `ff_pts`, `ff_conf`, `geo_pts`, `geo_msk` are reachable through `Deref`); forwards plan the
/// chunk through [`AsChunkView`], borrowing it.
#[derive(Debug, Clone, PartialEq)]
pub struct TrainChunk {
    /// Index of the scene in the manifest.
    pub scene: usize,
    /// Chunk centre `c` (SfM frame, scene units).
    pub center: [f32; 3],
    /// Chunk half-size `r` (scene units).
    pub radius: f64,
    /// Flat pixel indices, pixel order.
    pub pixels: Vec<u32>,
    /// Network input, chunk frame, `[K]` each: `ff_pts = (X_d - c) / r`, raw confidence
    /// `ff_conf`, `geo_pts = (X_s - c) / r` (0 where no DLT point) and the DLT mask `geo_msk`
    /// (the same struct as a scene chunk record's input; reachable through `Deref`).
    pub input: ChunkInput,
    /// `(X_gt - c) / r`, 0 where invalid.
    pub gt_pts: Vec<[f32; 3]>,
    /// Valid GT.
    pub gt_msk: Vec<bool>,
}

impl TrainChunk {
    /// A deterministic chunk of `k` pixels with arbitrary in-range values, a third of them with a
    /// DLT point and a fifth without GT (tests, benchmarks, fuzz seeds; `seed` varies the values).
    pub fn deterministic(scene: usize, k: usize, seed: u32) -> TrainChunk {
        let f = |i: usize, a: u32| {
            (((i as u32)
                .wrapping_mul(2_654_435_761)
                .wrapping_add(seed * 97 + a * 13))
                % 1000) as f32
                / 500.0
                - 1.0
        };
        TrainChunk {
            scene,
            center: [0.5, -0.25, 2.0],
            radius: 0.3,
            pixels: (0..k as u32).map(|p| p * 3 + seed).collect(),
            input: ChunkInput {
                ff_pts: (0..k).map(|i| [f(i, 0), f(i, 1), f(i, 2)]).collect(),
                ff_conf: (0..k).map(|i| 1.0 + (f(i, 3) + 1.0) * 2.0).collect(),
                geo_pts: (0..k)
                    .map(|i| {
                        if i % 3 == 0 {
                            [f(i, 4), f(i, 5), f(i, 6)]
                        } else {
                            [0.0; 3]
                        }
                    })
                    .collect(),
                geo_msk: (0..k).map(|i| i % 3 == 0).collect(),
            },
            gt_pts: (0..k)
                .map(|i| {
                    if i % 5 != 4 {
                        [f(i, 0) * 0.9, f(i, 1) * 0.9, f(i, 2) * 0.9]
                    } else {
                        [0.0; 3]
                    }
                })
                .collect(),
            gt_msk: (0..k).map(|i| i % 5 != 4).collect(),
        }
    }

    /// Pixels (dense tokens) `K`.
    pub fn len(&self) -> usize {
        self.pixels.len()
    }
    /// True when the chunk has no pixel.
    pub fn is_empty(&self) -> bool {
        self.pixels.is_empty()
    }
    /// Network tokens: dense + DLT.
    pub fn num_tokens(&self) -> usize {
        self.len() + self.geo_msk.iter().filter(|&&m| m).count()
    }
    /// An owned copy of the network input of this chunk, `geo_pts` rows without a DLT point
    /// written as 0 (the network ignores those rows, so planning the borrowed chunk gives the
    /// same result without the copy).
    pub fn to_input(&self) -> ChunkInput {
        ChunkInput {
            ff_pts: self.ff_pts.clone(),
            ff_conf: self.ff_conf.clone(),
            geo_pts: self
                .geo_pts
                .iter()
                .zip(&self.geo_msk)
                .map(|(p, &m)| if m { *p } else { [0.0; 3] })
                .collect(),
            geo_msk: self.geo_msk.clone(),
        }
    }
    /// Checks that every per-pixel array has `K` entries and all values are finite.
    pub fn validate(&self) -> std::result::Result<(), String> {
        let k = self.pixels.len();
        for (name, n) in [
            ("ff_pts", self.ff_pts.len()),
            ("ff_pts_conf", self.ff_conf.len()),
            ("geo_pts", self.geo_pts.len()),
            ("geo_msks", self.geo_msk.len()),
            ("gt_pts", self.gt_pts.len()),
            ("gt_msks", self.gt_msk.len()),
        ] {
            if n != k {
                return Err(format!("{name} has {n} rows, the chunk has {k} pixels"));
            }
        }
        let finite3 = |v: &[[f32; 3]]| v.iter().flatten().all(|x| x.is_finite());
        if !finite3(&self.ff_pts)
            || !finite3(&self.geo_pts)
            || !finite3(&self.gt_pts)
            || !self.ff_conf.iter().all(|x| x.is_finite())
        {
            return Err("non-finite value".into());
        }
        if !(self.radius.is_finite() && self.radius > 0.0) {
            return Err(format!("radius {} is not positive", self.radius));
        }
        Ok(())
    }
}

impl AsChunkView for TrainChunk {
    fn chunk_view(&self) -> ChunkView<'_> {
        self.input.view()
    }
}

impl std::ops::Deref for TrainChunk {
    type Target = ChunkInput;
    fn deref(&self) -> &ChunkInput {
        &self.input
    }
}

impl std::ops::DerefMut for TrainChunk {
    fn deref_mut(&mut self) -> &mut ChunkInput {
        &mut self.input
    }
}

/// A scene of the chunk set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneEntry {
    /// Scene name (sequence folder name, or `synth_<kind>_s<seed>`).
    pub name: String,
    /// Split.
    pub split: Split,
    /// Views.
    pub views: usize,
    /// ff height.
    pub height: usize,
    /// ff width.
    pub width: usize,
    /// Metres per SfM-frame unit (`1 / s` of the GT -> SfM similarity); converts chunk errors
    /// `|x̂ - x_gt| r` to metres for the validation AUC.
    pub metres_per_unit: f64,
    /// Where the scene came from (rebuilt from it by `ggpt-train eval`).
    pub source: crate::scene_source::SceneSource,
}

/// A shard of the chunk set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ShardEntry {
    /// File name relative to the chunk-set directory.
    pub file: String,
    /// Split of all its chunks.
    pub split: Split,
    /// Chunks in the shard.
    pub chunks: usize,
    /// Pixels (dense tokens) in the shard.
    pub pixels: usize,
    /// File size in bytes.
    pub bytes: u64,
    /// CRC-32 (IEEE) of the file.
    pub crc32: u32,
}

/// `manifest.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// [`FORMAT_NAME`].
    pub format: String,
    /// [`FORMAT_VERSION`].
    pub version: u32,
    /// How the set was made (free-form JSON: sampler parameters, seed, command).
    pub provenance: serde_json::Value,
    /// Scenes.
    pub scenes: Vec<SceneEntry>,
    /// Shards.
    pub shards: Vec<ShardEntry>,
}

/// Writes a chunk set: chunks are buffered and flushed into shards of at most
/// `max_chunks_per_shard` chunks; [`ChunkSetWriter::finish`] writes the manifest (atomically).
pub struct ChunkSetWriter {
    dir: PathBuf,
    max_chunks_per_shard: usize,
    manifest: Manifest,
    pending: [Vec<TrainChunk>; 2],
}

fn split_slot(s: Split) -> usize {
    match s {
        Split::Train => 0,
        Split::Val => 1,
    }
}

impl ChunkSetWriter {
    /// A writer into `dir` (created if needed).
    pub fn new(
        dir: &Path,
        max_chunks_per_shard: usize,
        provenance: serde_json::Value,
    ) -> Result<Self> {
        std::fs::create_dir_all(dir).map_err(io_err(dir))?;
        Ok(Self {
            dir: dir.to_path_buf(),
            max_chunks_per_shard: max_chunks_per_shard.max(1),
            manifest: Manifest {
                format: FORMAT_NAME.into(),
                version: FORMAT_VERSION,
                provenance,
                scenes: Vec::new(),
                shards: Vec::new(),
            },
            pending: [Vec::new(), Vec::new()],
        })
    }

    /// Registers a scene; returns its index for [`TrainChunk::scene`].
    pub fn add_scene(&mut self, scene: SceneEntry) -> usize {
        self.manifest.scenes.push(scene);
        self.manifest.scenes.len() - 1
    }

    /// Adds a chunk of a registered scene (its split is the scene's).
    pub fn add_chunk(&mut self, chunk: TrainChunk) -> Result<()> {
        let split = self
            .manifest
            .scenes
            .get(chunk.scene)
            .map(|s| s.split)
            .ok_or_else(|| {
                TrainError::Invalid(format!("chunk of unknown scene {}", chunk.scene))
            })?;
        chunk
            .validate()
            .map_err(|m| TrainError::Invalid(format!("chunk of scene {}: {m}", chunk.scene)))?;
        let slot = split_slot(split);
        self.pending[slot].push(chunk);
        if self.pending[slot].len() >= self.max_chunks_per_shard {
            self.flush(split)?;
        }
        Ok(())
    }

    fn flush(&mut self, split: Split) -> Result<()> {
        let chunks = std::mem::take(&mut self.pending[split_slot(split)]);
        if chunks.is_empty() {
            return Ok(());
        }
        let index = self
            .manifest
            .shards
            .iter()
            .filter(|s| s.split == split)
            .count();
        let file = format!("{}-{index:05}.safetensors", split.name());
        let path = self.dir.join(&file);
        let bytes = shard_bytes(&chunks)?;
        ggpt_core::io::atomic::write_atomic(&path, |w| w.write_all(&bytes))?;
        self.manifest.shards.push(ShardEntry {
            file,
            split,
            chunks: chunks.len(),
            pixels: chunks.iter().map(TrainChunk::len).sum(),
            bytes: bytes.len() as u64,
            crc32: crc32fast::hash(&bytes),
        });
        Ok(())
    }

    /// Flushes the pending chunks and writes `manifest.json`.
    pub fn finish(mut self) -> Result<Manifest> {
        self.flush(Split::Train)?;
        self.flush(Split::Val)?;
        let path = self.dir.join(MANIFEST);
        let text =
            serde_json::to_string_pretty(&self.manifest).map_err(|e| TrainError::Format {
                path: path.clone(),
                message: e.to_string(),
            })?;
        ggpt_core::io::atomic::write_atomic(&path, |w| w.write_all(text.as_bytes()))?;
        Ok(self.manifest)
    }
}

fn le_bytes<T: Copy, const N: usize>(
    values: impl Iterator<Item = T>,
    to: impl Fn(T) -> [u8; N],
) -> Vec<u8> {
    values.flat_map(to).collect()
}

/// Serialises chunks into one shard (safetensors bytes).
pub fn shard_bytes(chunks: &[TrainChunk]) -> Result<Vec<u8>> {
    let c = chunks.len();
    let t: usize = chunks.iter().map(TrainChunk::len).sum();
    let mut offsets = Vec::with_capacity(c + 1);
    offsets.push(0i64);
    for ch in chunks {
        let last = offsets.last().copied().unwrap_or(0);
        offsets.push(last + ch.len() as i64);
    }
    let pts = |f: fn(&TrainChunk) -> &Vec<[f32; 3]>| {
        le_bytes(
            chunks.iter().flat_map(f).flatten().copied(),
            f32::to_le_bytes,
        )
    };
    let msk = |f: fn(&TrainChunk) -> &Vec<bool>| {
        chunks
            .iter()
            .flat_map(f)
            .map(|&b| u8::from(b))
            .collect::<Vec<u8>>()
    };
    let mut w = StWriter::new();
    w.i64("offsets", &[c + 1], &offsets);
    w.raw(
        "scene",
        Dtype::I64,
        &[c],
        le_bytes(chunks.iter().map(|ch| ch.scene as i64), i64::to_le_bytes),
    );
    w.raw(
        "center",
        Dtype::F32,
        &[c, 3],
        le_bytes(chunks.iter().flat_map(|ch| ch.center), f32::to_le_bytes),
    );
    w.raw(
        "radius",
        Dtype::F64,
        &[c],
        le_bytes(chunks.iter().map(|ch| ch.radius), f64::to_le_bytes),
    );
    w.raw(
        "pixel",
        Dtype::I64,
        &[t],
        le_bytes(
            chunks
                .iter()
                .flat_map(|ch| ch.pixels.iter().map(|&p| i64::from(p))),
            i64::to_le_bytes,
        ),
    );
    w.raw("ff_pts", Dtype::F32, &[t, 3], pts(|ch| &ch.ff_pts));
    w.raw(
        "ff_pts_conf",
        Dtype::F32,
        &[t],
        le_bytes(
            chunks.iter().flat_map(|ch| ch.ff_conf.iter().copied()),
            f32::to_le_bytes,
        ),
    );
    w.raw("geo_pts", Dtype::F32, &[t, 3], pts(|ch| &ch.geo_pts));
    w.raw("geo_msks", Dtype::U8, &[t], msk(|ch| &ch.geo_msk));
    w.raw("gt_pts", Dtype::F32, &[t, 3], pts(|ch| &ch.gt_pts));
    w.raw("gt_msks", Dtype::U8, &[t], msk(|ch| &ch.gt_msk));
    w.finish(Path::new("shard"), None)
        .map_err(|e| TrainError::Invalid(format!("shard serialisation: {e}")))
}

/// A shard reader error as a [`TrainError::Shard`] naming the shard (and the tensor).
fn shard_error(path: &Path, e: CoreError) -> TrainError {
    let message = match e {
        CoreError::Format { key, message, .. } if key.is_empty() => message,
        CoreError::Format { key, message, .. } => format!("tensor '{key}': {message}"),
        CoreError::NonFinite {
            key, index, value, ..
        } => format!("tensor '{key}': non-finite value {value} at flat index {index}"),
        other => other.to_string(),
    };
    TrainError::Shard {
        path: path.to_path_buf(),
        message,
    }
}

fn triples(v: &[f32]) -> Vec<[f32; 3]> {
    v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
}

/// Parses shard bytes (already checksum-verified) into chunks; `path` names the shard in errors;
/// `num_scenes` bounds the scene indices.
pub fn parse_shard(bytes: &[u8], path: &Path, num_scenes: usize) -> Result<Vec<TrainChunk>> {
    parse_shard_owned(bytes.to_vec(), path, num_scenes)
}

/// [`parse_shard`] of bytes the caller hands over (no copy of the shard).
fn parse_shard_owned(bytes: Vec<u8>, path: &Path, num_scenes: usize) -> Result<Vec<TrainChunk>> {
    let shard_err = |message: String| TrainError::Shard {
        path: path.to_path_buf(),
        message,
    };
    let st = StFile::from_bytes(path, bytes).map_err(|e| shard_error(path, e))?;
    let c = st
        .shape("offsets")
        .map_err(|e| shard_error(path, e))?
        .first()
        .copied()
        .unwrap_or(0)
        .saturating_sub(1);
    let read = |e| shard_error(path, e);
    let offsets = st.i64("offsets", &[c + 1]).map_err(read)?;
    let t = offsets.last().copied().unwrap_or(0);
    if offsets.first() != Some(&0) || offsets.windows(2).any(|w| w[1] < w[0]) || t < 0 {
        return Err(shard_err(
            "offsets are not a non-decreasing sequence starting at 0".into(),
        ));
    }
    let t = t as usize;
    let scene = st.i64("scene", &[c]).map_err(read)?;
    let center = st.f32("center", &[c, 3]).map_err(read)?;
    let radius = st.f64("radius", &[c]).map_err(read)?;
    let pixel = st.i64("pixel", &[t]).map_err(read)?;
    let ff_pts = triples(&st.f32("ff_pts", &[t, 3]).map_err(read)?);
    let ff_conf = st.f32("ff_pts_conf", &[t]).map_err(read)?;
    let geo_pts = triples(&st.f32("geo_pts", &[t, 3]).map_err(read)?);
    let mask = |key: &str| -> Result<Vec<bool>> {
        Ok(st
            .u8(key, &[t])
            .map_err(read)?
            .iter()
            .map(|&b| b != 0)
            .collect())
    };
    let geo_msk = mask("geo_msks")?;
    let gt_pts = triples(&st.f32("gt_pts", &[t, 3]).map_err(read)?);
    let gt_msk = mask("gt_msks")?;
    let mut out = Vec::with_capacity(c);
    for i in 0..c {
        let (a, b) = (offsets[i] as usize, offsets[i + 1] as usize);
        let s = scene[i];
        if s < 0 || s as usize >= num_scenes {
            return Err(shard_err(format!(
                "chunk {i}: scene index {s} out of range ({num_scenes} scenes in the manifest)"
            )));
        }
        let pixels = pixel[a..b]
            .iter()
            .map(|&p| {
                u32::try_from(p)
                    .map_err(|_| shard_err(format!("chunk {i}: pixel index {p} out of range")))
            })
            .collect::<Result<Vec<u32>>>()?;
        let chunk = TrainChunk {
            scene: s as usize,
            center: [center[3 * i], center[3 * i + 1], center[3 * i + 2]],
            radius: radius[i],
            pixels,
            input: ChunkInput {
                ff_pts: ff_pts[a..b].to_vec(),
                ff_conf: ff_conf[a..b].to_vec(),
                geo_pts: geo_pts[a..b].to_vec(),
                geo_msk: geo_msk[a..b].to_vec(),
            },
            gt_pts: gt_pts[a..b].to_vec(),
            gt_msk: gt_msk[a..b].to_vec(),
        };
        chunk
            .validate()
            .map_err(|m| shard_err(format!("chunk {i}: {m}")))?;
        out.push(chunk);
    }
    Ok(out)
}

/// An opened chunk set (manifest only; shards are read by [`ChunkSet::load_split`]).
#[derive(Debug, Clone)]
pub struct ChunkSet {
    /// Directory.
    pub dir: PathBuf,
    /// Parsed manifest.
    pub manifest: Manifest,
}

impl ChunkSet {
    /// Opens `dir/manifest.json`.
    pub fn open(dir: &Path) -> Result<Self> {
        let path = dir.join(MANIFEST);
        let text = std::fs::read_to_string(&path).map_err(io_err(&path))?;
        let manifest: Manifest = serde_json::from_str(&text).map_err(|e| TrainError::Format {
            path: path.clone(),
            message: e.to_string(),
        })?;
        if manifest.format != FORMAT_NAME || manifest.version != FORMAT_VERSION {
            return Err(TrainError::Format {
                path,
                message: format!(
                    "format '{}' v{}, expected '{FORMAT_NAME}' v{FORMAT_VERSION}",
                    manifest.format, manifest.version
                ),
            });
        }
        Ok(Self {
            dir: dir.to_path_buf(),
            manifest,
        })
    }

    /// Reads, verifies (size, CRC-32, shapes, finiteness) and parses every shard of `split`.
    pub fn load_split(&self, split: Split) -> Result<Vec<TrainChunk>> {
        let mut out = Vec::new();
        for shard in self.manifest.shards.iter().filter(|s| s.split == split) {
            out.extend(self.load_shard(shard)?);
        }
        Ok(out)
    }

    /// Reads and verifies one shard.
    pub fn load_shard(&self, shard: &ShardEntry) -> Result<Vec<TrainChunk>> {
        let path = self.dir.join(&shard.file);
        // A mismatch is in the shard or in the manifest: the messages name both.
        let manifest = self.dir.join(MANIFEST);
        let m = manifest.display();
        let bytes = std::fs::read(&path).map_err(|e| TrainError::Shard {
            path: path.clone(),
            message: format!("cannot read the shard listed in {m}: {e}"),
        })?;
        if bytes.len() as u64 != shard.bytes {
            return Err(TrainError::Shard {
                path,
                message: format!(
                    "size {} bytes, {m} says {} (truncated or replaced shard, or edited manifest)",
                    bytes.len(),
                    shard.bytes
                ),
            });
        }
        let crc = crc32fast::hash(&bytes);
        if crc != shard.crc32 {
            return Err(TrainError::Shard {
                path,
                message: format!(
                    "CRC-32 {crc:08x}, {m} says {:08x} (corrupt shard or edited manifest)",
                    shard.crc32
                ),
            });
        }
        let chunks = parse_shard_owned(bytes, &path, self.manifest.scenes.len())?;
        if chunks.len() != shard.chunks {
            return Err(TrainError::Shard {
                path,
                message: format!("{} chunks, {m} says {}", chunks.len(), shard.chunks),
            });
        }
        Ok(chunks)
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A small deterministic chunk for tests.
    pub(crate) fn toy_chunk(scene: usize, k: usize, seed: u32) -> TrainChunk {
        TrainChunk::deterministic(scene, k, seed)
    }

    fn scene(name: &str, split: Split) -> SceneEntry {
        SceneEntry {
            name: name.into(),
            split,
            views: 2,
            height: 14,
            width: 14,
            metres_per_unit: 2.0,
            source: "test".into(),
        }
    }

    fn write_set(dir: &Path) -> (Vec<TrainChunk>, Vec<TrainChunk>) {
        let mut w = ChunkSetWriter::new(dir, 2, serde_json::json!({"test": true})).unwrap();
        let a = w.add_scene(scene("a", Split::Train));
        let b = w.add_scene(scene("b", Split::Val));
        let train: Vec<TrainChunk> = (0..5).map(|i| toy_chunk(a, 20 + i, i as u32)).collect();
        let val: Vec<TrainChunk> = (0..1).map(|i| toy_chunk(b, 30, 7 + i)).collect();
        for c in train.iter().chain(&val) {
            w.add_chunk(c.clone()).unwrap();
        }
        w.finish().unwrap();
        (train, val)
    }

    #[test]
    fn roundtrip_and_split_by_scene() {
        let dir = tempfile::tempdir().unwrap();
        let (train, val) = write_set(dir.path());
        let set = ChunkSet::open(dir.path()).unwrap();
        assert_eq!(
            set.manifest
                .shards
                .iter()
                .filter(|s| s.split == Split::Train)
                .count(),
            3
        );
        assert_eq!(set.load_split(Split::Train).unwrap(), train);
        assert_eq!(set.load_split(Split::Val).unwrap(), val);
    }

    #[test]
    fn corrupt_or_truncated_shard_is_an_error_naming_the_shard() {
        let dir = tempfile::tempdir().unwrap();
        write_set(dir.path());
        let set = ChunkSet::open(dir.path()).unwrap();
        let shard = dir.path().join("train-00001.safetensors");
        let good = std::fs::read(&shard).unwrap();
        // flipped byte in the payload
        let mut bad = good.clone();
        let n = bad.len();
        bad[n - 5] ^= 0x40;
        std::fs::write(&shard, &bad).unwrap();
        let msg = set.load_split(Split::Train).unwrap_err().to_string();
        assert!(
            msg.contains("train-00001.safetensors") && msg.contains("CRC-32"),
            "{msg}"
        );
        // truncated
        std::fs::write(&shard, &good[..good.len() / 2]).unwrap();
        let msg = set.load_split(Split::Train).unwrap_err().to_string();
        assert!(
            msg.contains("train-00001.safetensors") && msg.contains("truncated"),
            "{msg}"
        );
        // missing
        std::fs::remove_file(&shard).unwrap();
        let msg = set.load_split(Split::Train).unwrap_err().to_string();
        assert!(msg.contains("train-00001.safetensors"), "{msg}");
        // consistent checksum but inconsistent content (manifest edited): shape check names the shard
        let mut short = toy_chunk(0, 4, 1);
        short.ff_conf.pop();
        assert!(short.validate().is_err());
        let garbage = b"not a safetensors file at all".to_vec();
        let msg = parse_shard(&garbage, &shard, 2).unwrap_err().to_string();
        assert!(msg.contains("train-00001.safetensors"), "{msg}");
    }
}
