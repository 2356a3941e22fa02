//! The model folder contract (`docs/inference.md` "Model folders"): the files of a model folder
//! (`model.safetensors` with official key names, `model_config.json`, the optional
//! `inference.json`), resolving a weights path and configuration into a [`ModelSpec`], loading
//! it, and the shipped model (`models/ggpt-synth-small/`), embedded in every binary that links
//! this crate so that an installed binary finds it without the source tree. `ggpt-train`
//! writes this contract (`ggpt-train export`), `ggpt-infer` reads it.

use std::path::{Path, PathBuf};

use burn::tensor::Device;
use ggpt_core::chunking::ChunkingSettings;

use crate::error::{ModelError, Result};
use crate::weights::{load_checkpoint, load_safetensors_bytes};
use crate::{Ggpt, GgptConfig};

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

/// Folder name of the shipped model (`crates/ggpt-model/models/`, linked from `models/` of the
/// repository).
pub const SHIPPED_MODEL_NAME: &str = "ggpt-synth-small";
/// What `--weights` / `Model(...)` accept for the shipped model (a file or folder of that name,
/// when one exists, wins).
pub const SHIPPED: &str = "shipped";
/// The shipped model folder inside this crate (in the source tree, or the unpacked crate of a
/// source distribution).
const SOURCE_TREE_MODEL_DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/models/ggpt-synth-small");
/// The shipped model's weights (official key names), embedded at build time (2.5 MB).
const SHIPPED_WEIGHTS: &[u8] = include_bytes!("../models/ggpt-synth-small/model.safetensors");
/// The shipped model's configuration.
const SHIPPED_CONFIG: &str = include_str!("../models/ggpt-synth-small/model_config.json");
/// The shipped model's recommended inference settings.
const SHIPPED_INFERENCE: &str = include_str!("../models/ggpt-synth-small/inference.json");
/// The shipped model's files, as a model folder holds them.
const SHIPPED_FILES: [(&str, &[u8]); 3] = [
    (MODEL_WEIGHTS_FILE, SHIPPED_WEIGHTS),
    (MODEL_CONFIG_FILE, SHIPPED_CONFIG.as_bytes()),
    (INFERENCE_SETTINGS_FILE, SHIPPED_INFERENCE.as_bytes()),
];

/// The shipped model folder on disk, for tools that need files (training from it, copying it):
/// `models/ggpt-synth-small/` next to the running executable (a release archive), else the
/// source tree this crate was built from. A folder counts only when it holds the same files as
/// the embedded model. Inference does not need it: [`ModelSpec::shipped`] loads the embedded
/// copy from memory.
pub fn shipped_model_dir() -> Result<PathBuf> {
    let beside_exe = std::env::current_exe().ok().and_then(|exe| {
        exe.parent()
            .map(|d| d.join("models").join(SHIPPED_MODEL_NAME))
    });
    beside_exe
        .into_iter()
        .chain([PathBuf::from(SOURCE_TREE_MODEL_DIR)])
        .find(|d| holds_shipped_files(d))
        .map(|d| std::fs::canonicalize(&d).unwrap_or(d))
        .ok_or_else(|| ModelError::Missing {
            what: format!(
                "shipped model folder (not on disk next to this executable; the embedded copy is `--weights {SHIPPED}`)"
            ),
            path: PathBuf::from(SOURCE_TREE_MODEL_DIR),
        })
}

/// Whether `dir` holds the embedded shipped model's files, byte for byte.
fn holds_shipped_files(dir: &Path) -> bool {
    SHIPPED_FILES
        .iter()
        .all(|(name, bytes)| std::fs::read(dir.join(name)).is_ok_and(|b| b == *bytes))
}

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
    /// Weights file (`.safetensors` / `.pth` official keys, or `.bpk`); for the embedded shipped
    /// model, the name it is reported under (`<embedded>/ggpt-synth-small/model.safetensors`).
    pub weights: PathBuf,
    /// The weights' bytes when they are embedded in the binary (the shipped model): loaded from
    /// memory, nothing is read from or written to disk.
    pub embedded_weights: Option<&'static [u8]>,
    /// Network configuration.
    pub config: GgptConfig,
    /// Where the configuration came from.
    pub origin: ConfigOrigin,
    /// The model's `inference.json` (next to the weights), when present.
    pub inference: Option<ModelInferenceSettings>,
}

