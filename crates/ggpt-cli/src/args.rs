//! `clap` argument groups shared by several binaries. The same setting has the same flag in
//! every binary; older spellings are kept as hidden aliases for one release
//! (`docs/inference.md`, "Flag changes"). Every group is `serde`-serialisable, so a run records
//! the values it used in its `config.json`.

use std::fmt;
use std::path::PathBuf;
use std::str::FromStr;

use clap::{Args, ValueEnum};
use ggpt_core::chunking::ChunkingSettings;
use serde::{Deserialize, Serialize};

/// A built-in network configuration (`ggpt_model::GgptConfig::preset`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ModelPreset {
    /// The released configuration (53.4 M parameters).
    Released,
    /// The small configuration (the fixtures and the shipped model).
    Small,
    /// A tiny configuration for tests and demonstrations.
    Tiny,
}

impl ModelPreset {
    /// The preset's name, as `GgptConfig::preset` takes it.
    pub fn name(self) -> &'static str {
        match self {
            ModelPreset::Released => "released",
            ModelPreset::Small => "small",
            ModelPreset::Tiny => "tiny",
        }
    }
}

/// Which model to run: weights plus a configuration (a JSON file or a built-in preset).
#[derive(Args, Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ModelArgs {
    /// Weights: an official `.pth` / `.safetensors`, a project `.bpk`, a model folder
    /// (`model.safetensors` + `model_config.json` [+ `inference.json`]), `shipped` (the shipped
    /// model embedded in the binary, where the command runs inference) or, where the command
    /// says so, a training run or checkpoint directory.
    #[arg(long, alias = "model", value_name = "PATH")]
    pub weights: Option<PathBuf>,
    /// Model configuration JSON (the official `model_config` object, or a file with a
    /// `model_config` key). Default: `model_config.json` next to the weights.
    #[arg(long, conflicts_with = "preset", value_name = "FILE")]
    pub model_config: Option<PathBuf>,
    /// Built-in configuration instead of a file.
    #[arg(long, value_enum)]
    pub preset: Option<ModelPreset>,
    /// Old spelling of `--model-config FILE` / `--preset NAME` (a preset name or a file).
    #[arg(long = "config", hide = true, conflicts_with_all = ["model_config", "preset"])]
    #[serde(skip)]
    pub legacy_config: Option<String>,
}

impl ModelArgs {
    /// Folds the hidden `--config` into `--model-config` / `--preset`: a preset name becomes
    /// the preset, anything else a configuration file.
    pub fn normalized(&self) -> ModelArgs {
        let mut out = self.clone();
        if let Some(c) = out.legacy_config.take() {
            match ModelPreset::from_str(&c, true) {
                Ok(p) => out.preset = Some(p),
                Err(_) => out.model_config = Some(PathBuf::from(c)),
            }
        }
        out
    }

    /// The weights, or an error naming the flag.
    pub fn require_weights(&self) -> anyhow::Result<&PathBuf> {
        self.weights
            .as_ref()
            .ok_or_else(|| anyhow::anyhow!("give --weights PATH"))
    }

    /// The preset's name, if one was chosen.
    pub fn preset_name(&self) -> Option<&'static str> {
        self.preset.map(ModelPreset::name)
    }
}

/// A compute backend of `--device`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    /// The fastest CPU backend compiled in (flex, else ndarray).
    Cpu,
    /// Burn's ndarray backend.
    Ndarray,
    /// Burn's flex backend.
    Flex,
    /// Burn's wgpu backend (Vulkan / Metal / DX12).
    Wgpu,
    /// Burn's CUDA backend (the `cuda` feature).
    Cuda,
}

/// `--device`: a backend, with an adapter index for `wgpu:N` / `cuda:N`.
///
/// Not a `clap::ValueEnum` because of the index; parsing still checks the value against the
/// closed list and says what is accepted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DeviceArg {
    /// The backend.
    pub backend: Backend,
    /// Adapter index (`wgpu:1`); only for `wgpu` and `cuda`.
    pub index: Option<usize>,
}

impl DeviceArg {
    /// `cpu`.
    pub const CPU: DeviceArg = DeviceArg {
        backend: Backend::Cpu,
        index: None,
    };
}

impl Default for DeviceArg {
    fn default() -> Self {
        DeviceArg::CPU
    }
}

/// The values `--device` accepts, for messages and `--help`.
pub const DEVICE_VALUES: &str = "cpu, ndarray, flex, wgpu, wgpu:N, cuda, cuda:N";

