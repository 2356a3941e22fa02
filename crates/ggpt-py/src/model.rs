//! `Model`: a loaded GGPT network on a device ([`ggpt_infer::Refiner`]).

use std::path::PathBuf;
use std::sync::Mutex;

use ggpt_core::chunk_input::ChunkInput;
use ggpt_infer::Refiner;
use ggpt_model::model_dir::resolve_model;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use crate::arrays::{array, f32_values, json_value, to_npy};
use crate::errors::{infer_error, invalid, model_error};

/// A GGPT network loaded on a device. `weights`: `"shipped"` (the model embedded in the
/// package), an official `.pth` (read without torch) or `.safetensors`, a project `.bpk`, or a
/// model folder; `model_config` / `preset` (`released`, `small`, `tiny`) as `ggpt-infer`'s
/// `--model-config` / `--preset`; `device`: `cpu` (default), `flex`, `ndarray`, `wgpu[:N]`
/// (built with the `wgpu` feature); `threads`: CPU threads of this model's calls (0: all cores).
/// The first model of a process applies `ggpt-infer`'s glibc malloc settings
/// (`GGPT_RS_MALLOC_TUNING=0` keeps the process's own).
#[pyclass(module = "ggpt_rs._ggpt_rs", name = "Model", frozen)]
pub struct PyModel {
    /// Boxed: the refiner (its rayon pool) is 64-byte aligned, more than the Python object
    /// allocator guarantees for a pyclass's inline contents.
    pub(crate) refiner: Box<Mutex<Refiner>>,
    weights: String,
    shipped: bool,
    device: String,
    threads: usize,
    config: serde_json::Value,
}

impl PyModel {
    /// Runs `f` on the locked refiner.
    pub(crate) fn with<R>(&self, f: impl FnOnce(&mut Refiner) -> R) -> PyResult<R> {
        let mut guard = self
            .refiner
            .lock()
            .map_err(|_| invalid("the model is unusable: an earlier call panicked"))?;
        Ok(f(&mut guard))
    }
}

/// Environment variable that keeps the process's malloc settings when set to `0`.
const MALLOC_TUNING_ENV: &str = "GGPT_RS_MALLOC_TUNING";

/// The CLI's allocator settings ([`ggpt_model::device::tune_allocator`]: freed tensor buffers
/// reused from the heap instead of `mmap`/`munmap` per op), applied once, when the first model is
/// loaded (not at import), unless `GGPT_RS_MALLOC_TUNING=0`. Without them a CPU refinement from
/// Python took 23 % longer than the same one through `ggpt-infer run` (docs/python.md).
fn tune_allocator_once() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        if std::env::var(MALLOC_TUNING_ENV).as_deref() == Ok("0") {
            tracing::info!("{MALLOC_TUNING_ENV}=0: malloc settings left as they are");
        } else if !ggpt_model::device::tune_allocator() {
            tracing::warn!("glibc rejected the malloc settings; CPU forwards may be slower");
        }
    });
}

#[pymethods]
impl PyModel {
    #[new]
    #[pyo3(signature = (weights = PathBuf::from("shipped"), model_config = None, preset = None, device = "cpu", threads = 0))]
    fn new(
        py: Python<'_>,
        weights: PathBuf,
        model_config: Option<PathBuf>,
        preset: Option<String>,
        device: &str,
        threads: usize,
    ) -> PyResult<Self> {
        tune_allocator_once();
        let spec = resolve_model(&weights, model_config.as_deref(), preset.as_deref())
            .map_err(model_error)?;
        let (name, shipped) = (spec.weights.display().to_string(), spec.is_embedded());
        let config = serde_json::to_value(&spec.config).unwrap_or(serde_json::Value::Null);
        let refiner = py
            .detach(|| Refiner::load(spec, device, threads))
            .map_err(infer_error)?;
        let threads = refiner.threads();
        Ok(PyModel {
            refiner: Box::new(Mutex::new(refiner)),
            weights: name,
            shipped,
            device: device.to_string(),
            threads,
            config,
        })
    }

    /// The weights file (`<embedded>/ggpt-synth-small/model.safetensors` for the shipped model).
    #[getter]
    fn weights(&self) -> &str {
        &self.weights
    }

    /// Whether this is the shipped model embedded in the package.
    #[getter]
    fn shipped(&self) -> bool {
        self.shipped
    }

    /// The device name.
    #[getter]
    fn device(&self) -> &str {
        &self.device
    }

    /// CPU threads of this model's calls.
    #[getter]
    fn threads(&self) -> usize {
        self.threads
    }

