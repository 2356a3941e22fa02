//! Network configuration (network.md §1): the official `model_config` JSON as data.
//!
//! The same code runs the released model, the small fixture model and a tiny test model;
//! only the numbers in [`GgptConfig`] differ.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::{ModelError, Result};

/// Number of encoder stages / resolution levels (network.md §1.1).
pub const NUM_LEVELS: usize = 5;
/// Number of decoder stages.
pub const NUM_DEC_STAGES: usize = NUM_LEVELS - 1;
/// Input channels of a token: 16 type + 202 guidance channels (network.md §3.3).
pub const IN_CHANNELS: usize = 218;
/// Width of a type embedding (network.md §3.2).
pub const TYPE_EMBED_DIM: usize = 16;
/// Channels of the plan's `feat_no_embed` (218 - 16).
pub const FEAT_NO_EMBED_DIM: usize = IN_CHANNELS - TYPE_EMBED_DIM;
/// Serialization orders in row order (network.md §4.6); no shuffling.
pub const ORDERS: [&str; 4] = ["z", "z-trans", "hilbert", "hilbert-trans"];

fn default_in_channels() -> usize {
    IN_CHANNELS
}
fn default_grid() -> u32 {
    384
}
fn default_type_dim() -> usize {
    TYPE_EMBED_DIM
}
fn default_sin_dim() -> usize {
    32
}
fn default_mlp_ratio() -> usize {
    4
}
fn default_drop_path() -> f64 {
    0.3
}
fn default_bn_eps() -> f64 {
    1e-3
}
fn default_bn_momentum() -> f64 {
    0.01
}
fn default_ln_eps() -> f64 {
    1e-5
}
fn default_order() -> Vec<String> {
    ORDERS.iter().map(|s| (*s).to_string()).collect()
}
fn default_stride() -> Vec<usize> {
    vec![2; NUM_DEC_STAGES]
}

/// GGPT model configuration; deserialises the official `model_config` JSON object
/// (unknown fields such as `enc_dim`, `output_dim`, `enable_flash` are ignored).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GgptConfig {
    /// Encoder channels per stage `E_s` (5 stages).
    pub enc_channels: Vec<usize>,
    /// Blocks per encoder stage.
    pub enc_depths: Vec<usize>,
    /// Attention heads per encoder stage.
    pub enc_num_head: Vec<usize>,
    /// Decoder channels `D_s`, index 0 = finest (4 stages).
    pub dec_channels: Vec<usize>,
    /// Blocks per decoder stage.
    pub dec_depths: Vec<usize>,
    /// Attention heads per decoder stage.
    pub dec_num_head: Vec<usize>,
    /// Attention window (patch) size `P`, all stages.
    pub patch_size: usize,
    /// Head hidden width `W`.
    pub head_width: usize,
    /// Token input channels (218).
    #[serde(default = "default_in_channels")]
    pub in_channels: usize,
    /// Voxel grid resolution over `[-1, 1]^3` (384).
    #[serde(default = "default_grid")]
    pub grid_resolution: u32,
    /// Type-embedding width (16).
    #[serde(default = "default_type_dim")]
    pub type_embed_dim: usize,
    /// Sin+cos channels per axis of the positional encoding (32).
    #[serde(default = "default_sin_dim")]
    pub sinusoidal_dim: usize,
    /// MLP hidden ratio (4).
    #[serde(default = "default_mlp_ratio")]
    pub mlp_ratio: usize,
    /// Maximum drop-path rate in training (0.3, network.md §11.3).
    #[serde(default = "default_drop_path")]
    pub drop_path: f64,
    /// BatchNorm epsilon (1e-3).
    #[serde(default = "default_bn_eps")]
    pub bn_eps: f64,
    /// BatchNorm momentum, PyTorch convention (0.01).
    #[serde(default = "default_bn_momentum")]
    pub bn_momentum: f64,
    /// LayerNorm epsilon (1e-5).
    #[serde(default = "default_ln_eps")]
    pub ln_eps: f64,
    /// Serialization orders; must be `z, z-trans, hilbert, hilbert-trans`.
    #[serde(default = "default_order")]
    pub order: Vec<String>,
    /// Pooling strides; must all be 2.
    #[serde(default = "default_stride")]
    pub stride: Vec<usize>,
}

/// Largest channel count of a stage [`GgptConfig::validate`] accepts (released: 512).
pub const MAX_CHANNELS: usize = 4096;
/// Largest number of blocks in a stage (released: 6).
pub const MAX_DEPTH: usize = 64;
/// Largest MLP expansion ratio (released: 4).
pub const MAX_MLP_RATIO: usize = 16;
/// Largest serialization patch size (released: 1024).
pub const MAX_PATCH_SIZE: usize = 1 << 24;
/// Largest trainable parameter count (released: 53,409,828; 2^30 is 4 GiB of f32 weights).
pub const MAX_PARAMETERS: usize = 1 << 30;

