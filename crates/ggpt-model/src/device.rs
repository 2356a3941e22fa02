//! Device selection by name (CLI `--device`).

use burn::tensor::{Device, DeviceKind};

use crate::error::{ModelError, Result};

/// Device for `name`: `ndarray` (reference CPU backend), `flex` (fast pure-Rust CPU backend),
/// `cpu` (the fastest CPU backend compiled in: flex, else ndarray), `wgpu` (default adapter;
/// lavapipe on machines without a GPU).
#[allow(deprecated)]
pub fn device_from_name(name: &str) -> Result<Device> {
    match name {
        #[cfg(feature = "ndarray")]
        "ndarray" => Ok(Device::ndarray()),
        #[cfg(feature = "flex")]
        "flex" | "cpu" => Ok(Device::flex()),
        #[cfg(all(feature = "ndarray", not(feature = "flex")))]
        "cpu" => Ok(Device::ndarray()),
        #[cfg(feature = "wgpu")]
        "wgpu" => Ok(Device::wgpu(DeviceKind::DefaultDevice)),
        other => Err(ModelError::Device(other.to_string())),
    }
}

/// Silences an unused-import warning when wgpu is off.
#[allow(dead_code)]
fn _kind(_: DeviceKind) {}
