//! Minimal `torch.save` zip-pickle writer (pickle protocol 2 with the opcodes `torch.save`
//! emits, one stored zip entry per storage): a top-level dict of tensors and Python bools.
//!
//! It produces official-format files (`formats.md` §3: `gt.bin`, `ff_outputs.bin`,
//! `sfm_dlt_outputs.bin`; an official-key `.pth` state dict) without Python. The readers of those
//! files are tested against it (strided views, dtype conversion, malformed entries) and the
//! `ggpt-fuzz` harness builds its seeds with it. Hand-written because no maintained Rust crate
//! writes torch pickles (`pytorch-reader`, Burn's, only reads them).

use std::io::Write;
use std::path::Path;

use crate::io::atomic::write_bytes_atomic;
use crate::{CoreError, Result};

/// One value of the top-level dict.
#[derive(Debug, Clone, PartialEq)]
pub enum TorchValue {
    /// A tensor view of its own storage: storage type (`FloatStorage`, `BoolStorage`, ...),
    /// storage bytes (little-endian), storage numel, element offset, size, stride.
    Tensor {
        /// Storage type (`FloatStorage`, `BoolStorage`, ...).
        storage: &'static str,
        /// Storage bytes, little-endian.
        bytes: Vec<u8>,
        /// Elements in the storage.
        numel: usize,
        /// Element offset of the view in the storage.
        offset: usize,
        /// Shape of the view.
        size: Vec<usize>,
        /// Strides of the view, in elements.
        stride: Vec<usize>,
    },
    /// A Python bool.
    Bool(bool),
}

impl TorchValue {
    /// Contiguous f32 tensor of shape `size` (`values.len()` must be its element count).
    pub fn f32(values: &[f32], size: &[usize]) -> Self {
        TorchValue::Tensor {
            storage: "FloatStorage",
            bytes: values.iter().flat_map(|x| x.to_le_bytes()).collect(),
            numel: values.len(),
            offset: 0,
            size: size.to_vec(),
            stride: contiguous_strides(size),
        }
    }

    /// Contiguous bool tensor of shape `size`.
    pub fn bool(values: &[bool], size: &[usize]) -> Self {
        TorchValue::Tensor {
            storage: "BoolStorage",
            bytes: values.iter().map(|&b| u8::from(b)).collect(),
            numel: values.len(),
            offset: 0,
            size: size.to_vec(),
            stride: contiguous_strides(size),
        }
    }
}

/// Row-major strides (in elements) of `size`.
pub fn contiguous_strides(size: &[usize]) -> Vec<usize> {
    let mut s = vec![1; size.len()];
    for d in (0..size.len().saturating_sub(1)).rev() {
        s[d] = s[d + 1] * size[d + 1];
    }
    s
}

fn unicode(p: &mut Vec<u8>, s: &str) -> Result<()> {
    let len = u32::try_from(s.len())
        .map_err(|_| CoreError::Invalid(format!("pickle string of {} bytes", s.len())))?;
    p.push(b'X');
    p.extend_from_slice(&len.to_le_bytes());
    p.extend_from_slice(s.as_bytes());
    Ok(())
}

fn int(p: &mut Vec<u8>, v: usize) -> Result<()> {
    let v = i32::try_from(v)
        .map_err(|_| CoreError::Invalid(format!("pickle integer {v} does not fit BININT")))?;
    p.push(b'J');
    p.extend_from_slice(&v.to_le_bytes());
    Ok(())
}

fn tuple(p: &mut Vec<u8>, v: &[usize]) -> Result<()> {
    p.push(b'(');
    for &x in v {
        int(p, x)?;
    }
    p.push(b't');
    Ok(())
}

/// The torch zip archive of `entries` (dict order kept), with archive folder `stem` (what
/// `torch.save` names after the file stem).
pub fn torch_zip_bytes(stem: &str, entries: &[(&str, TorchValue)]) -> Result<Vec<u8>> {
    let mut p = vec![0x80, 2, b'}', b'('];
    let mut storages: Vec<&[u8]> = Vec::new();
    for (key, v) in entries {
        unicode(&mut p, key)?;
        match v {
            TorchValue::Bool(b) => p.push(if *b { 0x88 } else { 0x89 }),
            TorchValue::Tensor {
                storage,
                bytes,
                numel,
                offset,
                size,
                stride,
            } => {
                let id = storages.len();
                storages.push(bytes);
                p.extend_from_slice(b"ctorch._utils\n_rebuild_tensor_v2\n(");
                p.push(b'(');
                unicode(&mut p, "storage")?;
                p.extend_from_slice(format!("ctorch\n{storage}\n").as_bytes());
                unicode(&mut p, &id.to_string())?;
                unicode(&mut p, "cpu")?;
                int(&mut p, *numel)?;
                p.extend_from_slice(b"tQ");
                int(&mut p, *offset)?;
                tuple(&mut p, size)?;
                tuple(&mut p, stride)?;
                p.push(0x89);
                p.extend_from_slice(b"ccollections\nOrderedDict\n)R");
                p.extend_from_slice(b"tR");
            }
        }
    }
    p.extend_from_slice(b"u.");
    let zip_err = |e: zip::result::ZipError| CoreError::Invalid(format!("torch zip: {e}"));
    let io_err = |e: std::io::Error| CoreError::Invalid(format!("torch zip: {e}"));
    let mut zw = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let opts =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    zw.start_file(format!("{stem}/data.pkl"), opts)
        .map_err(zip_err)?;
    zw.write_all(&p).map_err(io_err)?;
    zw.start_file(format!("{stem}/byteorder"), opts)
        .map_err(zip_err)?;
    zw.write_all(b"little").map_err(io_err)?;
    for (i, s) in storages.iter().enumerate() {
        zw.start_file(format!("{stem}/data/{i}"), opts)
            .map_err(zip_err)?;
        zw.write_all(s).map_err(io_err)?;
    }
    zw.start_file(format!("{stem}/version"), opts)
        .map_err(zip_err)?;
    zw.write_all(b"3\n").map_err(io_err)?;
    Ok(zw.finish().map_err(zip_err)?.into_inner())
}

/// Writes `entries` as a torch zip at `path` (archive folder named after the file stem),
/// atomically.
pub fn write_torch_zip(path: &Path, entries: &[(&str, TorchValue)]) -> Result<()> {
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .ok_or_else(|| CoreError::format(path, "", "no file name"))?;
    write_bytes_atomic(path, &torch_zip_bytes(&stem, entries)?)
}