impl FromStr for DeviceArg {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let bad = || format!("unknown device {s:?} (one of {DEVICE_VALUES})");
        let (base, index) = match s.split_once(':') {
            Some((b, i)) => (b, Some(i.parse::<usize>().map_err(|_| bad())?)),
            None => (s, None),
        };
        let backend = match base {
            "cpu" => Backend::Cpu,
            "ndarray" => Backend::Ndarray,
            "flex" => Backend::Flex,
            "wgpu" => Backend::Wgpu,
            "cuda" => Backend::Cuda,
            _ => return Err(bad()),
        };
        if index.is_some() && !matches!(backend, Backend::Wgpu | Backend::Cuda) {
            return Err(format!("{s:?}: only wgpu and cuda take an adapter index"));
        }
        Ok(DeviceArg { backend, index })
    }
}

impl fmt::Display for DeviceArg {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let base = match self.backend {
            Backend::Cpu => "cpu",
            Backend::Ndarray => "ndarray",
            Backend::Flex => "flex",
            Backend::Wgpu => "wgpu",
            Backend::Cuda => "cuda",
        };
        match self.index {
            Some(i) => write!(f, "{base}:{i}"),
            None => f.write_str(base),
        }
    }
}

impl Serialize for DeviceArg {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for DeviceArg {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        s.parse().map_err(serde::de::Error::custom)
    }
}

/// Where the network runs.
#[derive(Args, Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct DeviceArgs {
    /// Compute device: `cpu` (the fastest CPU backend), `ndarray`, `flex`, `wgpu[:N]` or
    /// `cuda[:N]` (with the `cuda` feature).
    #[arg(long, default_value = "cpu", value_name = "DEVICE")]
    pub device: DeviceArg,
    /// CPU threads of the backends (0 = all cores).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
}

/// The chunk sampler (`pipeline.md` §5). A flag that is not given comes from the model
/// folder's `inference.json` where the command reads one, else from the official default.
#[derive(Args, Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct ChunkingArgs {
    /// Chunk sampler: cube half-size as a fraction of the scene radius R [default: 0.2].
    #[arg(long, value_name = "F")]
    pub chunk_size: Option<f64>,
    /// Chunk sampler: maximum pixels per chunk; a larger cube shrinks by 0.9 until it fits
    /// [default: 400000].
    #[arg(long, alias = "max-pixels", value_name = "N")]
    pub max_chunk_pixels: Option<usize>,
    /// Chunk sampler: initial minimum number of DLT pixels of an accepted chunk (lowered on
    /// rejections) [default: 100].
    #[arg(long, alias = "min-dlt", value_name = "N")]
    pub min_chunk_dlt: Option<usize>,
    /// Chunk sampler: initial minimum number of pixels of an accepted chunk (lowered on
    /// rejections) [default: 10000].
    #[arg(long, alias = "min-pixels", value_name = "N")]
    pub min_chunk_pixels: Option<usize>,
}

impl ChunkingArgs {
    /// The explicitly given values.
    pub fn settings(&self) -> ChunkingSettings {
        ChunkingSettings {
            chunk_size: self.chunk_size,
            max_pixels: self.max_chunk_pixels,
            min_dlt: self.min_chunk_dlt,
            min_pixels: self.min_chunk_pixels,
        }
    }

    /// The flag of a [`ChunkingSettings`] field, for messages (`max_pixels` ->
    /// `--max-chunk-pixels`).
    pub fn flag(field: &str) -> String {
        match field {
            "chunk_size" => "--chunk-size".into(),
            "max_pixels" => "--max-chunk-pixels".into(),
            "min_dlt" => "--min-chunk-dlt".into(),
            "min_pixels" => "--min-chunk-pixels".into(),
            other => format!("--{}", other.replace('_', "-")),
        }
    }
}

/// An SfM threshold preset (`ggpt_sfm::masks::Preset`, `sfm.md` §5).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SfmPresetArg {
    /// The official `benchmark_sfm.yaml` (the paper's evaluation).
    Benchmark,
    /// The official `demo.yaml` (the user-facing default of every command).
    #[default]
    Demo,
    /// The official recipe for more than 50 views.
    ManyViews,
}

impl SfmPresetArg {
    /// The preset's name, as `ggpt_sfm::masks::Preset::parse` takes it.
    pub fn name(self) -> &'static str {
        match self {
            SfmPresetArg::Benchmark => "benchmark",
            SfmPresetArg::Demo => "demo",
            SfmPresetArg::ManyViews => "many-views",
        }
    }
}

/// A synthetic scene family (`ggpt_synth::SceneKind`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SceneKindArg {
    /// A furnished room seen from inside.
    #[default]
    Room,
    /// An object on a ground plane seen from around.
    Object,
}

impl SceneKindArg {
    /// The kind's name, as `ggpt_synth::SceneKind::parse` takes it.
    pub fn name(self) -> &'static str {
        match self {
            SceneKindArg::Room => "room",
            SceneKindArg::Object => "object",
        }
    }
}

