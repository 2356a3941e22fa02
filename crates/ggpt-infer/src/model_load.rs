//! Resolving and loading the network: weights file, model configuration, the model's optional
//! recommended inference settings (`inference.json`), device.

use std::path::{Path, PathBuf};

use burn::tensor::Device;
use ggpt_scene::chunker::ChunkParams;
use ggpt_model::weights::load_checkpoint;
use ggpt_model::{Ggpt, GgptConfig};

use crate::{InferError, Result};

/// The shipped model folder (`models/ggpt-synth-small/` of the repository): `model.safetensors`
/// (official key names) and `model_config.json` (official model-config JSON).
pub const SHIPPED_MODEL_DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../models/ggpt-synth-small/");
/// Weights file name inside a model folder.
pub const MODEL_WEIGHTS_FILE: &str = "model.safetensors";
/// Model-configuration file name inside a model folder (next to the weights).
pub const MODEL_CONFIG_FILE: &str = "model_config.json";
/// Optional recommended inference settings of a model, next to the weights (and
/// `model_config.json`): `{"chunking": {"chunk_size", "max_pixels", "min_dlt", "min_pixels"}}`,
/// every field optional, unknown keys rejected.
pub const INFERENCE_SETTINGS_FILE: &str = "inference.json";
/// Other weight file names accepted inside a model folder, after [`MODEL_WEIGHTS_FILE`].
const OTHER_WEIGHT_FILES: [&str; 3] = ["model.pth", "model.bpk", "model.step228000.pth"];

/// Where the model configuration came from.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ConfigOrigin {
    /// A JSON file (`--model-config`, or `model_config.json` next to the weights).
    File(PathBuf),
    /// A built-in preset (`--preset`).
    Preset(String),
}

/// A resolved model: weights file, configuration and optional recommended inference settings.
#[derive(Debug, Clone)]
pub struct ModelSpec {
    /// Weights file (`.safetensors` / `.pth` official keys, or `.bpk`).
    pub weights: PathBuf,
    /// Network configuration.
    pub config: GgptConfig,
    /// Where the configuration came from.
    pub origin: ConfigOrigin,
    /// The model's `inference.json` (next to the weights), when present.
    pub inference: Option<ModelInferenceSettings>,
}

/// Chunk-sampler settings (`pipeline.md` §5), each optional: the `chunking` object of a model's
/// `inference.json`, or the explicit `--chunk-size` / `--max-chunk-pixels` / `--min-chunk-dlt`
/// / `--min-chunk-pixels` flags.
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
    pub fn validate(&self, name: impl Fn(&str) -> String) -> std::result::Result<(), String> {
        if let Some(c) = self.chunk_size {
            if !c.is_finite() || c <= 0.0 {
                return Err(format!("{} = {c}: must be a finite number > 0 (fraction of the scene radius)", name("chunk_size")));
            }
        }
        if self.max_pixels == Some(0) {
            return Err(format!("{} = 0: must be at least 1", name("max_pixels")));
        }
        Ok(())
    }
}

/// The contents of a model's `inference.json` (all sections optional, unknown keys rejected).
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InferenceSettings {
    /// Recommended chunk-sampler settings for this model.
    pub chunking: Option<ChunkingSettings>,
}

/// A model's `inference.json`: where it was read and what it holds.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelInferenceSettings {
    /// The file.
    pub path: PathBuf,
    /// Its contents.
    pub settings: InferenceSettings,
}

/// Reads and validates an `inference.json` file; every problem is an [`InferError::Settings`]
/// naming the file.
pub fn read_inference_settings(path: &Path) -> Result<InferenceSettings> {
    let err = |message: String| InferError::Settings { path: path.to_path_buf(), message };
    let text = std::fs::read_to_string(path).map_err(|e| err(format!("cannot read: {e}")))?;
    let settings: InferenceSettings = serde_json::from_str(&text).map_err(|e| {
        let kind = if e.is_data() { "invalid settings" } else { "malformed JSON" };
        err(format!("{kind}: {e} (expected {{\"chunking\": {{\"chunk_size\", \"max_pixels\", \"min_dlt\", \"min_pixels\"}}}}, all optional)"))
    })?;
    if let Some(c) = &settings.chunking {
        c.validate(|f| format!("chunking.{f}")).map_err(err)?;
    }
    Ok(settings)
}

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

