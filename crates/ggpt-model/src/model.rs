//! The whole GGPT network (network.md §3.2, §5–§10): guidance encoding, PTv3 backbone, head.

use burn::module::{Module, Param};
use burn::nn::{BatchNorm, Initializer};
use burn::tensor::{Device, Tensor};

use crate::block::Block;
use crate::config::{GgptConfig, NUM_DEC_STAGES, NUM_LEVELS, TYPE_EMBED_DIM};
use crate::error::{ModelError, Result};
use crate::head::Head;
use crate::linear_bn::LinearBnGelu;
use crate::pooling::SerializedPooling;
use crate::prepared::PreparedBatch;
use crate::readback::read_tensor_f32;
use crate::unpooling::Unpooling;

/// Encoder stage `s`: pooling from level `s - 1` (absent for `s = 0`) and its blocks.
#[derive(Module, Debug)]
pub struct EncoderStage {
    /// Serialized pooling (official `enc.enc{s}.down`).
    pub down: Option<SerializedPooling>,
    /// Blocks (official `enc.enc{s}.block{i}`).
    pub blocks: Vec<Block>,
}

/// Decoder stage `s`: unpooling from level `s + 1` and its blocks.
#[derive(Module, Debug)]
pub struct DecoderStage {
    /// Unpooling (official `dec.dec{s}.up`).
    pub up: Unpooling,
    /// Blocks (official `dec.dec{s}.block{i}`).
    pub blocks: Vec<Block>,
}

/// GGPT: type embeddings, stem, 5 encoder stages, 4 decoder stages (index = level), head.
#[derive(Module, Debug)]
pub struct Ggpt {
    /// `e_ff` `[16]`.
    pub ff_type_embed: Param<Tensor<1>>,
    /// `e_dlt` `[16]`.
    pub dlt_type_embed: Param<Tensor<1>>,
    /// Stem `GELU(BN(Linear(218 -> E_0)))` (official `backbone.backbone.embedding`).
    pub embedding: LinearBnGelu,
    /// Encoder stages 0..=4.
    pub enc: Vec<EncoderStage>,
    /// Decoder stages 0..=3 (index 0 = finest; run 3, 2, 1, 0).
    pub dec: Vec<DecoderStage>,
    /// Residual head.
    pub head: Head,
}

/// Network outputs over all tokens of a batch (token order, chunks concatenated).
#[derive(Debug, Clone)]
pub struct GgptOutput {
    /// `[N, 3]` refined token positions (normalised chunk coordinates).
    pub tokens_xyz: Tensor<2>,
    /// `[N]` confidences `1 + exp(h_3)`.
    pub tokens_conf: Tensor<1>,
    /// `[N, 4]` head pre-activation `h`.
    pub pre_activation: Tensor<2>,
}

/// Host-side outputs of one chunk (network.md §10), normalised chunk coordinates.
#[derive(Debug, Clone, PartialEq)]
pub struct ChunkOutput {
    /// `[K, 3]` refined dense points.
    pub ff_pts_out: Vec<[f32; 3]>,
    /// `[K]` dense confidences.
    pub ff_pts_conf_out: Vec<f32>,
    /// `[K, 3]` DLT-token outputs at their pixels, zeros where the pixel has no DLT point.
    pub geo_pts_out: Vec<[f32; 3]>,
    /// `[K]` DLT-token confidences at their pixels, zeros elsewhere.
    pub geo_pts_conf_out: Vec<f32>,
    /// `[N_b, 3]` all tokens of the chunk.
    pub tokens_xyz_out: Vec<[f32; 3]>,
    /// `[N_b]` all tokens of the chunk.
    pub tokens_conf_out: Vec<f32>,
}

impl Ggpt {
    /// Every BatchNorm of the network (stem, pooling projections, unpooling projections), for
    /// adjusting their momentum (e.g. BatchNorm re-estimation after training).
    pub fn batch_norms_mut(&mut self) -> Vec<&mut BatchNorm> {
        let mut out = vec![&mut self.embedding.norm];
        for stage in &mut self.enc {
            if let Some(down) = &mut stage.down {
                out.push(&mut down.norm);
            }
        }
        for stage in &mut self.dec {
            out.push(&mut stage.up.proj.norm);
            out.push(&mut stage.up.proj_skip.norm);
        }
        out
    }

