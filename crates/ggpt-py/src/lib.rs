//! `ggpt_rs._ggpt_rs`: the compiled module of the `ggpt-rs` Python package (docs/python.md).
//!
//! The binding is thin: every computation is a call into the Rust libraries (the SfM stage
//! `ggpt_sfm`, the refinement `ggpt_infer::Refiner`, the readers of `ggpt_core::io`), the same
//! code the command lines run. The pure-Python package around it (`python/ggpt_rs/`) adds the
//! adapters of user-facing inputs (torch tensors, VGGT dicts, a tqdm bar), the exception
//! classes and the type stubs.

mod arrays;
mod data;
mod errors;
mod model;
mod run;

use pyo3::prelude::*;

/// The compiled module.
#[pymodule]
fn _ggpt_rs(m: &Bound<'_, PyModule>) -> PyResult<()> {
    // The library logs through `tracing`; without a subscriber its events become `log` records,
    // which pyo3-log forwards to Python's `logging` (logger names = Rust module paths).
    let _ = pyo3_log::try_init();
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_class::<model::PyModel>()?;
    m.add_class::<data::PyFeedForward>()?;
    m.add_class::<data::PyMatches>()?;
    m.add_class::<data::PySfmResult>()?;
    m.add_class::<data::PyScene>()?;
    m.add_class::<run::PyRefinedScene>()?;
    m.add_function(wrap_pyfunction!(data::read_scene, m)?)?;
    m.add_function(wrap_pyfunction!(run::run_sfm, m)?)?;
    m.add_function(wrap_pyfunction!(run::refine, m)?)?;
    Ok(())
}
