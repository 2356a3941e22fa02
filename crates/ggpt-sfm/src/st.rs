//! Small typed reader / writer helpers over the `safetensors` crate (used by the input readers,
//! the output writer and the fixture tests). Errors name the file, the tensor key and the problem.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use safetensors::{Dtype, SafeTensors};

use crate::error::{Result, SfmError};

/// A deserialised safetensors file (owning its bytes) with typed accessors.
pub struct StFile {
    path: PathBuf,
    bytes: Vec<u8>,
}

/// One tensor converted to a common element type, with its shape.
#[derive(Debug, Clone, PartialEq)]
pub struct Tensor<T> {
    /// Shape (row-major).
    pub shape: Vec<usize>,
    /// Values in row-major order.
    pub data: Vec<T>,
}

impl StFile {
    /// Reads and validates the header of `path`.
    pub fn open(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| SfmError::Io { path: path.to_path_buf(), source: e })?;
        SafeTensors::deserialize(&bytes).map_err(|e| SfmError::format(path, "", format!("not a safetensors file: {e}")))?;
        Ok(StFile { path: path.to_path_buf(), bytes })
    }

    /// The file path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn st(&self) -> Result<SafeTensors<'_>> {
        SafeTensors::deserialize(&self.bytes).map_err(|e| SfmError::format(&self.path, "", format!("not a safetensors file: {e}")))
    }

    /// True when the file holds tensor `key`.
    pub fn has(&self, key: &str) -> bool {
        self.st().map(|st| st.tensor(key).is_ok()).unwrap_or(false)
    }

    /// All tensor names.
    pub fn names(&self) -> Vec<String> {
        self.st().map(|st| st.names().into_iter().map(|s| s.to_string()).collect()).unwrap_or_default()
    }

    /// The `__metadata__` map (empty when absent).
    pub fn metadata(&self) -> HashMap<String, String> {
        SafeTensors::read_metadata(&self.bytes)
            .ok()
            .and_then(|(_, m)| m.metadata().clone())
            .unwrap_or_default()
    }

    fn raw(&self, key: &str) -> Result<(Dtype, Vec<usize>, Vec<u8>)> {
        let st = self.st()?;
        let view = st.tensor(key).map_err(|e| SfmError::format(&self.path, key, format!("missing tensor: {e}")))?;
        Ok((view.dtype(), view.shape().to_vec(), view.data().to_vec()))
    }

    /// Tensor `key` as f32 (accepts F32, F64 (rounded), F16/BF16 are rejected).
    pub fn f32(&self, key: &str) -> Result<Tensor<f32>> {
        let (dt, shape, b) = self.raw(key)?;
        let data = match dt {
            Dtype::F32 => b.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect(),
            Dtype::F64 => b
                .chunks_exact(8)
                .map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]) as f32)
                .collect(),
            other => return Err(SfmError::format(&self.path, key, format!("expected F32 or F64, found {other:?}"))),
        };
        Ok(Tensor { shape, data })
    }

    /// Tensor `key` as f64 (accepts F64 and F32 (widened)).
    pub fn f64(&self, key: &str) -> Result<Tensor<f64>> {
        let (dt, shape, b) = self.raw(key)?;
        let data = match dt {
            Dtype::F64 => b
                .chunks_exact(8)
                .map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
                .collect(),
            Dtype::F32 => b.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64).collect(),
            other => return Err(SfmError::format(&self.path, key, format!("expected F64 or F32, found {other:?}"))),
        };
        Ok(Tensor { shape, data })
    }

    /// Tensor `key` as i64 (accepts I64, I32, U8, I8, BOOL).
    pub fn i64(&self, key: &str) -> Result<Tensor<i64>> {
        let (dt, shape, b) = self.raw(key)?;
        let data = match dt {
            Dtype::I64 => b
                .chunks_exact(8)
                .map(|c| i64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
                .collect(),
            Dtype::I32 => b.chunks_exact(4).map(|c| i32::from_le_bytes([c[0], c[1], c[2], c[3]]) as i64).collect(),
            Dtype::U8 | Dtype::BOOL => b.iter().map(|&v| v as i64).collect(),
            Dtype::I8 => b.iter().map(|&v| v as i8 as i64).collect(),
            other => return Err(SfmError::format(&self.path, key, format!("expected an integer dtype, found {other:?}"))),
        };
        Ok(Tensor { shape, data })
    }

    /// Tensor `key` as bool (accepts BOOL and U8; nonzero = true).
    pub fn bool(&self, key: &str) -> Result<Tensor<bool>> {
        let (dt, shape, b) = self.raw(key)?;
        match dt {
            Dtype::BOOL | Dtype::U8 => Ok(Tensor { shape, data: b.iter().map(|&v| v != 0).collect() }),
            other => Err(SfmError::format(&self.path, key, format!("expected BOOL, found {other:?}"))),
        }
    }

    /// Checks that tensor `t` of key `key` has shape `want`.
    pub fn expect_shape<T>(&self, key: &str, t: &Tensor<T>, want: &[usize]) -> Result<()> {
        if t.shape != want {
            return Err(SfmError::format(&self.path, key, format!("shape {:?}, expected {:?}", t.shape, want)));
        }
        Ok(())
    }
}

/// One tensor to write: name, dtype, shape and little-endian bytes.
pub struct OutTensor {
    /// Tensor name.
    pub name: String,
    /// Element type.
    pub dtype: Dtype,
    /// Shape.
    pub shape: Vec<usize>,
    /// Little-endian bytes.
    pub bytes: Vec<u8>,
}

impl OutTensor {
    /// An F32 tensor.
    pub fn f32(name: &str, shape: Vec<usize>, v: &[f32]) -> Self {
        OutTensor { name: name.into(), dtype: Dtype::F32, shape, bytes: v.iter().flat_map(|x| x.to_le_bytes()).collect() }
    }
    /// An F64 tensor.
    pub fn f64(name: &str, shape: Vec<usize>, v: &[f64]) -> Self {
        OutTensor { name: name.into(), dtype: Dtype::F64, shape, bytes: v.iter().flat_map(|x| x.to_le_bytes()).collect() }
    }
    /// A BOOL tensor.
    pub fn bool(name: &str, shape: Vec<usize>, v: &[bool]) -> Self {
        OutTensor { name: name.into(), dtype: Dtype::BOOL, shape, bytes: v.iter().map(|&b| b as u8).collect() }
    }
    /// A U16 tensor.
    pub fn u16(name: &str, shape: Vec<usize>, v: &[u16]) -> Self {
        OutTensor { name: name.into(), dtype: Dtype::U16, shape, bytes: v.iter().flat_map(|x| x.to_le_bytes()).collect() }
    }
}

/// Serialises tensors (and optional metadata) to safetensors bytes.
pub fn serialize(tensors: &[OutTensor], metadata: Option<HashMap<String, String>>) -> Result<Vec<u8>> {
    let mut views = Vec::with_capacity(tensors.len());
    for t in tensors {
        let v = safetensors::tensor::TensorView::new(t.dtype, t.shape.clone(), &t.bytes)
            .map_err(|e| SfmError::Invalid(format!("tensor {}: {e}", t.name)))?;
        views.push((t.name.clone(), v));
    }
    safetensors::tensor::serialize(views, metadata).map_err(|e| SfmError::Invalid(format!("safetensors serialisation: {e}")))
}
