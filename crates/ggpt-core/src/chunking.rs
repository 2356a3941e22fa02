//! Chunk-sampler overrides (`pipeline.md` §5): the `chunking` object of a model folder's
//! `inference.json` and the explicit command-line values. Plain data shared by the model-folder
//! contract (`ggpt_model::model_dir`) and the sampler's resolution
//! (`ggpt_scene::chunker::resolve_chunking`); neither crate depends on the other.

/// Chunk-sampler settings, each optional (`None`: not set at this layer).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChunkingSettings {
    /// Cube half-size as a fraction of the scene radius `R` (official 0.2).
    pub chunk_size: Option<f64>,
    /// Maximum pixels per chunk before the cube shrinks by 0.9 (official 400,000).
    pub max_pixels: Option<usize>,
    /// Initial minimum number of DLT pixels of an accepted chunk (official 100).
    pub min_dlt: Option<usize>,
    /// Initial minimum number of pixels of an accepted chunk (official 10,000).
    pub min_pixels: Option<usize>,
}

impl ChunkingSettings {
    /// Checks the values that are given: `chunk_size` finite and > 0, `max_pixels` >= 1.
    /// `name` turns a field name into the name shown in the message (a flag or a JSON path).
    pub fn validate(&self, name: impl Fn(&str) -> String) -> Result<(), String> {
        if let Some(c) = self.chunk_size
            && (!c.is_finite() || c <= 0.0)
        {
            return Err(format!(
                "{} = {c}: must be a finite number > 0 (fraction of the scene radius)",
                name("chunk_size")
            ));
        }
        if self.max_pixels == Some(0) {
            return Err(format!("{} = 0: must be at least 1", name("max_pixels")));
        }
        Ok(())
    }
}
