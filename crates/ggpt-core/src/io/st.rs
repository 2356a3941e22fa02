//! Small safetensors helpers shared by the readers and writers of this module (`formats.md` §1.2):
//! a typed, validating reader ([`StFile`]) whose errors name the file, the tensor key and the
//! problem, and an owned-tensor writer ([`StWriter`]).

use std::borrow::Cow;
use std::collections::HashMap;
use std::ops::Range;
use std::path::{Path, PathBuf};

use nalgebra::{Matrix3, Matrix3x4};
pub use safetensors::Dtype;
use safetensors::{SafeTensors, View};

use crate::{CoreError, Result};

/// Shape, dtype and byte range (into [`StFile::bytes`]) of one tensor.
#[derive(Debug, Clone)]
struct Entry {
    dtype: Dtype,
    shape: Vec<usize>,
    range: Range<usize>,
}

/// A parsed safetensors file held in memory.
#[derive(Debug)]
pub struct StFile {
    path: PathBuf,
    bytes: Vec<u8>,
    entries: HashMap<String, Entry>,
    metadata: HashMap<String, String>,
}

impl StFile {
    /// Reads and parses `path`; a truncated or malformed file is an error naming the file.
    pub fn open(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| CoreError::io(path, e))?;
        Self::from_bytes(path, bytes)
    }

    /// Parses an in-memory safetensors buffer (`path` is used in error messages only).
    pub fn from_bytes(path: &Path, bytes: Vec<u8>) -> Result<Self> {
        let (n, meta) = SafeTensors::read_metadata(&bytes).map_err(|e| {
            CoreError::format(
                path,
                "",
                format!("not a valid safetensors file (truncated or corrupt?): {e}"),
            )
        })?;
        let start = 8 + n;
        let mut entries = HashMap::new();
        for (name, info) in meta.tensors() {
            let (b, e) = info.data_offsets;
            entries.insert(
                name,
                Entry {
                    dtype: info.dtype,
                    shape: info.shape.clone(),
                    range: start + b..start + e,
                },
            );
        }
        let metadata = meta.metadata().clone().unwrap_or_default();
        Ok(Self {
            path: path.to_path_buf(),
            bytes,
            entries,
            metadata,
        })
    }

    /// The file path (for error messages).
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The `__metadata__` string map (empty when absent).
    pub fn metadata(&self) -> &HashMap<String, String> {
        &self.metadata
    }

    /// Names of all tensors, sorted.
    pub fn keys(&self) -> Vec<String> {
        let mut k: Vec<String> = self.entries.keys().cloned().collect();
        k.sort();
        k
    }

    /// True when the file holds a tensor named `key`.
    pub fn has(&self, key: &str) -> bool {
        self.entries.contains_key(key)
    }

    /// Shape of tensor `key` (error when missing).
    pub fn shape(&self, key: &str) -> Result<&[usize]> {
        Ok(&self.entry(key)?.shape)
    }

    /// Dtype of tensor `key` (error when missing).
    pub fn dtype(&self, key: &str) -> Result<Dtype> {
        Ok(self.entry(key)?.dtype)
    }

    /// Error naming this file and `key`.
    pub fn err(&self, key: &str, message: impl Into<String>) -> CoreError {
        CoreError::format(&self.path, key, message)
    }

    fn entry(&self, key: &str) -> Result<&Entry> {
        self.entries
            .get(key)
            .ok_or_else(|| self.err(key, "missing tensor"))
    }

    /// Raw bytes of `key` after checking its dtype and (when given) its exact shape.
    fn raw(&self, key: &str, dtype: Dtype, shape: Option<&[usize]>) -> Result<&[u8]> {
        let e = self.entry(key)?;
        if e.dtype != dtype {
            return Err(self.err(
                key,
                format!("wrong dtype {:?}, expected {dtype:?}", e.dtype),
            ));
        }
        if let Some(s) = shape
            && e.shape != s
        {
            return Err(self.err(key, format!("wrong shape {:?}, expected {s:?}", e.shape)));
        }
        self.bytes
            .get(e.range.clone())
            .ok_or_else(|| self.err(key, "data range outside the file"))
    }

    /// Dtype, shape and raw little-endian bytes of tensor `key`.
    pub fn tensor(&self, key: &str) -> Result<(Dtype, &[usize], &[u8])> {
        let e = self.entry(key)?;
        let b = self
            .bytes
            .get(e.range.clone())
            .ok_or_else(|| self.err(key, "data range outside the file"))?;
        Ok((e.dtype, &e.shape, b))
    }

    /// `F32` tensor `key` of exactly `shape` (row-major values).
    pub fn f32(&self, key: &str, shape: &[usize]) -> Result<Vec<f32>> {
        Ok(le_f32(self.raw(key, Dtype::F32, Some(shape))?))
    }

    /// `F64` tensor `key` of exactly `shape`.
    pub fn f64(&self, key: &str, shape: &[usize]) -> Result<Vec<f64>> {
        Ok(le_f64(self.raw(key, Dtype::F64, Some(shape))?))
    }

    /// `I64` tensor `key` of exactly `shape`.
    pub fn i64(&self, key: &str, shape: &[usize]) -> Result<Vec<i64>> {
        Ok(le_i64(self.raw(key, Dtype::I64, Some(shape))?))
    }

    /// `U8` tensor `key` of exactly `shape`.
    pub fn u8(&self, key: &str, shape: &[usize]) -> Result<Vec<u8>> {
        Ok(self.raw(key, Dtype::U8, Some(shape))?.to_vec())
    }

    /// `BOOL` tensor `key` of exactly `shape`; bytes other than 0 / 1 are an error.
    pub fn bool(&self, key: &str, shape: &[usize]) -> Result<Vec<bool>> {
        let raw = self.raw(key, Dtype::BOOL, Some(shape))?;
        raw.iter()
            .enumerate()
            .map(|(i, &b)| match b {
                0 => Ok(false),
                1 => Ok(true),
                _ => Err(self.err(
                    key,
                    format!("bool byte {b} at flat index {i} (must be 0 or 1)"),
                )),
            })
            .collect()
    }

    /// 0-d `BOOL` tensor `key`.
    pub fn scalar_bool(&self, key: &str) -> Result<bool> {
        let v = self.bool(key, &[])?;
        v.first()
            .copied()
            .ok_or_else(|| self.err(key, "empty scalar"))
    }

    /// `F32` tensor checked for shape and finiteness.
    pub fn f32_finite(&self, key: &str, shape: &[usize]) -> Result<Vec<f32>> {
        let v = self.f32(key, shape)?;
        check_finite_f32(&self.path, key, &v)?;
        Ok(v)
    }

    /// `[n, 3, 4]` `F64` extrinsics, finite.
    pub fn extrinsics_f64(&self, key: &str, n: usize) -> Result<Vec<Matrix3x4<f64>>> {
        let v = self.f64(key, &[n, 3, 4])?;
        check_finite_f64(&self.path, key, &v)?;
        Ok(v.chunks_exact(12).map(Matrix3x4::from_row_slice).collect())
    }

    /// `[n, 3, 3]` `F64` intrinsics, finite.
    pub fn intrinsics_f64(&self, key: &str, n: usize) -> Result<Vec<Matrix3<f64>>> {
        let v = self.f64(key, &[n, 3, 3])?;
        check_finite_f64(&self.path, key, &v)?;
        Ok(v.chunks_exact(9).map(Matrix3::from_row_slice).collect())
    }

    /// Error naming this file and `key` for a dtype outside `accepted`.
    fn dtype_err(&self, key: &str, accepted: &str, found: Dtype) -> CoreError {
        self.err(key, format!("expected {accepted}, found {found:?}"))
    }

    /// Tensor `key` of any shape converted to `f32`: `F32` as stored, `F64` rounded to `f32`;
    /// other dtypes are an error. Check the shape with [`StFile::expect_shape`].
    pub fn f32_tensor(&self, key: &str) -> Result<Tensor<f32>> {
        let (dtype, shape, b) = self.tensor(key)?;
        let data = match dtype {
            Dtype::F32 => le_f32(b),
            Dtype::F64 => le_f64(b).into_iter().map(|v| v as f32).collect(),
            other => return Err(self.dtype_err(key, "F32 or F64", other)),
        };
        Ok(Tensor::new(shape, data))
    }

    /// Tensor `key` of any shape converted to `f64`: `F64` as stored, `F32` widened; other
    /// dtypes are an error.
    pub fn f64_tensor(&self, key: &str) -> Result<Tensor<f64>> {
        let (dtype, shape, b) = self.tensor(key)?;
        let data = match dtype {
            Dtype::F64 => le_f64(b),
            Dtype::F32 => le_f32(b).into_iter().map(f64::from).collect(),
            other => return Err(self.dtype_err(key, "F64 or F32", other)),
        };
        Ok(Tensor::new(shape, data))
    }

    /// Tensor `key` of any shape converted to `i64`: `I64`, `I32`, `U8`, `I8` and `BOOL`;
    /// other dtypes are an error.
    pub fn i64_tensor(&self, key: &str) -> Result<Tensor<i64>> {
        let (dtype, shape, b) = self.tensor(key)?;
        let data = match dtype {
            Dtype::I64 => le_i64(b),
            Dtype::I32 => b
                .chunks_exact(4)
                .map(|c| i64::from(i32::from_le_bytes([c[0], c[1], c[2], c[3]])))
                .collect(),
            Dtype::U8 | Dtype::BOOL => b.iter().map(|&v| i64::from(v)).collect(),
            Dtype::I8 => b.iter().map(|&v| i64::from(v as i8)).collect(),
            other => return Err(self.dtype_err(key, "an integer dtype", other)),
        };
        Ok(Tensor::new(shape, data))
    }

    /// Tensor `key` of any shape as booleans: `BOOL` or `U8`, nonzero = true; other dtypes are
    /// an error.
    pub fn bool_tensor(&self, key: &str) -> Result<Tensor<bool>> {
        let (dtype, shape, b) = self.tensor(key)?;
        match dtype {
            Dtype::BOOL | Dtype::U8 => Ok(Tensor::new(shape, b.iter().map(|&v| v != 0).collect())),
            other => Err(self.dtype_err(key, "BOOL", other)),
        }
    }

    /// Mask tensor `key` of any shape: `BOOL`, `U8`, `I32`, `I64` or `F32`, nonzero = true (the
    /// mask convention of the chunk-record and training-case inputs, [`mask_values`]).
    pub fn mask_tensor(&self, key: &str) -> Result<Tensor<bool>> {
        let (dtype, shape, b) = self.tensor(key)?;
        let data = mask_values(dtype, b)
            .ok_or_else(|| self.err(key, format!("unsupported mask dtype {dtype:?}")))?;
        Ok(Tensor::new(shape, data))
    }

    /// Checks that tensor `t`, read from `key`, has shape `want` (error naming file and key).
    pub fn expect_shape<T>(&self, key: &str, t: &Tensor<T>, want: &[usize]) -> Result<()> {
        if t.shape != want {
            return Err(self.err(key, format!("shape {:?}, expected {want:?}", t.shape)));
        }
        Ok(())
    }
}