impl GgptConfig {
    /// The released checkpoint's configuration (network.md §1.1), 53,409,828 parameters.
    pub fn released() -> Self {
        Self::from_parts(
            [128, 128, 256, 256, 512],
            [2, 2, 2, 6, 2],
            [2, 4, 8, 16, 32],
            [96, 96, 128, 256],
            [2, 2, 2, 2],
            [4, 4, 8, 16],
            1024,
            256,
        )
    }

    /// The `ggpt_small` fixture configuration (network.md §1.2), 623,772 parameters.
    pub fn small() -> Self {
        Self::from_parts(
            [16, 16, 24, 32, 32],
            [2, 2, 2, 6, 2],
            [2, 2, 2, 4, 2],
            [16, 16, 24, 32],
            [2, 2, 2, 2],
            [2, 2, 3, 2],
            128,
            64,
        )
    }

    /// A tiny configuration for fast tests (same code paths; two blocks in enc0/dec0 so
    /// both the z and z-trans rows and the stale-conv-input quirk are exercised).
    pub fn tiny() -> Self {
        Self::from_parts(
            [8, 8, 16, 16, 16],
            [2, 1, 1, 1, 1],
            [2, 2, 2, 2, 2],
            [8, 8, 8, 16],
            [1, 1, 1, 2],
            [2, 2, 2, 2],
            32,
            16,
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn from_parts(
        enc_channels: [usize; 5],
        enc_depths: [usize; 5],
        enc_num_head: [usize; 5],
        dec_channels: [usize; 4],
        dec_depths: [usize; 4],
        dec_num_head: [usize; 4],
        patch_size: usize,
        head_width: usize,
    ) -> Self {
        Self {
            enc_channels: enc_channels.to_vec(),
            enc_depths: enc_depths.to_vec(),
            enc_num_head: enc_num_head.to_vec(),
            dec_channels: dec_channels.to_vec(),
            dec_depths: dec_depths.to_vec(),
            dec_num_head: dec_num_head.to_vec(),
            patch_size,
            head_width,
            in_channels: IN_CHANNELS,
            grid_resolution: default_grid(),
            type_embed_dim: TYPE_EMBED_DIM,
            sinusoidal_dim: default_sin_dim(),
            mlp_ratio: default_mlp_ratio(),
            drop_path: default_drop_path(),
            bn_eps: default_bn_eps(),
            bn_momentum: default_bn_momentum(),
            ln_eps: default_ln_eps(),
            order: default_order(),
            stride: default_stride(),
        }
    }

    /// A preset by name: `released`, `small` or `tiny`.
    pub fn preset(name: &str) -> Result<Self> {
        match name {
            "released" => Ok(Self::released()),
            "small" => Ok(Self::small()),
            "tiny" => Ok(Self::tiny()),
            other => Err(ModelError::Config {
                path: "<preset>".into(),
                message: format!("unknown preset '{other}' (expected released, small or tiny)"),
            }),
        }
    }

    /// Parses a JSON text holding either the `model_config` object itself or an object with a
    /// `model_config` key (e.g. a fixture `manifest.json`), then validates it.
    pub fn from_json_str(text: &str, origin: &Path) -> Result<Self> {
        let err = |message: String| ModelError::Config {
            path: origin.to_path_buf(),
            message,
        };
        let value: serde_json::Value =
            serde_json::from_str(text).map_err(|e| err(format!("invalid JSON: {e}")))?;
        let object = match value.get("model_config") {
            Some(inner) => inner.clone(),
            None => value,
        };
        let cfg: Self = serde_json::from_value(object).map_err(|e| err(format!("{e}")))?;
        cfg.validate().map_err(err)?;
        Ok(cfg)
    }

    /// Reads and parses a JSON configuration file (see [`GgptConfig::from_json_str`]).
    pub fn from_json_file(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| ModelError::Config {
            path: path.to_path_buf(),
            message: format!("cannot read: {e}"),
        })?;
        Self::from_json_str(&text, path)
    }

    /// Checks the structural constraints the implementation relies on.
    pub fn validate(&self) -> std::result::Result<(), String> {
        let lens = [
            ("enc_channels", self.enc_channels.len(), NUM_LEVELS),
            ("enc_depths", self.enc_depths.len(), NUM_LEVELS),
            ("enc_num_head", self.enc_num_head.len(), NUM_LEVELS),
            ("dec_channels", self.dec_channels.len(), NUM_DEC_STAGES),
            ("dec_depths", self.dec_depths.len(), NUM_DEC_STAGES),
            ("dec_num_head", self.dec_num_head.len(), NUM_DEC_STAGES),
            ("stride", self.stride.len(), NUM_DEC_STAGES),
        ];
        for (name, len, want) in lens {
            if len != want {
                return Err(format!("{name} has {len} entries, expected {want}"));
            }
        }
        for s in 0..NUM_LEVELS {
            let (c, h) = (self.enc_channels[s], self.enc_num_head[s]);
            if c == 0 || h == 0 || c % h != 0 {
                return Err(format!(
                    "encoder stage {s}: {c} channels not divisible by {h} heads"
                ));
            }
            if self.enc_depths[s] == 0 {
                return Err(format!("encoder stage {s} has no block"));
            }
        }
        for s in 0..NUM_DEC_STAGES {
            let (c, h) = (self.dec_channels[s], self.dec_num_head[s]);
            if c == 0 || h == 0 || c % h != 0 {
                return Err(format!(
                    "decoder stage {s}: {c} channels not divisible by {h} heads"
                ));
            }
            if self.dec_depths[s] == 0 {
                return Err(format!("decoder stage {s} has no block"));
            }
        }
        if self.in_channels != IN_CHANNELS || self.type_embed_dim != TYPE_EMBED_DIM {
            return Err(format!(
                "in_channels {} / type_embed_dim {} unsupported (expected {IN_CHANNELS} / {TYPE_EMBED_DIM})",
                self.in_channels, self.type_embed_dim
            ));
        }
        if self.sinusoidal_dim != 32 {
            return Err(format!(
                "sinusoidal_dim {} unsupported (expected 32)",
                self.sinusoidal_dim
            ));
        }
        if self
            .order
            .iter()
            .map(String::as_str)
            .ne(ORDERS.iter().copied())
        {
            return Err(format!(
                "order {:?} unsupported (expected {ORDERS:?})",
                self.order
            ));
        }
        if self.stride.iter().any(|&s| s != 2) {
            return Err(format!(
                "stride {:?} unsupported (expected all 2)",
                self.stride
            ));
        }
        if self.patch_size == 0 || self.head_width == 0 || self.mlp_ratio == 0 {
            return Err("patch_size, head_width and mlp_ratio must be positive".into());
        }
        if !(0.0..1.0).contains(&self.drop_path) {
            return Err(format!("drop_path {} outside [0, 1)", self.drop_path));
        }
        // Burn's BatchNorm / LayerNorm constructors panic on these; here they are errors.
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if !positive(self.bn_eps) || !positive(self.ln_eps) {
            return Err(format!(
                "bn_eps {} / ln_eps {}: must be finite and > 0",
                self.bn_eps, self.ln_eps
            ));
        }
        if !(self.bn_momentum.is_finite() && (0.0..=1.0).contains(&self.bn_momentum)) {
            return Err(format!("bn_momentum {} outside [0, 1]", self.bn_momentum));
        }
        // Sanity bounds, far above any published configuration, so that a corrupt or edited
        // configuration is an error here and not a multi-terabyte allocation in `Ggpt::new`.
        let channels = self.enc_channels.iter().chain(&self.dec_channels);
        if let Some(c) = channels.into_iter().find(|&&c| c > MAX_CHANNELS) {
            return Err(format!(
                "{c} channels in a stage (at most {MAX_CHANNELS} supported)"
            ));
        }
        if let Some(d) = self
            .enc_depths
            .iter()
            .chain(&self.dec_depths)
            .find(|&&d| d > MAX_DEPTH)
        {
            return Err(format!(
                "{d} blocks in a stage (at most {MAX_DEPTH} supported)"
            ));
        }
        if self.mlp_ratio > MAX_MLP_RATIO
            || self.head_width > MAX_CHANNELS
            || self.patch_size > MAX_PATCH_SIZE
        {
            return Err(format!(
                "mlp_ratio {} / head_width {} / patch_size {} out of range (at most {MAX_MLP_RATIO} / {MAX_CHANNELS} / {MAX_PATCH_SIZE})",
                self.mlp_ratio, self.head_width, self.patch_size
            ));
        }
        let params = self.parameter_count();
        if params > MAX_PARAMETERS {
            return Err(format!(
                "{params} parameters (at most {MAX_PARAMETERS} supported; the released network has 53,409,828)"
            ));
        }
        Ok(())
    }

    /// Decoder input channels of stage `s` from the coarser level (`D_{s+1}`, `D_4 := E_4`).
    pub fn dec_in_channels(&self, s: usize) -> usize {
        if s + 1 < NUM_DEC_STAGES {
            self.dec_channels[s + 1]
        } else {
            self.enc_channels[NUM_LEVELS - 1]
        }
    }

    /// Closed-form trainable parameter count (network.md §1.3).
    pub fn parameter_count(&self) -> usize {
        let block = |c: usize| {
            27 * c * c
                + c
                + c * c
                + c
                + 2 * c
                + 2 * c
                + 3 * c * c
                + 3 * c
                + c * c
                + c
                + 2 * c
                + self.mlp_ratio * c * c
                + self.mlp_ratio * c
                + self.mlp_ratio * c * c
                + c
        };
        let e = &self.enc_channels;
        let d = &self.dec_channels;
        let mut n = 2 * self.type_embed_dim;
        n += self.in_channels * e[0] + 3 * e[0];
        for s in 0..NUM_LEVELS {
            if s > 0 {
                n += e[s - 1] * e[s] + 3 * e[s];
            }
            n += self.enc_depths[s] * block(e[s]);
        }
        for s in 0..NUM_DEC_STAGES {
            n += (self.dec_in_channels(s) + e[s]) * d[s] + 6 * d[s];
            n += self.dec_depths[s] * block(d[s]);
        }
        let w = self.head_width;
        n += (d[0] + self.in_channels) * w + w + w * w + w + 4 * w + 4;
        n
    }

    /// Drop-path rate of every encoder block, in stage order (network.md §11.3).
    pub fn enc_drop_path_rates(&self) -> Vec<Vec<f64>> {
        let total: usize = self.enc_depths.iter().sum();
        let rates = linspace(self.drop_path, total);
        let mut out = Vec::with_capacity(NUM_LEVELS);
        let mut k = 0;
        for &depth in &self.enc_depths {
            out.push(rates[k..k + depth].to_vec());
            k += depth;
        }
        out
    }

    /// Drop-path rate of every decoder block, `[stage s][block i]` (network.md §11.3:
    /// `linspace(0, max, total)` cut by stage `s = 0..3`, reversed within the stage).
    pub fn dec_drop_path_rates(&self) -> Vec<Vec<f64>> {
        let total: usize = self.dec_depths.iter().sum();
        let rates = linspace(self.drop_path, total);
        let mut out = Vec::with_capacity(NUM_DEC_STAGES);
        let mut k = 0;
        for &depth in &self.dec_depths {
            let mut stage = rates[k..k + depth].to_vec();
            stage.reverse();
            out.push(stage);
            k += depth;
        }
        out
    }
}

/// `n` evenly spaced values from 0 to `max` inclusive (torch.linspace semantics).
fn linspace(max: f64, n: usize) -> Vec<f64> {
    match n {
        0 => Vec::new(),
        1 => vec![0.0],
        _ => (0..n).map(|i| max * i as f64 / (n - 1) as f64).collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn released_parameter_count() {
        assert_eq!(GgptConfig::released().parameter_count(), 53_409_828);
        assert!(GgptConfig::released().validate().is_ok());
    }

    #[test]
    fn small_parameter_count() {
        assert_eq!(GgptConfig::small().parameter_count(), 623_772);
    }

    #[test]
    fn parses_fixture_manifest_and_bare_config() {
        let path = Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../../shared/fixtures/ggpt_small/manifest.json"
        ));
        let cfg = GgptConfig::from_json_file(path).expect("manifest parses");
        assert_eq!(cfg, GgptConfig::small());
        let text = std::fs::read_to_string(path).expect("readable");
        let v: serde_json::Value = serde_json::from_str(&text).expect("json");
        let bare = serde_json::to_string(&v["model_config"]).expect("json");
        assert_eq!(
            GgptConfig::from_json_str(&bare, Path::new("<json>")).expect("bare"),
            cfg
        );
    }

    #[test]
    fn rejects_bad_configs() {
        let mut c = GgptConfig::small();
        c.enc_num_head[2] = 5;
        assert!(c.validate().unwrap_err().contains("encoder stage 2"));
        let mut c = GgptConfig::small();
        c.dec_depths.pop();
        assert!(c.validate().unwrap_err().contains("dec_depths"));
        assert!(GgptConfig::preset("huge").is_err());
    }

    #[test]
    fn drop_path_rates_match_spec_table() {
        let c = GgptConfig::released();
        let enc = c.enc_drop_path_rates();
        assert!((enc[0][1] - 0.023077).abs() < 1e-6);
        assert!((enc[3][0] - 0.138462).abs() < 1e-6);
        assert!((enc[4][1] - 0.3).abs() < 1e-12);
        let dec = c.dec_drop_path_rates();
        assert!((dec[0][0] - 0.042857).abs() < 1e-6 && dec[0][1] == 0.0);
        assert!((dec[2][0] - 0.214286).abs() < 1e-6);
        assert!((dec[3][0] - 0.3).abs() < 1e-12 && (dec[3][1] - 0.257143).abs() < 1e-6);
    }
}
