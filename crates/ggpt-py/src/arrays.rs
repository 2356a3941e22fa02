//! numpy in and out. In: any numpy array of float32 / float64 / uint8 / bool / int32 / int64
//! (any memory layout; read in C order) becomes an [`NpyArray`], copied once. Out: a `Vec` is
//! handed to numpy without a copy (`PyArray::from_vec`) and reshaped.

use ggpt_core::io::npy::{NpyArray, NpyData};
use nalgebra::{Matrix3, Matrix3x4};
use numpy::{PyArray1, PyArrayDyn, PyArrayMethods};
use pyo3::prelude::*;

use crate::errors::invalid;

/// `obj` as a numpy array: numpy arrays as they are, torch tensors through
/// `.detach().cpu().numpy()` (without importing torch), anything else through `numpy.asarray`.
pub fn as_numpy<'py>(obj: &Bound<'py, PyAny>, name: &str) -> PyResult<Bound<'py, PyAny>> {
    let py = obj.py();
    if obj.cast::<numpy::PyUntypedArray>().is_ok() {
        return Ok(obj.clone());
    }
    let converted = if obj.hasattr("detach")? && obj.hasattr("cpu")? {
        obj.call_method0("detach")?
            .call_method0("cpu")?
            .call_method0("numpy")
    } else {
        py.import("numpy")?.call_method1("asarray", (obj,))
    };
    converted.map_err(|e| {
        invalid(format!(
            "{name}: cannot be read as a numpy array ({e}); give a float32 numpy array"
        ))
    })
}

/// Copies a numpy array (or a torch tensor, see [`as_numpy`]) into an [`NpyArray`]; `name`
/// names it in errors.
pub fn to_npy(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<NpyArray> {
    let obj = &as_numpy(obj, name)?;
    macro_rules! try_dtype {
        ($t:ty, $variant:ident) => {
            if let Ok(a) = obj.cast::<PyArrayDyn<$t>>() {
                let ro = a.readonly();
                let view = ro.as_array();
                let shape = view.shape().to_vec();
                let data: Vec<$t> = view.iter().copied().collect();
                return NpyArray::new(shape, NpyData::$variant(data))
                    .map_err(|e| invalid(format!("{name}: {e}")));
            }
        };
    }
    try_dtype!(f32, F32);
    try_dtype!(f64, F64);
    try_dtype!(u8, U8);
    try_dtype!(bool, Bool);
    try_dtype!(i32, I32);
    try_dtype!(i64, I64);
    let described = obj
        .getattr("dtype")
        .map(|d| d.to_string())
        .unwrap_or_else(|_| obj.get_type().to_string());
    Err(invalid(format!(
        "{name}: expected a numpy array of float32, float64, uint8 or bool, got {described}"
    )))
}

/// Float values of `obj` as f32 (f64 rounded) with their shape (one copy out of numpy).
pub fn f32_values(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<(Vec<usize>, Vec<f32>)> {
    let a = to_npy(obj, name)?;
    let shape = a.shape.clone();
    let v = a.into_f32().map_err(|a| {
        invalid(format!(
            "{name}: expected float32 or float64, got {}",
            a.data.descr()
        ))
    })?;
    Ok((shape, v))
}

/// A `Vec` as a numpy array of `shape` (no copy of the values).
pub fn array<'py, T: numpy::Element>(
    py: Python<'py>,
    values: Vec<T>,
    shape: &[usize],
) -> PyResult<Bound<'py, PyAny>> {
    Ok(PyArray1::from_vec(py, values)
        .reshape(shape.to_vec())?
        .into_any())
}

/// `[N, 3, 4]` float64 `cam_from_world` matrices.
pub fn extrinsics<'py>(py: Python<'py>, m: &[Matrix3x4<f64>]) -> PyResult<Bound<'py, PyAny>> {
    let v: Vec<f64> = m
        .iter()
        .flat_map(|x| (0..3).flat_map(move |r| (0..4).map(move |c| x[(r, c)])))
        .collect();
    array(py, v, &[m.len(), 3, 4])
}

/// `[N, 3, 3]` float64 intrinsics.
pub fn intrinsics<'py>(py: Python<'py>, m: &[Matrix3<f64>]) -> PyResult<Bound<'py, PyAny>> {
    let v: Vec<f64> = m
        .iter()
        .flat_map(|x| (0..3).flat_map(move |r| (0..3).map(move |c| x[(r, c)])))
        .collect();
    array(py, v, &[m.len(), 3, 3])
}

/// A JSON value as a Python object (through `json.loads`: dicts, lists, numbers, strings).
pub fn json_value<'py>(py: Python<'py>, v: &serde_json::Value) -> PyResult<Bound<'py, PyAny>> {
    py.import("json")?.call_method1("loads", (v.to_string(),))
}
