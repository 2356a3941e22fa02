//! Readback: device tensors to host vectors, the ground floor under the kernels and the
//! network modules (`docs/architecture.md`, "Kernel layer"). Every readback is counted
//! ([`crate::device_stats::note_readback`]); a failed device execution becomes a
//! [`ModelError::Readback`] naming the tensor instead of a panic.

use burn::backend::Backend;
use burn::backend::tensor::IntTensor;
use burn::tensor::{Int, Tensor, TensorData};

use crate::error::{ModelError, Result};

/// Reads a tensor back to the host as `Vec<f32>`. A failed device execution (e.g. a GPU buffer
/// allocation above the device's limits or out of memory) becomes [`ModelError::Readback`]
/// naming the tensor, with a hint to run smaller forwards, instead of a panic.
pub fn read_tensor_f32<const D: usize>(t: &Tensor<D>, name: &str) -> Result<Vec<f32>> {
    tensor_into_f32(t.clone(), name)
}

/// [`read_tensor_f32`] of an owned tensor (no copy of the tensor data on the host).
pub fn tensor_into_f32<const D: usize>(t: Tensor<D>, name: &str) -> Result<Vec<f32>> {
    crate::device_stats::note_readback();
    let data = t.try_into_data().map_err(|e| ModelError::Readback {
        name: name.to_string(),
        message: format!("device execution failed ({e}); if the device ran out of memory or hit a buffer-size limit, run smaller forwards (--max-tokens-per-forward / smaller chunks)"),
    })?;
    data_into_f32(data, name)
}

/// Converts tensor data to `Vec<f32>`, naming the tensor on failure.
pub fn read_f32(data: &burn::tensor::TensorData, name: &str) -> Result<Vec<f32>> {
    data_into_f32(data.clone(), name)
}

/// [`read_f32`] of owned data.
fn data_into_f32(data: burn::tensor::TensorData, name: &str) -> Result<Vec<f32>> {
    data.convert::<f32>()
        .try_into_vec::<f32>()
        .map_err(|e| ModelError::Readback {
            name: name.to_string(),
            message: format!("{e:?}"),
        })
}

/// The f32 values of `t`, row-major; `None` when they cannot be read back.
pub(crate) fn read_values<const D: usize>(t: Tensor<D>) -> Option<Vec<f32>> {
    tensor_into_f32(t, "host readback").ok()
}

/// The values of an index table read back to the host, `None` when the readback fails or an
/// entry is negative (the host kernels' tables: [`crate::attention::HostAttnIndex`],
/// [`crate::host_conv_grad::HostConvTables`]).
pub(crate) fn read_indices(t: &Tensor<1, Int>) -> Option<Vec<usize>> {
    crate::device_stats::note_readback();
    indices_of(t.clone().try_into_data().ok()?)
}

/// [`read_indices`] for a backend's int primitive (inside the kernel layer, where no `Tensor`
/// wraps it).
pub(crate) fn read_indices_primitive<B: Backend>(t: &IntTensor<B>) -> Option<Vec<usize>> {
    crate::device_stats::note_readback();
    indices_of(burn::tensor::try_read_sync(B::int_into_data(t.clone()))?.ok()?)
}

/// The entries of an index table as `usize`; `None` when one is negative.
fn indices_of(data: TensorData) -> Option<Vec<usize>> {
    let v = data.convert::<i64>().try_to_vec::<i64>().ok()?;
    v.into_iter().map(|x| usize::try_from(x).ok()).collect()
}
