//! The tests' short names for the library's torch-zip writer (`ggpt_core::io::torch_zip`).

use std::path::Path;

pub use ggpt_core::io::torch_zip::TorchValue as Value;

/// Contiguous f32 tensor.
pub fn f32_tensor(v: &[f32], size: &[usize]) -> Value {
    Value::f32(v, size)
}

/// Contiguous bool tensor.
pub fn bool_tensor(v: &[bool], size: &[usize]) -> Value {
    Value::bool(v, size)
}

/// Writes a torch zip with the given entries (in order).
pub fn write_torch(path: &Path, entries: &[(&str, Value)]) {
    ggpt_core::io::torch_zip::write_torch_zip(path, entries).expect("writing the torch zip");
}