impl ModelSpec {
    /// The shipped model (`ggpt-synth-small`, the `small` configuration), embedded in the binary:
    /// its weights, configuration and `inference.json` come from memory.
    pub fn shipped() -> Result<Self> {
        let base = PathBuf::from("<embedded>").join(SHIPPED_MODEL_NAME);
        let config_path = base.join(MODEL_CONFIG_FILE);
        let config = GgptConfig::from_json_str(SHIPPED_CONFIG, &config_path)?;
        let settings_path = base.join(INFERENCE_SETTINGS_FILE);
        let settings = parse_inference_settings(SHIPPED_INFERENCE, &settings_path)?;
        Ok(ModelSpec {
            weights: base.join(MODEL_WEIGHTS_FILE),
            embedded_weights: Some(SHIPPED_WEIGHTS),
            config,
            origin: ConfigOrigin::File(config_path),
            inference: Some(ModelInferenceSettings {
                path: settings_path,
                settings,
            }),
        })
    }

    /// Whether this is the embedded shipped model.
    pub fn is_embedded(&self) -> bool {
        self.embedded_weights.is_some()
    }

    /// The model layer of the chunk-sampler resolution: the `inference.json` path and its
    /// `chunking` object (`None` without the file).
    pub fn chunking_layer(&self) -> Option<(&Path, Option<&ChunkingSettings>)> {
        self.inference
            .as_ref()
            .map(|m| (m.path.as_path(), m.settings.chunking.as_ref()))
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

/// Reads and validates an `inference.json` file; every problem is a [`ModelError::Settings`]
/// naming the file.
pub fn read_inference_settings(path: &Path) -> Result<InferenceSettings> {
    let text = std::fs::read_to_string(path).map_err(|e| ModelError::Settings {
        path: path.to_path_buf(),
        message: format!("cannot read: {e}"),
    })?;
    parse_inference_settings(&text, path)
}

/// Parses and validates the text of an `inference.json` read from `path` (named in errors).
fn parse_inference_settings(text: &str, path: &Path) -> Result<InferenceSettings> {
    let err = |message: String| ModelError::Settings {
        path: path.to_path_buf(),
        message,
    };
    let settings: InferenceSettings = serde_json::from_str(text).map_err(|e| {
        let kind = if e.is_data() { "invalid settings" } else { "malformed JSON" };
        err(format!("{kind}: {e} (expected {{\"chunking\": {{\"chunk_size\", \"max_pixels\", \"min_dlt\", \"min_pixels\"}}}}, all optional)"))
    })?;
    if let Some(c) = &settings.chunking {
        c.validate(|f| format!("chunking.{f}")).map_err(err)?;
    }
    Ok(settings)
}

/// Resolves `weights` (a file, a model folder holding `model.safetensors`, or [`SHIPPED`] for
/// the embedded shipped model when no file of that name exists) and the configuration:
/// `model_config` file, else `preset`, else `model_config.json` next to the weights. Missing
/// files give [`ModelError::Missing`] naming the path.
pub fn resolve_model(
    weights: &Path,
    model_config: Option<&Path>,
    preset: Option<&str>,
) -> Result<ModelSpec> {
    if weights == Path::new(SHIPPED) && !weights.exists() {
        if model_config.is_some() || preset.is_some() {
            return Err(ModelError::Config {
                path: PathBuf::from(SHIPPED),
                message: format!(
                    "the shipped model has its own configuration: give no model configuration or preset with `{SHIPPED}`"
                ),
            });
        }
        return ModelSpec::shipped();
    }
    let weights = if weights.is_dir() {
        std::iter::once(MODEL_WEIGHTS_FILE)
            .chain(OTHER_WEIGHT_FILES)
            .map(|f| weights.join(f))
            .find(|p| p.is_file())
            .ok_or_else(|| ModelError::Missing {
                what: format!("weights ({MODEL_WEIGHTS_FILE} in the model folder)"),
                path: weights.join(MODEL_WEIGHTS_FILE),
            })?
    } else if weights.is_file() {
        weights.to_path_buf()
    } else {
        return Err(ModelError::Missing {
            what: "weights".into(),
            path: weights.to_path_buf(),
        });
    };
    let (config, origin) = match (model_config, preset) {
        (Some(path), _) => {
            if !path.is_file() {
                return Err(ModelError::Missing {
                    what: "model configuration".into(),
                    path: path.to_path_buf(),
                });
            }
            (
                GgptConfig::from_json_file(path)?,
                ConfigOrigin::File(path.to_path_buf()),
            )
        }
        (None, Some(name)) => (
            GgptConfig::preset(name)?,
            ConfigOrigin::Preset(name.to_string()),
        ),
        (None, None) => {
            let path = weights.with_file_name(MODEL_CONFIG_FILE);
            if !path.is_file() {
                return Err(ModelError::Missing {
                    what: format!(
                        "model configuration (give --model-config FILE or --preset released|small|tiny, or put {MODEL_CONFIG_FILE} next to the weights)"
                    ),
                    path,
                });
            }
            (GgptConfig::from_json_file(&path)?, ConfigOrigin::File(path))
        }
    };
    let settings_path = weights.with_file_name(INFERENCE_SETTINGS_FILE);
    let inference = if settings_path.is_file() {
        let settings = read_inference_settings(&settings_path)?;
        Some(ModelInferenceSettings {
            path: settings_path,
            settings,
        })
    } else {
        None
    };
    Ok(ModelSpec {
        weights,
        embedded_weights: None,
        config,
        origin,
        inference,
    })
}

/// Builds the network on `device` and loads the weights strictly (from memory for the embedded
/// shipped model).
pub fn load_model(spec: &ModelSpec, device: &Device) -> Result<Ggpt> {
    let model = Ggpt::new(&spec.config, device);
    match spec.embedded_weights {
        Some(bytes) => load_safetensors_bytes(model, bytes.to_vec(), &spec.weights),
        None => load_checkpoint(model, &spec.weights),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resolves_folder_config_and_reports_missing_files() {
        let dir = tempfile::tempdir().unwrap();
        let e = resolve_model(&dir.path().join("nope.safetensors"), None, Some("tiny"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("weights not found") && e.contains("nope.safetensors"),
            "{e}"
        );
        let e = resolve_model(dir.path(), None, Some("tiny"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("model.safetensors"), "{e}");
        let w = dir.path().join(MODEL_WEIGHTS_FILE);
        std::fs::write(&w, b"x").unwrap();
        let spec = resolve_model(dir.path(), None, Some("tiny")).unwrap();
        assert_eq!(spec.weights, w);
        assert_eq!(spec.origin, ConfigOrigin::Preset("tiny".into()));
        let e = resolve_model(dir.path(), None, None)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("model_config.json") && e.contains("--model-config"),
            "{e}"
        );
        let e = resolve_model(&w, Some(&dir.path().join("c.json")), None)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("model configuration not found") && e.contains("c.json"),
            "{e}"
        );
        assert!(resolve_model(&w, None, Some("huge")).is_err());
    }

    #[test]
    fn the_shipped_model_is_found_and_embedded() {
        let dir = shipped_model_dir().unwrap();
        assert!(holds_shipped_files(&dir), "{}", dir.display());
        let spec = resolve_model(&dir, None, None).unwrap();
        assert_eq!(spec.weights, dir.join(MODEL_WEIGHTS_FILE));
        assert!(!spec.is_embedded());
        assert!(
            spec.inference.is_some(),
            "the shipped model has an inference.json"
        );
        // The embedded copy: same configuration and settings as the folder, from memory.
        let embedded = resolve_model(Path::new(SHIPPED), None, None).unwrap();
        assert!(embedded.is_embedded());
        assert_eq!(embedded.config, spec.config);
        assert_eq!(
            embedded.inference.as_ref().map(|m| &m.settings),
            spec.inference.as_ref().map(|m| &m.settings)
        );
        let e = resolve_model(Path::new(SHIPPED), None, Some("small"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("own configuration"), "{e}");
        // An incomplete or stale folder does not count.
        let tmp = tempfile::tempdir().unwrap();
        assert!(!holds_shipped_files(tmp.path()));
        for (name, bytes) in SHIPPED_FILES {
            std::fs::write(tmp.path().join(name), bytes).unwrap();
        }
        assert!(holds_shipped_files(tmp.path()));
        std::fs::write(tmp.path().join(MODEL_CONFIG_FILE), b"{}").unwrap();
        assert!(!holds_shipped_files(tmp.path()));
    }

    #[test]
    fn the_embedded_model_loads_like_the_folder() {
        let device = crate::device::device_from_name("cpu").unwrap();
        let folder = load_model(
            &resolve_model(&shipped_model_dir().unwrap(), None, None).unwrap(),
            &device,
        )
        .unwrap();
        let embedded = load_model(&ModelSpec::shipped().unwrap(), &device).unwrap();
        let (a, b) = (all_values(&folder), all_values(&embedded));
        assert!(a.len() >= crate::weights::num_trainable_params(&folder));
        assert!(
            a == b,
            "the embedded copy loads other values than the folder"
        );
    }

    /// Every float value of the model's parameters and buffers, in visiting order.
    fn all_values(m: &Ggpt) -> Vec<f32> {
        use burn::module::{Module, ModuleVisitor, Param};
        use burn::tensor::Tensor;
        struct Collect(Vec<f32>);
        impl ModuleVisitor for Collect {
            fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
                let data = param.val().into_data();
                self.0.extend(data.iter::<f32>());
            }
        }
        let mut c = Collect(Vec::new());
        m.visit(&mut c);
        c.0
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
    fn bad_inference_json_gives_clear_errors() {
        let dir = tempfile::tempdir().unwrap();
        let cases = [
            (
                "{\"chunking\": {\"max_pixels\": 10000,}}",
                "malformed JSON: trailing comma",
            ),
            (
                r#"{"chunking": {"max_pixel": 10000}}"#,
                "invalid settings: unknown field `max_pixel`",
            ),
            (
                r#"{"chunking": {}, "fusion": "mean"}"#,
                "unknown field `fusion`",
            ),
            (
                r#"{"chunking": {"max_pixels": -5}}"#,
                "invalid settings: invalid value: integer `-5`",
            ),
            (
                r#"{"chunking": {"chunk_size": "0.2"}}"#,
                "invalid settings: invalid type: string",
            ),
            (
                r#"{"chunking": {"chunk_size": 0}}"#,
                "chunking.chunk_size = 0",
            ),
            (
                r#"{"chunking": {"max_pixels": 0}}"#,
                "chunking.max_pixels = 0",
            ),
            (r#"[1, 2]"#, "invalid settings"),
            ("", "malformed JSON"),
        ];
        for (text, want) in cases {
            let e = spec_with(dir.path(), Some(text)).unwrap_err();
            assert!(matches!(e, ModelError::Settings { .. }), "{text}: {e:?}");
            let e = e.to_string();
            assert!(
                e.contains(want)
                    && e.contains("inference.json")
                    && e.contains(&dir.path().display().to_string()),
                "{text}: {e}"
            );
        }
        // Next to a weights file given directly, too.
        let w = dir.path().join("weights.bpk");
        std::fs::write(&w, b"x").unwrap();
        let e = resolve_model(&w, None, Some("tiny"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("inference.json") && e.contains("malformed JSON"),
            "{e}"
        );
        std::fs::remove_file(dir.path().join(INFERENCE_SETTINGS_FILE)).unwrap();
        let spec = resolve_model(&w, None, Some("tiny")).unwrap();
        assert!(spec.inference.is_none());
    }
}
