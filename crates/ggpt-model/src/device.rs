//! Device selection by name (CLI `--device`).

use burn::tensor::{Device, DeviceKind};

use crate::error::{ModelError, Result};

/// Device for `name`: `ndarray` (reference CPU backend), `flex` (fast pure-Rust CPU backend),
/// `cpu` (the fastest CPU backend compiled in: flex, else ndarray), `wgpu` (default adapter;
/// lavapipe on machines without a GPU), `wgpu:N` (the N-th discrete GPU), and with the `cuda`
/// feature `cuda` / `cuda:N` (Burn's CUDA backend, GPU N).
#[allow(deprecated)]
pub fn device_from_name(name: &str) -> Result<Device> {
    let (base, index) = split_index(name)?;
    match (default_device_env_name(base), index) {
        #[cfg(feature = "ndarray")]
        (Some("ndarray"), None) => Ok(Device::ndarray()),
        #[cfg(feature = "flex")]
        (Some("flex"), None) => Ok(Device::flex()),
        #[cfg(feature = "wgpu")]
        (Some("wgpu"), None) => Ok(Device::wgpu(DeviceKind::DefaultDevice)),
        #[cfg(feature = "wgpu")]
        (Some("wgpu"), Some(i)) => Ok(Device::wgpu(DeviceKind::DiscreteGpu(i))),
        #[cfg(feature = "cuda")]
        (Some("cuda"), i) => Ok(Device::cuda(i.unwrap_or(0))),
        (None, _) if matches!(base, "wgpu" | "cuda") => Err(ModelError::NotCompiled {
            device: name.to_string(),
            feature: if base == "wgpu" { "wgpu" } else { "cuda" },
        }),
        _ => Err(ModelError::Device(name.to_string())),
    }
}

/// `wgpu:1` -> (`wgpu`, Some(1)); `cpu` -> (`cpu`, None).
fn split_index(name: &str) -> Result<(&str, Option<usize>)> {
    match name.split_once(':') {
        None => Ok((name, None)),
        Some((base, i)) => i
            .parse()
            .map(|i| (base, Some(i)))
            .map_err(|_| ModelError::Device(name.to_string())),
    }
}

/// The backend, by its `BURN_DEVICE` name (`flex`, `ndarray`, `wgpu`), that `--device name`
/// selects ([`device_from_name`] builds its device), `None` for an unknown or uncompiled name.
/// Binaries pin Burn's default device to it, because Burn 0.22.1 creates some tensors on `Device::default()` whatever device the model is
/// on (`ModuleOptimizer::load_record`: the optimizer state of a resumed run), and with the `wgpu`
/// feature compiled in that default is a wgpu adapter: a CPU run would probe Vulkan.
pub fn default_device_env_name(name: &str) -> Option<&'static str> {
    let name = name.split_once(':').map_or(name, |(base, _)| base);
    match name {
        #[cfg(feature = "ndarray")]
        "ndarray" => Some("ndarray"),
        #[cfg(feature = "flex")]
        "flex" | "cpu" => Some("flex"),
        #[cfg(all(feature = "ndarray", not(feature = "flex")))]
        "cpu" => Some("ndarray"),
        #[cfg(feature = "wgpu")]
        "wgpu" => Some("wgpu"),
        #[cfg(feature = "cuda")]
        "cuda" => Some("cuda"),
        _ => None,
    }
}

/// Sizes the process-wide rayon pool used by the CPU backends (flex: gemm, attention and
/// element-wise kernels; ndarray: `multi-threads`) and by host planning: `threads = 0` keeps
/// rayon's default (all cores, or `RAYON_NUM_THREADS`).
///
/// Call once at start-up, before the first tensor operation: rayon's global pool can be sized
/// only before its first use. ndarray's matrix products (matrixmultiply) read
/// `MATMUL_NUM_THREADS` instead; binaries set that variable as well.
pub fn init_cpu_threads(threads: usize) -> Result<()> {
    if threads == 0 {
        return Ok(());
    }
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build_global()
        .map_err(|e| {
            ModelError::Threads(format!(
                "cannot size the CPU thread pool to {threads} threads: {e}"
            ))
        })
}

/// Keeps freed memory in the process instead of returning it to the kernel after every tensor
/// operation (glibc malloc; a no-op elsewhere). CPU forwards allocate and free large buffers
/// (activations, im2col blocks) op after op; with glibc's defaults every buffer above 128 KiB is
/// a fresh `mmap` whose pages fault in on first touch and are unmapped on free, which profiles
/// showed as ~20 % of a CPU forward. Raising the mmap threshold to glibc's maximum (32 MiB on
/// 64-bit: `mallopt` rejects anything above `HEAP_MAX_SIZE / 2`, and a rejected value left the
/// default in place before 2026-12-03) and the trim threshold to 1 GiB lets those buffers be
/// reused from the heap. Peak memory is unchanged (the same buffers are live); the resident size
/// stays at the peak between forwards. Call once at start-up; returns whether glibc accepted
/// both settings (`true` off glibc).
pub fn tune_allocator() -> bool {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        /// glibc's largest accepted `M_MMAP_THRESHOLD` on 64-bit (`DEFAULT_MMAP_THRESHOLD_MAX`).
        const MMAP_THRESHOLD: libc::c_int = 32 << 20;
        const TRIM_THRESHOLD: libc::c_int = 1 << 30;
        // SAFETY: mallopt only adjusts glibc malloc parameters; no memory is touched.
        unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1
                && libc::mallopt(libc::M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1
        }
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        true
    }
}

/// Threads the CPU backends use now (the rayon global pool's size).
pub fn cpu_threads() -> usize {
    rayon::current_num_threads()
}

/// Silences an unused-import warning when wgpu is off.
#[allow(dead_code)]
fn _kind(_: DeviceKind) {}

#[cfg(test)]
mod index_tests {
    use super::*;

    #[test]
    fn the_allocator_settings_are_accepted() {
        assert!(tune_allocator(), "glibc rejected a mallopt setting");
    }

    #[test]
    fn device_names_take_an_optional_index() {
        assert_eq!(split_index("wgpu:1").unwrap(), ("wgpu", Some(1)));
        assert_eq!(split_index("cpu").unwrap(), ("cpu", None));
        assert!(split_index("wgpu:x").is_err());
        assert_eq!(
            default_device_env_name("wgpu:3"),
            default_device_env_name("wgpu")
        );
        assert!(
            device_from_name("ndarray:1").is_err(),
            "CPU backends take no index"
        );
        assert!(device_from_name("tpu").is_err());
        #[cfg(not(feature = "wgpu"))]
        {
            let e = device_from_name("wgpu:0").unwrap_err().to_string();
            assert!(e.contains("--features wgpu"), "{e}");
        }
    }
}
