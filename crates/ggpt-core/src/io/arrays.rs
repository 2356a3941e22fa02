//! Named arrays with typed, validating getters, shared by the `.npz` readers (the `ggpt-infer`
//! scene folder, feed-forward outputs of VGGT / MapAnything / Pi3) and the Python binding,
//! which hands its numpy arrays over as [`NamedArrays`].

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use nalgebra::{Matrix3, Matrix3x4};

use crate::io::npy::{NpyArray, NpyData, read_npz};
use crate::{CoreError, Dims, Result};

/// Named arrays (an `.npz`, or the arrays of a Python dict) with typed, validating getters:
/// every error names the origin (a file, or a description such as `predictions`) and the key.
#[derive(Debug, Clone)]
pub struct NamedArrays {
    path: PathBuf,
    arrays: BTreeMap<String, NpyArray>,
}

impl NamedArrays {
    /// Reads an `.npz` file.
    pub fn open_npz(path: &Path) -> Result<Self> {
        Ok(Self {
            path: path.to_path_buf(),
            arrays: read_npz(path)?,
        })
    }

    /// Arrays from memory; `origin` names them in errors.
    pub fn new(origin: impl Into<PathBuf>, arrays: BTreeMap<String, NpyArray>) -> Self {
        Self {
            path: origin.into(),
            arrays,
        }
    }

    /// Where the arrays came from.
    pub fn origin(&self) -> &Path {
        &self.path
    }

    /// The keys, sorted.
    pub fn keys(&self) -> Vec<&str> {
        self.arrays.keys().map(String::as_str).collect()
    }

    /// The array `key`, if present.
    pub fn array(&self, key: &str) -> Option<&NpyArray> {
        self.arrays.get(key)
    }

    /// Changes the shape of `key` in place with `f` (no effect when absent); the caller keeps
    /// the number of values (the typed getters check it).
    pub fn reshape_with(&mut self, key: &str, f: impl FnOnce(&mut Vec<usize>)) {
        if let Some(a) = self.arrays.get_mut(key) {
            f(&mut a.shape);
        }
    }

    /// Removes `key`, returning its array.
    pub fn remove(&mut self, key: &str) -> Option<NpyArray> {
        self.arrays.remove(key)
    }

    /// Overwrites one f32 value (tests of the validation).
    #[cfg(test)]
    pub(crate) fn set_f32(&mut self, key: &str, index: usize, value: f32) {
        if let Some(NpyArray {
            data: NpyData::F32(v),
            ..
        }) = self.arrays.get_mut(key)
        {
            v[index] = value;
        }
    }