    /// Every BatchNorm with its Burn module path (`embedding.norm`, `enc.{s}.down.norm`,
    /// `dec.{s}.up.proj.norm`, `dec.{s}.up.proj_skip.norm`), in the order of
    /// [`Ggpt::batch_norms_mut`]; `weights::official_key` gives the official names.
    pub fn named_batch_norms(&self) -> Vec<(String, &BatchNorm)> {
        let mut out = vec![("embedding.norm".to_string(), &self.embedding.norm)];
        for (s, stage) in self.enc.iter().enumerate() {
            if let Some(down) = &stage.down {
                out.push((format!("enc.{s}.down.norm"), &down.norm));
            }
        }
        for (s, stage) in self.dec.iter().enumerate() {
            out.push((format!("dec.{s}.up.proj.norm"), &stage.up.proj.norm));
            out.push((
                format!("dec.{s}.up.proj_skip.norm"),
                &stage.up.proj_skip.norm,
            ));
        }
        out
    }

    /// Sets the drop probability of every block's drop path (`0` switches it off while the
    /// training flag stays on).
    pub fn set_drop_path(&mut self, prob: f64) {
        for block in self
            .enc
            .iter_mut()
            .flat_map(|s| s.blocks.iter_mut())
            .chain(self.dec.iter_mut().flat_map(|s| s.blocks.iter_mut()))
        {
            block.drop_path.prob = prob;
        }
    }

    /// A freshly initialised network (network.md §11.4) on `device`.
    pub fn new(cfg: &GgptConfig, device: &Device) -> Self {
        let normal = Initializer::Normal {
            mean: 0.0,
            std: 1.0,
        };
        let enc_rates = cfg.enc_drop_path_rates();
        let dec_rates = cfg.dec_drop_path_rates();
        let enc = (0..NUM_LEVELS)
            .map(|s| {
                let c = cfg.enc_channels[s];
                EncoderStage {
                    down: (s > 0)
                        .then(|| SerializedPooling::new(cfg, cfg.enc_channels[s - 1], c, device)),
                    blocks: (0..cfg.enc_depths[s])
                        .map(|i| {
                            Block::new(cfg, c, cfg.enc_num_head[s], i, enc_rates[s][i], device)
                        })
                        .collect(),
                }
            })
            .collect();
        let dec = (0..NUM_DEC_STAGES)
            .map(|s| {
                let c = cfg.dec_channels[s];
                DecoderStage {
                    up: Unpooling::new(cfg, cfg.dec_in_channels(s), cfg.enc_channels[s], c, device),
                    blocks: (0..cfg.dec_depths[s])
                        .map(|i| {
                            Block::new(cfg, c, cfg.dec_num_head[s], i, dec_rates[s][i], device)
                        })
                        .collect(),
                }
            })
            .collect();
        Self {
            ff_type_embed: normal.init([TYPE_EMBED_DIM], device),
            dlt_type_embed: normal.init([TYPE_EMBED_DIM], device),
            embedding: LinearBnGelu::new(cfg, cfg.in_channels, cfg.enc_channels[0], device),
            enc,
            dec,
            head: Head::new(
                cfg.dec_channels[0] + cfg.in_channels,
                cfg.head_width,
                device,
            ),
        }
    }
}

impl GgptOutput {
    /// Reads the outputs back and splits them per chunk (network.md §10 table).
    pub fn to_chunks(&self, batch: &PreparedBatch) -> Result<Vec<ChunkOutput>> {
        let xyz = read_tensor_f32(&self.tokens_xyz, "tokens_xyz")?;
        let conf = read_tensor_f32(&self.tokens_conf, "tokens_conf")?;
        let n = batch.num_tokens;
        if xyz.len() != 3 * n || conf.len() != n {
            return Err(ModelError::Plan(format!(
                "outputs have {} / {} values for {n} tokens",
                xyz.len(),
                conf.len()
            )));
        }
        let mut out = Vec::with_capacity(batch.chunks.len());
        for span in &batch.chunks {
            let nb = span.num_tokens();
            let tok_xyz: Vec<[f32; 3]> = (span.start..span.start + nb)
                .map(|t| [xyz[3 * t], xyz[3 * t + 1], xyz[3 * t + 2]])
                .collect();
            let tok_conf = conf[span.start..span.start + nb].to_vec();
            let k = span.num_dense;
            let mut geo_pts = vec![[0.0f32; 3]; k];
            let mut geo_conf = vec![0.0f32; k];
            for (m, &pixel) in span.dlt_pixel.iter().enumerate() {
                if let (Some(dst), Some(dc)) = (geo_pts.get_mut(pixel), geo_conf.get_mut(pixel)) {
                    *dst = tok_xyz[k + m];
                    *dc = tok_conf[k + m];
                }
            }
            out.push(ChunkOutput {
                ff_pts_out: tok_xyz[..k].to_vec(),
                ff_pts_conf_out: tok_conf[..k].to_vec(),
                geo_pts_out: geo_pts,
                geo_pts_conf_out: geo_conf,
                tokens_xyz_out: tok_xyz,
                tokens_conf_out: tok_conf,
            });
        }
        Ok(out)
    }
}
