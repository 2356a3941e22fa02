//! Resolution of the chunk-sampler settings (`pipeline.md` §5) over three layers: explicit
//! values (command-line flags or a library caller), a model folder's `inference.json`, and the
//! caller's base parameters (the official defaults for the CLIs). Every value in force carries
//! its origin, and `config.json` records both.

use std::path::{Path, PathBuf};

pub use ggpt_core::chunking::ChunkingSettings;

use crate::chunker::ChunkParams;
use crate::error::SceneError;

/// Where a resolved setting came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum SettingOrigin {
    /// The built-in (official) default, or the caller's base value.
    #[serde(rename = "default")]
    Default,
    /// The model folder's `inference.json`.
    #[serde(rename = "model inference.json")]
    Model,
    /// An explicit command-line flag (or library override).
    #[serde(rename = "flag")]
    Flag,
}

impl std::fmt::Display for SettingOrigin {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            SettingOrigin::Default => "default",
            SettingOrigin::Model => "model inference.json",
            SettingOrigin::Flag => "flag",
        })
    }
}

/// A resolved value and its origin.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Resolved<T> {
    /// The value in force.
    pub value: T,
    /// Where it came from.
    pub origin: SettingOrigin,
}

/// The chunk-sampler settings in force, each with its origin (written to `config.json` as
/// `chunking`).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ResolvedChunking {
    /// Cube half-size as a fraction of `R`.
    pub chunk_size: Resolved<f64>,
    /// Maximum pixels per chunk.
    pub max_pixels: Resolved<usize>,
    /// Initial minimum DLT pixels per chunk.
    pub min_dlt: Resolved<usize>,
    /// Initial minimum pixels per chunk.
    pub min_pixels: Resolved<usize>,
    /// The model's `inference.json`, when one was found (whether or not it set a value).
    pub model_inference_json: Option<PathBuf>,
    /// The complete sampler parameters (the four above over the base parameters).
    #[serde(skip)]
    pub params: ChunkParams,
}

impl ResolvedChunking {
    /// One log line: `chunk_size 0.2 (default), max_pixels 10000 (model inference.json), ...`.
    pub fn describe(&self) -> String {
        let mut s = format!(
            "chunk_size {} ({}), max_pixels {} ({}), min_dlt {} ({}), min_pixels {} ({})",
            self.chunk_size.value,
            self.chunk_size.origin,
            self.max_pixels.value,
            self.max_pixels.origin,
            self.min_dlt.value,
            self.min_dlt.origin,
            self.min_pixels.value,
            self.min_pixels.origin
        );
        if let Some(p) = &self.model_inference_json {
            s.push_str(&format!("; model settings {}", p.display()));
        }
        s
    }
}