    /// The network configuration (the official `model_config` object) as a dict.
    #[getter]
    fn config<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        json_value(py, &self.config)
    }

    /// The network on prepared chunk records (normalised chunk coordinates, as the official
    /// `chunk` inputs): each dict holds `ff_pts [K, 3]`, `ff_pts_conf [K]`, `geo_pts [K, 3]`,
    /// `geo_msks [K]` (bool); each result `ff_pts_out [K, 3]`, `ff_pts_conf_out [K]`,
    /// `geo_pts_out [K, 3]`, `geo_pts_conf_out [K]`, `tokens_xyz_out [T, 3]`,
    /// `tokens_conf_out [T]` (float32). One forward per chunk (as the official inference), or
    /// one for all with `batched=True`.
    #[pyo3(signature = (chunks, batched = false))]
    fn forward_chunks<'py>(
        &self,
        py: Python<'py>,
        chunks: &Bound<'py, PyList>,
        batched: bool,
    ) -> PyResult<Bound<'py, PyList>> {
        let mut inputs = Vec::with_capacity(chunks.len());
        for (c, item) in chunks.iter().enumerate() {
            let d = item
                .cast::<PyDict>()
                .map_err(|_| invalid(format!("chunks[{c}]: expected a dict of arrays")))?;
            let get = |k: &str| -> PyResult<Bound<'py, PyAny>> {
                d.get_item(k)?
                    .ok_or_else(|| invalid(format!("chunks[{c}]: missing {k:?}")))
            };
            let pts = |k: &str| -> PyResult<Vec<[f32; 3]>> {
                let (shape, v) = f32_values(&get(k)?, k)?;
                if shape.len() != 2 || shape[1] != 3 {
                    return Err(invalid(format!(
                        "chunks[{c}].{k}: shape {shape:?}, expected [K, 3]"
                    )));
                }
                Ok(v.chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect())
            };
            let ff_pts = pts("ff_pts")?;
            let geo_pts = pts("geo_pts")?;
            let (_, ff_conf) = f32_values(&get("ff_pts_conf")?, "ff_pts_conf")?;
            let msk = to_npy(&get("geo_msks")?, "geo_msks")?;
            let geo_msk = match msk.data {
                ggpt_core::io::npy::NpyData::Bool(v) => v,
                ggpt_core::io::npy::NpyData::U8(v) => v.into_iter().map(|b| b != 0).collect(),
                _ => return Err(invalid(format!("chunks[{c}].geo_msks: expected bool"))),
            };
            let k = ff_pts.len();
            if geo_pts.len() != k || ff_conf.len() != k || geo_msk.len() != k {
                return Err(invalid(format!(
                    "chunks[{c}]: ff_pts has {k} rows, ff_pts_conf {}, geo_pts {}, geo_msks {}",
                    ff_conf.len(),
                    geo_pts.len(),
                    geo_msk.len()
                )));
            }
            inputs.push(ChunkInput {
                ff_pts,
                ff_conf,
                geo_pts,
                geo_msk,
            });
        }
        let outputs = py
            .detach(|| {
                self.with(|r| {
                    if batched {
                        r.forward_chunks(&inputs)
                    } else {
                        let mut all = Vec::with_capacity(inputs.len());
                        for one in inputs.chunks(1) {
                            all.extend(r.forward_chunks(one)?);
                        }
                        Ok(all)
                    }
                })
            })?
            .map_err(infer_error)?;
        let out = PyList::empty(py);
        for o in outputs {
            let d = PyDict::new(py);
            let flat = |v: Vec<[f32; 3]>| v.into_iter().flatten().collect::<Vec<f32>>();
            let (k, t) = (o.ff_pts_conf_out.len(), o.tokens_conf_out.len());
            d.set_item("ff_pts_out", array(py, flat(o.ff_pts_out), &[k, 3])?)?;
            d.set_item("ff_pts_conf_out", array(py, o.ff_pts_conf_out, &[k])?)?;
            d.set_item("geo_pts_out", array(py, flat(o.geo_pts_out), &[k, 3])?)?;
            d.set_item("geo_pts_conf_out", array(py, o.geo_pts_conf_out, &[k])?)?;
            d.set_item(
                "tokens_xyz_out",
                array(py, flat(o.tokens_xyz_out), &[t, 3])?,
            )?;
            d.set_item("tokens_conf_out", array(py, o.tokens_conf_out, &[t])?)?;
            out.append(d)?;
        }
        Ok(out)
    }

    fn __repr__(&self) -> String {
        format!(
            "Model(weights={:?}, device={:?}, threads={})",
            if self.shipped {
                "shipped"
            } else {
                &self.weights
            },
            self.device,
            self.threads
        )
    }
}
