//! The whole GGPT network (network.md §3.2, §5–§10): guidance encoding, PTv3 backbone, head.

use burn::module::{Module, Param};
use burn::nn::{BatchNorm, Initializer};
use burn::tensor::{Device, Tensor};

use crate::block::Block;
use crate::config::{GgptConfig, NUM_DEC_STAGES, NUM_LEVELS, TYPE_EMBED_DIM};
use crate::error::{ModelError, Result};
use crate::head::{Head, head_outputs};
use crate::linear_bn::LinearBnGelu;
use crate::ops::map_row_blocks;
use crate::pooling::SerializedPooling;
use crate::prepared::PreparedBatch;
use crate::recorder::Recorder;
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
            out.push((format!("dec.{s}.up.proj_skip.norm"), &stage.up.proj_skip.norm));
        }
        out
    }

    /// Sets the drop probability of every block's drop path (`0` switches it off while the
    /// training flag stays on).
    pub fn set_drop_path(&mut self, prob: f64) {
        for block in self.enc.iter_mut().flat_map(|s| s.blocks.iter_mut()).chain(self.dec.iter_mut().flat_map(|s| s.blocks.iter_mut())) {
            block.drop_path.prob = prob;
        }
    }

    /// A freshly initialised network (network.md §11.4) on `device`.
    pub fn new(cfg: &GgptConfig, device: &Device) -> Self {
        let normal = Initializer::Normal { mean: 0.0, std: 1.0 };
        let enc_rates = cfg.enc_drop_path_rates();
        let dec_rates = cfg.dec_drop_path_rates();
        let enc = (0..NUM_LEVELS)
            .map(|s| {
                let c = cfg.enc_channels[s];
                EncoderStage {
                    down: (s > 0).then(|| SerializedPooling::new(cfg, cfg.enc_channels[s - 1], c, device)),
                    blocks: (0..cfg.enc_depths[s])
                        .map(|i| Block::new(cfg, c, cfg.enc_num_head[s], i, enc_rates[s][i], device))
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
                        .map(|i| Block::new(cfg, c, cfg.dec_num_head[s], i, dec_rates[s][i], device))
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
            head: Head::new(cfg.dec_channels[0] + cfg.in_channels, cfg.head_width, device),
        }
    }

    /// Forward of a prepared batch.
    pub fn forward(&self, batch: &PreparedBatch) -> GgptOutput {
        self.forward_recorded(batch, &mut Recorder::disabled())
    }

    /// Forward recording the fixture-named intermediates into `rec` (when enabled).
    pub fn forward_recorded(&self, batch: &PreparedBatch, rec: &mut Recorder) -> GgptOutput {
        let [n, _] = batch.feat_no_embed.dims();
        let types = Tensor::stack::<2>(vec![self.ff_type_embed.val(), self.dlt_type_embed.val()], 0);
        let type_rows = types.select(0, batch.type_index.clone());
        let feat = Tensor::cat(vec![type_rows, batch.feat_no_embed.clone()], 1);
        rec.record(|| "input.feat".into(), &feat);
        rec.record(|| "input.coord".into(), &batch.coord);
        let mut x = self.embedding.forward(feat.clone());
        rec.record(|| "embedding.out".into(), &x);
        let mut skips = Vec::with_capacity(NUM_LEVELS);
        for (s, stage) in self.enc.iter().enumerate() {
            let level = &batch.levels[s];
            if let (Some(down), Some(prev)) = (&stage.down, s.checked_sub(1).and_then(|p| batch.levels[p].pool.as_ref())) {
                x = down.forward(x, prev, rec, &format!("enc{s}.down"));
            }
            for (i, block) in stage.blocks.iter().enumerate() {
                x = block.forward(x.clone(), x, level, rec, &format!("enc{s}.block{i}"));
            }
            rec.record(|| format!("enc{s}.out"), &x);
            skips.push(x.clone());
        }
        let mut y = x;
        for s in (0..NUM_DEC_STAGES).rev() {
            let stage = &self.dec[s];
            let level = &batch.levels[s];
            let Some(pool) = level.pool.as_ref() else { continue };
            let skip = skips[s].clone();
            let (u, proj_skip) = stage.up.forward(y, skip, pool.cluster.clone(), rec, &format!("dec{s}.up"));
            let mut x = u;
            let mut x_conv = proj_skip;
            for (i, block) in stage.blocks.iter().enumerate() {
                x = block.forward(x, x_conv, level, rec, &format!("dec{s}.block{i}"));
                x_conv = x.clone();
            }
            rec.record(|| if s == 0 { "backbone.out".into() } else { format!("dec{s}.out") }, &x);
            y = x;
        }
        // Row blocks bound the [N, D_0 + 218] / [N, W] intermediates on large chunks.
        let [_, d0] = y.dims();
        let width = (d0 + feat.dims()[1]).max(self.head.fc1.weight.dims()[1]);
        let both = Tensor::cat(vec![y, feat], 1);
        let h = map_row_blocks(both, width, |rows| self.head.forward(rows));
        rec.record(|| "head.pre_activation".into(), &h);
        let (tokens_xyz, tokens_conf) = head_outputs(h.clone(), batch.coord.clone());
        debug_assert_eq!(tokens_xyz.dims(), [n, 3]);
        GgptOutput { tokens_xyz, tokens_conf, pre_activation: h }
    }
}

impl GgptOutput {
    /// Reads the outputs back and splits them per chunk (network.md §10 table).
    pub fn to_chunks(&self, batch: &PreparedBatch) -> Result<Vec<ChunkOutput>> {
        let xyz = read_tensor_f32(&self.tokens_xyz, "tokens_xyz")?;
        let conf = read_tensor_f32(&self.tokens_conf, "tokens_conf")?;
        let n = batch.num_tokens;
        if xyz.len() != 3 * n || conf.len() != n {
            return Err(ModelError::Plan(format!("outputs have {} / {} values for {n} tokens", xyz.len(), conf.len())));
        }
        let mut out = Vec::with_capacity(batch.chunks.len());
        for span in &batch.chunks {
            let nb = span.num_tokens();
            let tok_xyz: Vec<[f32; 3]> =
                (span.start..span.start + nb).map(|t| [xyz[3 * t], xyz[3 * t + 1], xyz[3 * t + 2]]).collect();
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

/// Reads a tensor back to the host as `Vec<f32>`. A failed device execution (e.g. a GPU buffer
/// allocation above the device's limits or out of memory) becomes [`ModelError::Readback`]
/// naming the tensor, with a hint to run smaller forwards, instead of a panic.
pub fn read_tensor_f32<const D: usize>(t: &burn::tensor::Tensor<D>, name: &str) -> Result<Vec<f32>> {
    let data = t.try_to_data().map_err(|e| ModelError::Readback {
        name: name.to_string(),
        message: format!("device execution failed ({e}); if the device ran out of memory or hit a buffer-size limit, run smaller forwards (--max-tokens-per-forward / smaller chunks)"),
    })?;
    read_f32(&data, name)
}

/// Converts tensor data to `Vec<f32>`, naming the tensor on failure.
pub fn read_f32(data: &burn::tensor::TensorData, name: &str) -> Result<Vec<f32>> {
    data.clone()
        .convert::<f32>()
        .try_to_vec::<f32>()
        .map_err(|e| ModelError::Readback { name: name.to_string(), message: format!("{e:?}") })
}