/// One tensor converted to a common element type, with its shape (the dtype-converting getters
/// [`StFile::f32_tensor`], [`StFile::f64_tensor`], [`StFile::i64_tensor`],
/// [`StFile::bool_tensor`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Tensor<T> {
    /// Shape (row-major).
    pub shape: Vec<usize>,
    /// Values in row-major order.
    pub data: Vec<T>,
}

impl<T> Tensor<T> {
    fn new(shape: &[usize], data: Vec<T>) -> Self {
        Self {
            shape: shape.to_vec(),
            data,
        }
    }
}

/// Little-endian `f32` values of a byte slice (a trailing partial element is ignored).
pub fn le_f32(b: &[u8]) -> Vec<f32> {
    b.chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// Little-endian `f64` values of a byte slice.
pub fn le_f64(b: &[u8]) -> Vec<f64> {
    b.chunks_exact(8)
        .map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
        .collect()
}

/// Little-endian `i64` values of a byte slice.
pub fn le_i64(b: &[u8]) -> Vec<i64> {
    b.chunks_exact(8)
        .map(|c| i64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
        .collect()
}

/// Mask values of raw little-endian tensor bytes, nonzero = true: `BOOL` / `U8` bytes, `I32`,
/// `I64` or `F32` elements; `None` for any other dtype.
pub fn mask_values(dtype: Dtype, b: &[u8]) -> Option<Vec<bool>> {
    Some(match dtype {
        Dtype::BOOL | Dtype::U8 => b.iter().map(|&v| v != 0).collect(),
        Dtype::I32 => b
            .chunks_exact(4)
            .map(|c| i32::from_le_bytes([c[0], c[1], c[2], c[3]]) != 0)
            .collect(),
        Dtype::I64 => b
            .chunks_exact(8)
            .map(|c| c.iter().any(|&x| x != 0))
            .collect(),
        Dtype::F32 => le_f32(b).into_iter().map(|v| v != 0.0).collect(),
        _ => return None,
    })
}

/// Error naming `path` and `key` at the first non-finite value.
pub fn check_finite_f32(path: &Path, key: &str, v: &[f32]) -> Result<()> {
    match v.iter().position(|x| !x.is_finite()) {
        Some(index) => Err(CoreError::NonFinite {
            path: path.to_path_buf(),
            key: key.to_string(),
            index,
            value: f64::from(v[index]),
        }),
        None => Ok(()),
    }
}

/// Error naming `path` and `key` at the first non-finite value.
pub fn check_finite_f64(path: &Path, key: &str, v: &[f64]) -> Result<()> {
    match v.iter().position(|x| !x.is_finite()) {
        Some(index) => Err(CoreError::NonFinite {
            path: path.to_path_buf(),
            key: key.to_string(),
            index,
            value: v[index],
        }),
        None => Ok(()),
    }
}

/// One owned tensor for [`StWriter`].
struct Owned {
    dtype: Dtype,
    shape: Vec<usize>,
    data: Vec<u8>,
}

impl View for &Owned {
    fn dtype(&self) -> Dtype {
        self.dtype
    }
    fn shape(&self) -> &[usize] {
        &self.shape
    }
    fn data(&self) -> Cow<'_, [u8]> {
        Cow::Borrowed(&self.data)
    }
    fn data_len(&self) -> usize {
        self.data.len()
    }
}

/// Collects tensors and serialises them as one safetensors buffer.
#[derive(Default)]
pub struct StWriter {
    tensors: Vec<(String, Owned)>,
}

impl StWriter {
    /// Empty writer.
    pub fn new() -> Self {
        Self::default()
    }

    fn push(&mut self, name: &str, dtype: Dtype, shape: &[usize], data: Vec<u8>) {
        self.tensors.push((
            name.to_string(),
            Owned {
                dtype,
                shape: shape.to_vec(),
                data,
            },
        ));
    }

    /// Adds a tensor from raw little-endian bytes (the caller guarantees size = numel x dtype size).
    pub fn raw(&mut self, name: &str, dtype: Dtype, shape: &[usize], data: Vec<u8>) {
        self.push(name, dtype, shape, data);
    }

    /// Adds an `F32` tensor.
    pub fn f32(&mut self, name: &str, shape: &[usize], v: &[f32]) {
        self.push(
            name,
            Dtype::F32,
            shape,
            v.iter().flat_map(|x| x.to_le_bytes()).collect(),
        );
    }

    /// Adds an `F64` tensor.
    pub fn f64(&mut self, name: &str, shape: &[usize], v: &[f64]) {
        self.push(
            name,
            Dtype::F64,
            shape,
            v.iter().flat_map(|x| x.to_le_bytes()).collect(),
        );
    }

    /// Adds an `I64` tensor.
    pub fn i64(&mut self, name: &str, shape: &[usize], v: &[i64]) {
        self.push(
            name,
            Dtype::I64,
            shape,
            v.iter().flat_map(|x| x.to_le_bytes()).collect(),
        );
    }

    /// Adds a `U16` tensor.
    pub fn u16(&mut self, name: &str, shape: &[usize], v: &[u16]) {
        self.push(
            name,
            Dtype::U16,
            shape,
            v.iter().flat_map(|x| x.to_le_bytes()).collect(),
        );
    }

    /// Adds a `U8` tensor.
    pub fn u8(&mut self, name: &str, shape: &[usize], v: &[u8]) {
        self.push(name, Dtype::U8, shape, v.to_vec());
    }

    /// Adds a `BOOL` tensor (one byte per value).
    pub fn bool(&mut self, name: &str, shape: &[usize], v: &[bool]) {
        self.push(
            name,
            Dtype::BOOL,
            shape,
            v.iter().map(|&b| u8::from(b)).collect(),
        );
    }

    /// Adds `[n, 3, 4]` `F64` extrinsics (row-major).
    pub fn extrinsics(&mut self, name: &str, m: &[Matrix3x4<f64>]) {
        let v: Vec<f64> = m
            .iter()
            .flat_map(|m| m.transpose().iter().copied().collect::<Vec<_>>())
            .collect();
        self.f64(name, &[m.len(), 3, 4], &v);
    }

    /// Adds `[n, 3, 3]` `F64` intrinsics (row-major).
    pub fn intrinsics(&mut self, name: &str, m: &[Matrix3<f64>]) {
        let v: Vec<f64> = m
            .iter()
            .flat_map(|m| m.transpose().iter().copied().collect::<Vec<_>>())
            .collect();
        self.f64(name, &[m.len(), 3, 3], &v);
    }

    /// Serialises all tensors with the given `__metadata__` (`path` names errors). A tensor whose
    /// byte count is not its element count times its dtype size is an error naming it.
    pub fn finish(self, path: &Path, metadata: Option<HashMap<String, String>>) -> Result<Vec<u8>> {
        for (name, t) in &self.tensors {
            let bits = t.shape.iter().product::<usize>() * t.dtype.bitsize();
            if bits.div_ceil(8) != t.data.len() {
                return Err(CoreError::format(
                    path,
                    name.as_str(),
                    format!(
                        "{} bytes for a {:?} tensor of shape {:?}",
                        t.data.len(),
                        t.dtype,
                        t.shape
                    ),
                ));
            }
        }
        let views: Vec<(String, &Owned)> =
            self.tensors.iter().map(|(n, t)| (n.clone(), t)).collect();
        safetensors::serialize(views, metadata)
            .map_err(|e| CoreError::format(path, "", format!("cannot serialise safetensors: {e}")))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn roundtrip_and_errors_name_key() {
        let p = Path::new("x.safetensors");
        let mut w = StWriter::new();
        w.f32("a", &[2, 2], &[1.0, 2.0, 3.0, f32::NAN]);
        w.bool("b", &[], &[true]);
        let bytes = w.finish(p, None).unwrap();
        let f = StFile::from_bytes(p, bytes.clone()).unwrap();
        assert_eq!(f.f32("a", &[2, 2]).unwrap()[..3], [1.0, 2.0, 3.0]);
        assert!(f.scalar_bool("b").unwrap());
        let e = f.f32_finite("a", &[2, 2]).unwrap_err().to_string();
        assert!(
            e.contains("x.safetensors") && e.contains("[a]") && e.contains("non-finite"),
            "{e}"
        );
        let e = f.f32("a", &[4]).unwrap_err().to_string();
        assert!(e.contains("[a]") && e.contains("shape"), "{e}");
        let e = f.f64("a", &[2, 2]).unwrap_err().to_string();
        assert!(e.contains("[a]") && e.contains("dtype"), "{e}");
        let e = f.f32("zz", &[1]).unwrap_err().to_string();
        assert!(e.contains("[zz]") && e.contains("missing"), "{e}");
        let e = StFile::from_bytes(p, bytes[..bytes.len() - 3].to_vec())
            .unwrap_err()
            .to_string();
        assert!(e.contains("x.safetensors"), "{e}");
    }
}