    /// Removes a leading batch dimension of extent 1 from every array whose rank is at least
    /// `min_rank[key]` + 1 (e.g. VGGT's `[1, S, H, W, 3]`); a leading batch of another extent is
    /// an error naming the key (ggpt-rs refines one scene at a time).
    pub fn squeeze_batch(&mut self, min_rank: &[(&str, usize)]) -> Result<()> {
        for &(key, rank) in min_rank {
            let path = self.path.clone();
            if let Some(a) = self.arrays.get_mut(key)
                && a.shape.len() == rank + 1
            {
                if a.shape[0] != 1 {
                    return Err(CoreError::format(
                        path,
                        key,
                        format!(
                            "shape {:?} has a leading batch of {}: give one scene (batch 1) at a time",
                            a.shape, a.shape[0]
                        ),
                    ));
                }
                a.shape.remove(0);
            }
        }
        Ok(())
    }
    /// A format error naming the origin and `key`.
    pub fn err(&self, key: &str, m: impl Into<String>) -> CoreError {
        CoreError::format(&self.path, key, m)
    }
    /// Whether `key` is present.
    pub fn has(&self, key: &str) -> bool {
        self.arrays.contains_key(key)
    }
    /// The array `key`, or an error naming it.
    pub fn get(&self, key: &str) -> Result<&NpyArray> {
        self.arrays
            .get(key)
            .ok_or_else(|| self.err(key, "missing array"))
    }
    /// The array `key` with exactly `shape`.
    pub fn shaped(&self, key: &str, shape: &[usize]) -> Result<&NpyArray> {
        let a = self.get(key)?;
        if a.shape != shape {
            return Err(self.err(
                key,
                format!("wrong shape {:?}, expected {shape:?}", a.shape),
            ));
        }
        Ok(a)
    }
    /// `<f4` only (point maps are stored as f32), finite.
    pub fn f32_exact(&self, key: &str, shape: &[usize]) -> Result<Vec<f32>> {
        let a = self.shaped(key, shape)?;
        let NpyData::F32(v) = &a.data else {
            return Err(self.err(key, format!("wrong dtype {}, expected <f4", a.data.descr())));
        };
        crate::io::st::check_finite_f32(&self.path, key, v)?;
        Ok(v.clone())
    }
    /// `<f4` or `<f8` as f64, finite.
    pub fn floats(&self, key: &str, shape: &[usize]) -> Result<Vec<f64>> {
        let a = self.shaped(key, shape)?;
        let v = a.to_f64().ok_or_else(|| {
            self.err(
                key,
                format!("wrong dtype {}, expected <f4 or <f8", a.data.descr()),
            )
        })?;
        crate::io::st::check_finite_f64(&self.path, key, &v)?;
        Ok(v)
    }
    /// `[n, 3, 4]` or `[n, 4, 4]` (last row `0 0 0 1`) matrices, `<f4` or `<f8`, finite.
    pub fn extrinsics(&self, key: &str, n: usize) -> Result<Vec<Matrix3x4<f64>>> {
        let four = self.get(key)?.shape == [n, 4, 4];
        if !four {
            let v = self.floats(key, &[n, 3, 4])?;
            return Ok(v.chunks_exact(12).map(Matrix3x4::from_row_slice).collect());
        }
        let v = self.floats(key, &[n, 4, 4])?;
        let mut out = Vec::with_capacity(n);
        for (i, m) in v.chunks_exact(16).enumerate() {
            if [m[12], m[13], m[14], m[15] - 1.0]
                .iter()
                .any(|x| x.abs() > 1e-6)
            {
                return Err(self.err(key, format!("view {i}: last row is not 0 0 0 1")));
            }
            out.push(Matrix3x4::from_row_slice(&m[..12]));
        }
        Ok(out)
    }
    /// `[n, 3, 3]` matrices, `<f4` or `<f8`, finite.
    pub fn intrinsics(&self, key: &str, n: usize) -> Result<Vec<Matrix3<f64>>> {
        Ok(self
            .floats(key, &[n, 3, 3])?
            .chunks_exact(9)
            .map(Matrix3::from_row_slice)
            .collect())
    }
    /// `|b1` values of `shape`.
    pub fn bools(&self, key: &str, shape: &[usize]) -> Result<Vec<bool>> {
        let a = self.shaped(key, shape)?;
        match &a.data {
            NpyData::Bool(v) => Ok(v.clone()),
            d => Err(self.err(key, format!("wrong dtype {}, expected |b1", d.descr()))),
        }
    }
    /// A one-element `|b1` array.
    pub fn scalar_bool(&self, key: &str) -> Result<bool> {
        let a = self.get(key)?;
        match (&a.data, a.shape.iter().product::<usize>()) {
            (NpyData::Bool(v), 1) => v.first().copied().ok_or_else(|| self.err(key, "empty")),
            _ => Err(self.err(
                key,
                format!(
                    "expected a bool scalar, found {} {:?}",
                    a.data.descr(),
                    a.shape
                ),
            )),
        }
    }
    /// `[N,h,w,3]` u8 (÷255) or f32 in [0, 1].
    pub fn images(&self, key: &str, d: Dims) -> Result<Vec<f32>> {
        let a = self.shaped(key, &[d.n, d.h, d.w, 3])?;
        match &a.data {
            NpyData::U8(v) => Ok(v.iter().map(|&b| f32::from(b) / 255.0).collect()),
            NpyData::F32(v) => {
                if let Some(i) = v.iter().position(|x| !(0.0..=1.0).contains(x)) {
                    return Err(self.err(
                        key,
                        format!("value {} at flat index {i} outside [0, 1]", v[i]),
                    ));
                }
                Ok(v.clone())
            }
            other => Err(self.err(
                key,
                format!("wrong dtype {}, expected |u1 or <f4", other.descr()),
            )),
        }
    }
}