/// The command-line flag of a [`ChunkingSettings`] field (`chunk_size` -> `--chunk-size`,
/// `max_pixels` -> `--max-chunk-pixels`, `min_dlt` -> `--min-chunk-dlt`, `min_pixels` ->
/// `--min-chunk-pixels`), for messages.
pub fn chunking_flag(field: &str) -> String {
    match field {
        "chunk_size" => "--chunk-size".into(),
        "max_pixels" => "--max-chunk-pixels".into(),
        "min_dlt" => "--min-chunk-dlt".into(),
        "min_pixels" => "--min-chunk-pixels".into(),
        other => other.into(),
    }
}

/// Resolves the chunk-sampler settings: an explicit `flags` value always wins, then the model's
/// `inference.json` (`spec.inference`), then `base` (the official defaults,
/// `ChunkParams::default()`, for the CLI). Flag values are validated here (`flag_name` names
/// them in the message, e.g. `chunk_size` -> `--chunk-size`); the model's values were validated
/// when its file was read. Fields not exposed (`max_chunks_after_converge`) come from `base`.
pub fn resolve_chunking(base: &ChunkParams, spec: &ModelSpec, flags: &ChunkingSettings, flag_name: impl Fn(&str) -> String) -> Result<ResolvedChunking> {
    flags.validate(flag_name).map_err(InferError::Invalid)?;
    let model = spec.inference.as_ref().and_then(|m| m.settings.chunking).unwrap_or_default();
    fn pick<T: Copy>(flag: Option<T>, model: Option<T>, base: T) -> Resolved<T> {
        match (flag, model) {
            (Some(value), _) => Resolved { value, origin: SettingOrigin::Flag },
            (None, Some(value)) => Resolved { value, origin: SettingOrigin::Model },
            (None, None) => Resolved { value: base, origin: SettingOrigin::Default },
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
    let model_inference_json = spec.inference.as_ref().map(|m| m.path.clone());
    Ok(ResolvedChunking { chunk_size, max_pixels, min_dlt, min_pixels, model_inference_json, params })
}

/// Resolves `weights` (a file, or a model folder holding `model.safetensors`) and the
/// configuration: `model_config` file, else `preset`, else `model_config.json` next to the
/// weights. Missing files give [`InferError::Missing`] naming the path.
pub fn resolve_model(weights: &Path, model_config: Option<&Path>, preset: Option<&str>) -> Result<ModelSpec> {
    let weights = if weights.is_dir() {
        std::iter::once(MODEL_WEIGHTS_FILE)
            .chain(OTHER_WEIGHT_FILES)
            .map(|f| weights.join(f))
            .find(|p| p.is_file())
            .ok_or_else(|| InferError::Missing {
                what: format!("weights ({MODEL_WEIGHTS_FILE} in the model folder)"),
                path: weights.join(MODEL_WEIGHTS_FILE),
            })?
    } else if weights.is_file() {
        weights.to_path_buf()
    } else {
        return Err(InferError::Missing { what: "weights".into(), path: weights.to_path_buf() });
    };
    let (config, origin) = match (model_config, preset) {
        (Some(path), _) => {
            if !path.is_file() {
                return Err(InferError::Missing { what: "model configuration".into(), path: path.to_path_buf() });
            }
            (GgptConfig::from_json_file(path)?, ConfigOrigin::File(path.to_path_buf()))
        }
        (None, Some(name)) => (GgptConfig::preset(name)?, ConfigOrigin::Preset(name.to_string())),
        (None, None) => {
            let path = weights.with_file_name(MODEL_CONFIG_FILE);
            if !path.is_file() {
                return Err(InferError::Missing {
                    what: format!("model configuration (give --model-config FILE or --preset released|small|tiny, or put {MODEL_CONFIG_FILE} next to the weights)"),
                    path,
                });
            }
            (GgptConfig::from_json_file(&path)?, ConfigOrigin::File(path))
        }
    };
    let settings_path = weights.with_file_name(INFERENCE_SETTINGS_FILE);
    let inference = if settings_path.is_file() {
        let settings = read_inference_settings(&settings_path)?;
        Some(ModelInferenceSettings { path: settings_path, settings })
    } else {
        None
    };
    Ok(ModelSpec { weights, config, origin, inference })
}

/// Builds the network on `device` and loads the weights strictly.
pub fn load_model(spec: &ModelSpec, device: &Device) -> Result<Ggpt> {
    Ok(load_checkpoint(Ggpt::new(&spec.config, device), &spec.weights)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resolves_folder_config_and_reports_missing_files() {
        let dir = tempfile::tempdir().unwrap();
        let e = resolve_model(&dir.path().join("nope.safetensors"), None, Some("tiny")).unwrap_err().to_string();
        assert!(e.contains("weights not found") && e.contains("nope.safetensors"), "{e}");
        let e = resolve_model(dir.path(), None, Some("tiny")).unwrap_err().to_string();
        assert!(e.contains("model.safetensors"), "{e}");
        let w = dir.path().join(MODEL_WEIGHTS_FILE);
        std::fs::write(&w, b"x").unwrap();
        let spec = resolve_model(dir.path(), None, Some("tiny")).unwrap();
        assert_eq!(spec.weights, w);
        assert_eq!(spec.origin, ConfigOrigin::Preset("tiny".into()));
        let e = resolve_model(dir.path(), None, None).unwrap_err().to_string();
        assert!(e.contains("model_config.json") && e.contains("--model-config"), "{e}");
        let e = resolve_model(&w, Some(&dir.path().join("c.json")), None).unwrap_err().to_string();
        assert!(e.contains("model configuration not found") && e.contains("c.json"), "{e}");
        assert!(resolve_model(&w, None, Some("huge")).is_err());
    }

    fn spec_with(dir: &Path, inference_json: Option<&str>) -> Result<ModelSpec> {
        let w = dir.join(MODEL_WEIGHTS_FILE);
        std::fs::write(&w, b"x").unwrap();
        if let Some(text) = inference_json {
            std::fs::write(dir.join(INFERENCE_SETTINGS_FILE), text).unwrap();
        }
        resolve_model(dir, None, Some("tiny"))
    }

    #[test]
    fn chunking_precedence_flag_over_model_over_default() {
        let dir = tempfile::tempdir().unwrap();
        let base = ChunkParams::default();
        // No inference.json: everything is the default.
        let spec = spec_with(dir.path(), None).unwrap();
        assert!(spec.inference.is_none());
        let r = resolve_chunking(&base, &spec, &ChunkingSettings::default(), chunking_flag).unwrap();
        assert_eq!(r.params, base);
        assert!([r.max_pixels.origin, r.min_dlt.origin, r.min_pixels.origin, r.chunk_size.origin].iter().all(|&o| o == SettingOrigin::Default));
        assert_eq!(r.model_inference_json, None);
        // inference.json with two of the four fields; one flag overrides one of them.
        let spec = spec_with(dir.path(), Some(r#"{"chunking": {"max_pixels": 10000, "min_pixels": 4000}}"#)).unwrap();
        let path = dir.path().join(INFERENCE_SETTINGS_FILE);
        assert_eq!(spec.inference.as_ref().map(|m| &m.path), Some(&path));
        let flags = ChunkingSettings { min_pixels: Some(5000), chunk_size: Some(0.3), ..ChunkingSettings::default() };
        let r = resolve_chunking(&base, &spec, &flags, chunking_flag).unwrap();
        assert_eq!(r.chunk_size, Resolved { value: 0.3, origin: SettingOrigin::Flag });
        assert_eq!(r.max_pixels, Resolved { value: 10000, origin: SettingOrigin::Model });
        assert_eq!(r.min_dlt, Resolved { value: 100, origin: SettingOrigin::Default });
        assert_eq!(r.min_pixels, Resolved { value: 5000, origin: SettingOrigin::Flag });
        assert_eq!(
            r.params,
            ChunkParams { chunk_size: 0.3, max_pixels: 10000, min_dlt: 100, min_pixels: 5000, max_chunks_after_converge: base.max_chunks_after_converge }
        );
        assert_eq!(r.model_inference_json.as_ref(), Some(&path));
        // config.json form: value + origin per field, the file path.
        let j = serde_json::to_value(&r).unwrap();
        assert_eq!(j["max_pixels"], serde_json::json!({"value": 10000, "origin": "model inference.json"}));
        assert_eq!(j["chunk_size"]["origin"], "flag");
        assert_eq!(j["min_dlt"]["origin"], "default");
        assert_eq!(j["model_inference_json"], serde_json::json!(path));
        let line = r.describe();
        assert!(line.contains("max_pixels 10000 (model inference.json)") && line.contains("chunk_size 0.3 (flag)") && line.contains("min_dlt 100 (default)"), "{line}");
        // The base layer is the caller's parameters (library users), not always the official ones.
        let custom = ChunkParams { min_dlt: 40, max_chunks_after_converge: 7, ..ChunkParams::default() };
        let r = resolve_chunking(&custom, &spec, &ChunkingSettings::default(), chunking_flag).unwrap();
        assert_eq!((r.params.min_dlt, r.params.max_chunks_after_converge, r.params.max_pixels), (40, 7, 10000));
        // An empty file object or chunking object is valid and changes nothing.
        for text in ["{}", r#"{"chunking": {}}"#, r#"{"chunking": null}"#] {
            let spec = spec_with(dir.path(), Some(text)).unwrap();
            assert!(spec.inference.is_some(), "{text}");
            assert_eq!(resolve_chunking(&base, &spec, &ChunkingSettings::default(), chunking_flag).unwrap().params, base, "{text}");
        }
    }

    #[test]
    fn bad_inference_json_and_flags_give_clear_errors() {
        let dir = tempfile::tempdir().unwrap();
        let cases = [
            ("{\"chunking\": {\"max_pixels\": 10000,}}", "malformed JSON: trailing comma"),
            (r#"{"chunking": {"max_pixel": 10000}}"#, "invalid settings: unknown field `max_pixel`"),
            (r#"{"chunking": {}, "fusion": "mean"}"#, "unknown field `fusion`"),
            (r#"{"chunking": {"max_pixels": -5}}"#, "invalid settings: invalid value: integer `-5`"),
            (r#"{"chunking": {"chunk_size": "0.2"}}"#, "invalid settings: invalid type: string"),
            (r#"{"chunking": {"chunk_size": 0}}"#, "chunking.chunk_size = 0"),
            (r#"{"chunking": {"max_pixels": 0}}"#, "chunking.max_pixels = 0"),
            (r#"[1, 2]"#, "invalid settings"),
            ("", "malformed JSON"),
        ];
        for (text, want) in cases {
            let e = spec_with(dir.path(), Some(text)).unwrap_err();
            assert!(matches!(e, InferError::Settings { .. }), "{text}: {e:?}");
            let e = e.to_string();
            assert!(e.contains(want) && e.contains("inference.json") && e.contains(&dir.path().display().to_string()), "{text}: {e}");
        }
        // Next to a weights file given directly, too.
        let w = dir.path().join("weights.bpk");
        std::fs::write(&w, b"x").unwrap();
        let e = resolve_model(&w, None, Some("tiny")).unwrap_err().to_string();
        assert!(e.contains("inference.json") && e.contains("malformed JSON"), "{e}");
        std::fs::remove_file(dir.path().join(INFERENCE_SETTINGS_FILE)).unwrap();
        let spec = resolve_model(&w, None, Some("tiny")).unwrap();
        assert!(spec.inference.is_none());
        // Bad flags name the flag.
        for (flags, want) in [
            (ChunkingSettings { chunk_size: Some(f64::NAN), ..ChunkingSettings::default() }, "--chunk-size = NaN"),
            (ChunkingSettings { chunk_size: Some(-0.1), ..ChunkingSettings::default() }, "--chunk-size = -0.1"),
            (ChunkingSettings { max_pixels: Some(0), ..ChunkingSettings::default() }, "--max-chunk-pixels = 0"),
        ] {
            let e = resolve_chunking(&ChunkParams::default(), &spec, &flags, chunking_flag).unwrap_err().to_string();
            assert!(e.contains(want), "{e}");
        }
    }
}
