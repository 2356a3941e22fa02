//! Test helpers: reading the shared reference fixtures in place (never copied, never skipped).

use std::path::PathBuf;

use safetensors::{Dtype, SafeTensors};

/// `<workspace>/../shared/fixtures`.
pub fn fixtures_dir() -> PathBuf {
    PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../../shared/fixtures"
    ))
}

/// One safetensors fixture file held in memory.
pub struct Fixture {
    name: String,
    bytes: Vec<u8>,
}

impl Fixture {
    /// Loads `<fixtures>/<rel>`; panics (test failure) when it is missing.
    pub fn load(rel: &str) -> Self {
        let path = fixtures_dir().join(rel);
        let bytes =
            std::fs::read(&path).unwrap_or_else(|e| panic!("fixture {path:?} missing: {e}"));
        Fixture {
            name: rel.to_string(),
            bytes,
        }
    }
    /// `sfm_small/steps.safetensors`.
    pub fn sfm_steps() -> Self {
        Self::load("sfm_small/steps.safetensors")
    }
    /// `sfm_small/inputs.safetensors`.
    pub fn sfm_inputs() -> Self {
        Self::load("sfm_small/inputs.safetensors")
    }
    /// `official_format/synth_room_s0/reference.safetensors`.
    pub fn official_reference() -> Self {
        Self::load("official_format/synth_room_s0/reference.safetensors")
    }

    fn raw(&self, key: &str, dtype: Dtype) -> (Vec<usize>, Vec<u8>) {
        let st =
            SafeTensors::deserialize(&self.bytes).unwrap_or_else(|e| panic!("{}: {e}", self.name));
        let view = st
            .tensor(key)
            .unwrap_or_else(|e| panic!("{}: {key}: {e}", self.name));
        assert_eq!(view.dtype(), dtype, "{}: {key}: dtype", self.name);
        (view.shape().to_vec(), view.data().to_vec())
    }
    /// F32 tensor, flat.
    pub fn f32(&self, key: &str) -> Vec<f32> {
        let (_, d) = self.raw(key, Dtype::F32);
        d.chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect()
    }
    /// F64 tensor, flat.
    pub fn f64(&self, key: &str) -> Vec<f64> {
        let (_, d) = self.raw(key, Dtype::F64);
        d.chunks_exact(8)
            .map(|b| f64::from_le_bytes(b.try_into().unwrap()))
            .collect()
    }
    /// I64 tensor, flat.
    pub fn i64(&self, key: &str) -> Vec<i64> {
        let (_, d) = self.raw(key, Dtype::I64);
        d.chunks_exact(8)
            .map(|b| i64::from_le_bytes(b.try_into().unwrap()))
            .collect()
    }
    /// BOOL tensor, flat.
    pub fn bool(&self, key: &str) -> Vec<bool> {
        let (_, d) = self.raw(key, Dtype::BOOL);
        d.iter().map(|&b| b != 0).collect()
    }
}