/// Resolves the chunk-sampler settings: an explicit `flags` value always wins, then the model's
/// `inference.json` (`model`: its path and `chunking` object, `ggpt_model::model_dir::ModelSpec::chunking_layer`), then `base` (the official defaults,
/// `ChunkParams::default()`, for the CLI). Flag values are validated here (`flag_name` names
/// them in the message, e.g. `chunk_size` -> `--chunk-size`); the model's values were validated
/// when its file was read. Fields not exposed (`max_chunks_after_converge`) come from `base`.
pub fn resolve_chunking(
    base: &ChunkParams,
    model: Option<(&Path, Option<&ChunkingSettings>)>,
    flags: &ChunkingSettings,
    flag_name: impl Fn(&str) -> String,
) -> Result<ResolvedChunking, SceneError> {
    flags.validate(flag_name).map_err(SceneError::Invalid)?;
    let model_json = model.map(|(path, _)| path.to_path_buf());
    let model = model.and_then(|(_, c)| c.copied()).unwrap_or_default();
    fn pick<T: Copy>(flag: Option<T>, model: Option<T>, base: T) -> Resolved<T> {
        match (flag, model) {
            (Some(value), _) => Resolved {
                value,
                origin: SettingOrigin::Flag,
            },
            (None, Some(value)) => Resolved {
                value,
                origin: SettingOrigin::Model,
            },
            (None, None) => Resolved {
                value: base,
                origin: SettingOrigin::Default,
            },
        }
    }
    let chunk_size = pick(flags.chunk_size, model.chunk_size, base.chunk_size);
    let max_pixels = pick(flags.max_pixels, model.max_pixels, base.max_pixels);
    let min_dlt = pick(flags.min_dlt, model.min_dlt, base.min_dlt);
    let min_pixels = pick(flags.min_pixels, model.min_pixels, base.min_pixels);
    let params = ChunkParams {
        chunk_size: chunk_size.value,
        max_pixels: max_pixels.value,
        min_dlt: min_dlt.value,
        min_pixels: min_pixels.value,
        ..base.clone()
    };
    Ok(ResolvedChunking {
        chunk_size,
        max_pixels,
        min_dlt,
        min_pixels,
        model_inference_json: model_json,
        params,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The flag names of `ggpt-infer` (what the messages below show).
    fn chunking_flag(field: &str) -> String {
        match field {
            "chunk_size" => "--chunk-size".into(),
            "max_pixels" => "--max-chunk-pixels".into(),
            other => other.into(),
        }
    }

    #[test]
    fn chunking_precedence_flag_over_model_over_default() {
        let base = ChunkParams::default();
        // No inference.json: everything is the default.
        let r = resolve_chunking(&base, None, &ChunkingSettings::default(), chunking_flag).unwrap();
        assert_eq!(r.params, base);
        assert!(
            [
                r.max_pixels.origin,
                r.min_dlt.origin,
                r.min_pixels.origin,
                r.chunk_size.origin
            ]
            .iter()
            .all(|&o| o == SettingOrigin::Default)
        );
        assert_eq!(r.model_inference_json, None);
        // inference.json with two of the four fields; one flag overrides one of them.
        let path = PathBuf::from("model/inference.json");
        let model = ChunkingSettings {
            max_pixels: Some(10000),
            min_pixels: Some(4000),
            ..ChunkingSettings::default()
        };
        let spec = Some((path.as_path(), Some(&model)));
        let flags = ChunkingSettings {
            min_pixels: Some(5000),
            chunk_size: Some(0.3),
            ..ChunkingSettings::default()
        };
        let r = resolve_chunking(&base, spec, &flags, chunking_flag).unwrap();
        assert_eq!(
            r.chunk_size,
            Resolved {
                value: 0.3,
                origin: SettingOrigin::Flag
            }
        );
        assert_eq!(
            r.max_pixels,
            Resolved {
                value: 10000,
                origin: SettingOrigin::Model
            }
        );
        assert_eq!(
            r.min_dlt,
            Resolved {
                value: 100,
                origin: SettingOrigin::Default
            }
        );
        assert_eq!(
            r.min_pixels,
            Resolved {
                value: 5000,
                origin: SettingOrigin::Flag
            }
        );
        assert_eq!(
            r.params,
            ChunkParams {
                chunk_size: 0.3,
                max_pixels: 10000,
                min_dlt: 100,
                min_pixels: 5000,
                max_chunks_after_converge: base.max_chunks_after_converge
            }
        );
        assert_eq!(r.model_inference_json.as_ref(), Some(&path));
        // config.json form: value + origin per field, the file path.
        let j = serde_json::to_value(&r).unwrap();
        assert_eq!(
            j["max_pixels"],
            serde_json::json!({"value": 10000, "origin": "model inference.json"})
        );
        assert_eq!(j["chunk_size"]["origin"], "flag");
        assert_eq!(j["min_dlt"]["origin"], "default");
        assert_eq!(j["model_inference_json"], serde_json::json!(path));
        let line = r.describe();
        assert!(
            line.contains("max_pixels 10000 (model inference.json)")
                && line.contains("chunk_size 0.3 (flag)")
                && line.contains("min_dlt 100 (default)"),
            "{line}"
        );
        // The base layer is the caller's parameters (library users), not always the official ones.
        let custom = ChunkParams {
            min_dlt: 40,
            max_chunks_after_converge: 7,
            ..ChunkParams::default()
        };
        let r =
            resolve_chunking(&custom, spec, &ChunkingSettings::default(), chunking_flag).unwrap();
        assert_eq!(
            (
                r.params.min_dlt,
                r.params.max_chunks_after_converge,
                r.params.max_pixels
            ),
            (40, 7, 10000)
        );
        // A model file without a chunking object, or with an empty one, changes nothing.
        let empty = ChunkingSettings::default();
        for layer in [(path.as_path(), None), (path.as_path(), Some(&empty))] {
            let r = resolve_chunking(
                &base,
                Some(layer),
                &ChunkingSettings::default(),
                chunking_flag,
            )
            .unwrap();
            assert_eq!(
                (&r.params, r.model_inference_json.as_ref()),
                (&base, Some(&path))
            );
        }
    }

    #[test]
    fn bad_flags_name_the_flag() {
        let path = PathBuf::from("model/inference.json");
        let model = ChunkingSettings::default();
        let spec = Some((path.as_path(), Some(&model)));
        // Bad flags name the flag.
        for (flags, want) in [
            (
                ChunkingSettings {
                    chunk_size: Some(f64::NAN),
                    ..ChunkingSettings::default()
                },
                "--chunk-size = NaN",
            ),
            (
                ChunkingSettings {
                    chunk_size: Some(-0.1),
                    ..ChunkingSettings::default()
                },
                "--chunk-size = -0.1",
            ),
            (
                ChunkingSettings {
                    max_pixels: Some(0),
                    ..ChunkingSettings::default()
                },
                "--max-chunk-pixels = 0",
            ),
        ] {
            let e = resolve_chunking(&ChunkParams::default(), spec, &flags, chunking_flag)
                .unwrap_err()
                .to_string();
            assert!(e.contains(want), "{e}");
        }
    }
}