/// Simulation regime of synthetic scenes (`ggpt_synth::Regime`, `docs/synthetic.md`).
#[derive(clap::ValueEnum, Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RegimeArg {
    /// Realistic matcher failures and VGGT-like structured feed-forward error, calibrated to the
    /// paper's ranges (SfM covers 20-70 % of the pixels).
    #[default]
    Benchmark,
    /// The first regime: dense, near-exact SfM guidance (reproduces earlier numbers).
    Easy,
}

impl RegimeArg {
    /// The regime's name, as `ggpt_synth::Regime::parse` takes it.
    pub fn name(self) -> &'static str {
        match self {
            RegimeArg::Benchmark => "benchmark",
            RegimeArg::Easy => "easy",
        }
    }
}

/// Progress bars on or off.
#[derive(Args, Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct ProgressArgs {
    /// No progress bars (logs still go to stderr; `RUST_LOG=warn` silences them).
    #[arg(long, alias = "no-progress", global = true)]
    pub quiet: bool,
}

impl ProgressArgs {
    /// Whether bars are drawn.
    pub fn bars(&self) -> bool {
        !self.quiet
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser, Debug)]
    struct Cli {
        #[command(flatten)]
        model: ModelArgs,
        #[command(flatten)]
        device: DeviceArgs,
        #[command(flatten)]
        chunking: ChunkingArgs,
        #[command(flatten)]
        progress: ProgressArgs,
        #[arg(long, value_enum, default_value_t)]
        sfm_preset: SfmPresetArg,
    }

    fn parse(args: &[&str]) -> Result<Cli, clap::Error> {
        Cli::try_parse_from(std::iter::once("x").chain(args.iter().copied()))
    }

    #[test]
    fn device_values_round_trip_and_bad_ones_are_named() {
        for s in ["cpu", "ndarray", "flex", "wgpu", "wgpu:1", "cuda", "cuda:0"] {
            let d: DeviceArg = s.parse().unwrap();
            assert_eq!(d.to_string(), s);
            let j = serde_json::to_string(&d).unwrap();
            assert_eq!(serde_json::from_str::<DeviceArg>(&j).unwrap(), d);
        }
        for s in ["gpu", "wgpu:x", "cpu:1", "", "wgpu:"] {
            let e = s.parse::<DeviceArg>().unwrap_err();
            assert!(e.contains(s) || s.is_empty(), "{e}");
        }
        let e = parse(&["--device", "tpu"]).unwrap_err().to_string();
        assert!(e.contains("tpu") && e.contains("wgpu:N"), "{e}");
    }

    #[test]
    fn old_spellings_are_hidden_aliases() {
        let c = parse(&["--max-pixels", "5", "--min-dlt", "3", "--no-progress"]).unwrap();
        assert_eq!(c.chunking.max_chunk_pixels, Some(5));
        assert_eq!(c.chunking.min_chunk_dlt, Some(3));
        assert!(c.progress.quiet);
        let c = parse(&["--model", "w.pth", "--config", "released"]).unwrap();
        let m = c.model.normalized();
        assert_eq!(m.weights, Some(PathBuf::from("w.pth")));
        assert_eq!(m.preset, Some(ModelPreset::Released));
        let m = parse(&["--config", "cfg.json"]).unwrap().model.normalized();
        assert_eq!(m.model_config, Some(PathBuf::from("cfg.json")));
        assert!(parse(&["--config", "a.json", "--preset", "small"]).is_err());
        assert!(parse(&["--model-config", "a.json", "--preset", "small"]).is_err());
    }

    #[test]
    fn defaults_and_flags_for_messages() {
        let c = parse(&[]).unwrap();
        assert_eq!(c.device.device, DeviceArg::CPU);
        assert_eq!(c.sfm_preset, SfmPresetArg::Demo);
        assert!(c.progress.bars());
        assert_eq!(ChunkingArgs::flag("max_pixels"), "--max-chunk-pixels");
        let c = parse(&["--chunk-size", "0.3", "--min-chunk-pixels", "9"]).unwrap();
        let s = c.chunking.settings();
        assert_eq!((s.chunk_size, s.min_pixels), (Some(0.3), Some(9)));
        let j = serde_json::to_value(&c.device).unwrap();
        assert_eq!(j["device"], "cpu");
    }

    #[test]
    fn help_hides_the_old_spellings() {
        use clap::CommandFactory;
        let help = Cli::command().render_long_help().to_string();
        assert!(help.contains("--max-chunk-pixels") && help.contains("--model-config"));
        assert!(!help.contains("--max-pixels") && !help.contains("--no-progress"));
        assert!(!help.contains("--config "), "{help}");
    }
}
