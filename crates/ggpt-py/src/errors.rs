//! The library's error enums as the typed Python exceptions of `ggpt_rs.exceptions` (defined in
//! Python, so that they can derive from both `GgptError` and a builtin such as `ValueError`).

use std::path::Path;

use ggpt_core::CoreError;
use ggpt_infer::InferError;
use ggpt_model::ModelError;
use ggpt_scene::SceneError;
use ggpt_sfm::SfmError;
use pyo3::IntoPyObjectExt;
use pyo3::exceptions::{PyKeyboardInterrupt, PyRuntimeError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

/// The Python exception class `name` of `ggpt_rs.exceptions`, raised with `message` and the
/// keyword attributes `attrs`.
fn raise(name: &str, message: String, attrs: &[(&str, Py<PyAny>)]) -> PyErr {
    Python::attach(|py| {
        let build = || -> PyResult<PyErr> {
            let cls = py.import("ggpt_rs.exceptions")?.getattr(name)?;
            let kwargs = PyDict::new(py);
            for (k, v) in attrs {
                kwargs.set_item(k, v)?;
            }
            let exc = cls.call((message.clone(),), Some(&kwargs))?;
            Ok(PyErr::from_value(exc))
        };
        build().unwrap_or_else(|e| {
            PyRuntimeError::new_err(format!("{message} (and raising {name} failed: {e})"))
        })
    })
}

/// A path as a Python `str` attribute.
fn path_attr(p: &Path) -> Py<PyAny> {
    attr(p.display().to_string())
}

/// Any value as a Python attribute.
fn attr<T>(v: T) -> Py<PyAny>
where
    T: for<'py> IntoPyObject<'py>,
{
    Python::attach(|py| v.into_py_any(py).unwrap_or_else(|_| py.None()))
}

/// `ggpt_core` errors.
pub fn core_error(e: CoreError) -> PyErr {
    let message = e.to_string();
    match e {
        CoreError::NonFinite {
            path,
            key,
            index,
            value,
        } => raise(
            "NonFiniteError",
            message,
            &[
                ("array", attr(key)),
                ("index", attr(index)),
                ("value", attr(value)),
                ("path", path_attr(&path)),
            ],
        ),
        CoreError::Format { path, key, .. } => raise(
            "FormatError",
            message,
            &[("path", path_attr(&path)), ("key", attr(key))],
        ),
        CoreError::Io { path, .. } => raise(
            "FormatError",
            message,
            &[("path", path_attr(&path)), ("key", attr(""))],
        ),
        CoreError::Invalid(_) => raise("InvalidInputError", message, &[]),
        CoreError::Numeric(_) => raise("GgptError", message, &[]),
    }
}

/// `ggpt_sfm` errors.
pub fn sfm_error(e: SfmError) -> PyErr {
    let message = e.to_string();
    match e {
        SfmError::Core(c) => core_error(c),
        SfmError::Cancelled => PyKeyboardInterrupt::new_err("cancelled"),
        SfmError::Format { path, key, .. } => raise(
            "FormatError",
            message,
            &[("path", path_attr(&path)), ("key", attr(key))],
        ),
        SfmError::Io { path, .. } => raise(
            "FormatError",
            message,
            &[("path", path_attr(&path)), ("key", attr(""))],
        ),
        SfmError::Shape(_) | SfmError::Invalid(_) => raise("InvalidInputError", message, &[]),
        SfmError::Numeric(_) => raise("SfmError", message, &[]),
    }
}

/// `ggpt_scene` errors.
pub fn scene_error(e: SceneError) -> PyErr {
    let message = e.to_string();
    match e {
        SceneError::Core(c) => core_error(c),
        SceneError::Cancelled => PyKeyboardInterrupt::new_err("cancelled"),
        SceneError::NonFinite { what, index, value } => raise(
            "NonFiniteError",
            message,
            &[
                ("array", attr(what)),
                ("index", attr(index)),
                ("value", attr(value)),
            ],
        ),
        SceneError::NoDltPoint => raise("NoGuidanceError", message, &[]),
        SceneError::Invalid(_) => raise("InvalidInputError", message, &[]),
        _ => raise("GgptError", message, &[]),
    }
}

/// `ggpt_model` errors.
pub fn model_error(e: ModelError) -> PyErr {
    let message = e.to_string();
    let path = match &e {
        ModelError::Config { path, .. }
        | ModelError::Missing { path, .. }
        | ModelError::Settings { path, .. }
        | ModelError::CheckpointRead { path, .. }
        | ModelError::CheckpointMismatch { path, .. }
        | ModelError::CheckpointWrite { path, .. }
        | ModelError::ChunkInput { path, .. } => Some(path.clone()),
        _ => None,
    };
    let attrs: Vec<(&str, Py<PyAny>)> = path.iter().map(|p| ("path", path_attr(p))).collect();
    raise("ModelError", message, &attrs)
}

/// `ggpt_infer` errors (the umbrella of the others).
pub fn infer_error(e: InferError) -> PyErr {
    match e {
        InferError::Core(c) => core_error(c),
        InferError::Scene(s) => scene_error(s),
        InferError::Sfm(s) => sfm_error(s),
        InferError::Model(m) => model_error(m),
        InferError::Invalid(m) => raise("InvalidInputError", m, &[]),
        InferError::Write { ref path, .. } => {
            let p = path_attr(path);
            raise("GgptError", e.to_string(), &[("path", p)])
        }
        other => raise("GgptError", other.to_string(), &[]),
    }
}

/// An invalid argument of the Python API (raised as `InvalidInputError`).
pub fn invalid(message: impl Into<String>) -> PyErr {
    raise("InvalidInputError", message.into(), &[])
}
