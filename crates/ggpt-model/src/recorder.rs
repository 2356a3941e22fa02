//! Optional recorder of named intermediate tensors (fixture names, network.md §13).

use std::collections::HashMap;

use burn::tensor::Tensor;

/// Collects `name -> tensor` when enabled; a no-op otherwise (names are built lazily).
#[derive(Debug, Default)]
pub struct Recorder {
    enabled: bool,
    /// Recorded tensors (all rank 2, rows = tokens of the level over the whole batch).
    pub tensors: HashMap<String, Tensor<2>>,
}

impl Recorder {
    /// A recorder that keeps every tensor.
    pub fn enabled() -> Self {
        Self {
            enabled: true,
            tensors: HashMap::new(),
        }
    }

    /// A recorder that keeps nothing.
    pub fn disabled() -> Self {
        Self::default()
    }

    /// Records `tensor` under `name()` when enabled (cheap clone of a device handle).
    pub fn record(&mut self, name: impl FnOnce() -> String, tensor: &Tensor<2>) {
        if self.enabled {
            self.tensors.insert(name(), tensor.clone());
        }
    }
}
