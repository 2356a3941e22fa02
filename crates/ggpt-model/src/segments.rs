//! The network's forward (network.md §3.2, §5–§10) as one list of segments over tensor slots.
//!
//! This is the single description of the graph. The plain forward ([`Ggpt::forward`], here) runs
//! the segments in order and drops each slot after its last reader. The recomputing training
//! step ([`crate::recompute`]) keeps the slots as checkpoints, then re-runs each segment under
//! autodiff in reverse order.
//!
//! ```text
//! slot 0  feat  = [e_type | feat_no_embed]            [N_0, 218]   Embed  []              -> [feat]
//!         x     = GELU(BN(Linear(feat)))              [N_0, E_0]   Stem   [feat]          -> [x]
//! enc s:  x     = pool(x)                 (s > 0)     [N_s, E_s]   Down   [x]             -> [x]
//!   block i: x1 = x  + CPE(x_conv)                                 Cpe    [x, x_conv]     -> [x1]
//!            x2 = x1 + DropPath(Attn(LN1(x1)))                     Attn   [x1]            -> [x2]
//!            x3 = x2 + DropPath(MLP(LN2(x2)))                      Mlp    [x2]            -> [x3]
//!         skip_s = x3 of the stage's last block
//! dec s (3, 2, 1, 0): (u, proj_skip) = up(y, skip_s)  [N_s, D_s]   Up     [y, skip_s]     -> [u, proj_skip]
//!   blocks as above, x_conv of block 0 = proj_skip (§9.2)
//! head:   h = head([y | feat]), outputs                [N_0, 4]    Head   [y, feat]       -> GgptOutput
//! ```

use burn::tensor::Tensor;

use crate::block::Block;
use crate::config::{NUM_DEC_STAGES, NUM_LEVELS};
use crate::head::head_outputs;
use crate::model::{Ggpt, GgptOutput};
use crate::ops::map_row_blocks;
use crate::prepared::{PreparedBatch, PreparedLevel};
use crate::recorder::Recorder;

/// A stage of the backbone: encoder stage `s` (level `s`) or decoder stage `s`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// Encoder stage `0..=4`.
    Enc(usize),
    /// Decoder stage `0..=3`.
    Dec(usize),
}

impl Stage {
    /// The stage's name in recorded keys and profiles: `enc0`..`enc4`, `dec0`..`dec3`.
    pub fn name(self) -> String {
        match self {
            Stage::Enc(s) => format!("enc{s}"),
            Stage::Dec(s) => format!("dec{s}"),
        }
    }
}

/// One third of a block (`crate::block`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BlockPart {
    /// `x1 = x + CPE(x_conv)`.
    Cpe,
    /// `x2 = x1 + DropPath(Attn(LN1(x1)))`.
    Attn,
    /// `x3 = x2 + DropPath(MLP(LN2(x2)))`.
    Mlp,
}

/// What a segment computes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Op {
    /// Type embeddings concatenated to the guidance channels.
    Embed,
    /// The stem `GELU(BN(Linear))`.
    Stem,
    /// Serialized pooling into encoder level `s` (`s >= 1`).
    Down(usize),
    /// Part of block `block` of `stage`.
    Block {
        /// The stage.
        stage: Stage,
        /// Block index within the stage.
        block: usize,
        /// Which part.
        part: BlockPart,
    },
    /// Unpooling of decoder stage `s`.
    Up(usize),
}

/// A segment: its op, the slots it reads and the slots it writes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Segment {
    /// The computation.
    pub op: Op,
    /// Slots read, in the op's argument order (a slot may appear twice: `[x, x]`).
    pub inputs: Vec<usize>,
    /// Slots written.
    pub outputs: Vec<usize>,
}

/// The whole forward: segments in execution order over `num_slots` rank-2 slots, then the
/// head ([`Ggpt::run_head`]) on two slots.
#[derive(Debug, Clone)]
pub struct Program {
    /// Segments in execution order (the head excluded).
    pub segments: Vec<Segment>,
    /// The head's inputs: the decoder output `y` and `feat`.
    pub head_inputs: [usize; 2],
    /// Number of slots.
    pub num_slots: usize,
    /// Per slot, the index of the last segment reading it (`segments.len()` for the head).
    pub last_use: Vec<usize>,
}

/// Slot of the input features `feat` (read by the stem and the head).
pub const FEAT_SLOT: usize = 0;

impl Program {
    /// The program of a network with the given stage depths (blocks per encoder / decoder
    /// stage, [`NUM_LEVELS`] / [`NUM_DEC_STAGES`] entries).
    pub fn new(enc_depths: &[usize], dec_depths: &[usize]) -> Self {
        let mut segments = Vec::new();
        let mut next = FEAT_SLOT + 1;
        let mut fresh = || {
            let s = next;
            next += 1;
            s
        };
        segments.push(Segment {
            op: Op::Embed,
            inputs: vec![],
            outputs: vec![FEAT_SLOT],
        });
        let mut x = fresh();
        segments.push(Segment {
            op: Op::Stem,
            inputs: vec![FEAT_SLOT],
            outputs: vec![x],
        });
        let blocks = |segments: &mut Vec<Segment>,
                      fresh: &mut dyn FnMut() -> usize,
                      stage: Stage,
                      depth: usize,
                      mut x: usize,
                      mut x_conv: usize| {
            for block in 0..depth {
                let (x1, x2, x3) = (fresh(), fresh(), fresh());
                let seg = |part, inputs, out| Segment {
                    op: Op::Block { stage, block, part },
                    inputs,
                    outputs: vec![out],
                };
                segments.push(seg(BlockPart::Cpe, vec![x, x_conv], x1));
                segments.push(seg(BlockPart::Attn, vec![x1], x2));
                segments.push(seg(BlockPart::Mlp, vec![x2], x3));
                x = x3;
                x_conv = x3;
            }
            x
        };
        let mut skips = Vec::with_capacity(NUM_LEVELS);
        for (s, &depth) in enc_depths.iter().enumerate().take(NUM_LEVELS) {
            if s > 0 {
                let pooled = fresh();
                segments.push(Segment {
                    op: Op::Down(s),
                    inputs: vec![x],
                    outputs: vec![pooled],
                });
                x = pooled;
            }
            x = blocks(&mut segments, &mut fresh, Stage::Enc(s), depth, x, x);
            skips.push(x);
        }
        let mut y = x;
        for s in (0..NUM_DEC_STAGES.min(dec_depths.len())).rev() {
            let (u, proj_skip) = (fresh(), fresh());
            segments.push(Segment {
                op: Op::Up(s),
                inputs: vec![y, skips[s]],
                outputs: vec![u, proj_skip],
            });
            y = blocks(
                &mut segments,
                &mut fresh,
                Stage::Dec(s),
                dec_depths[s],
                u,
                proj_skip,
            );
        }
        let head_inputs = [y, FEAT_SLOT];
        let num_slots = next;
        let mut last_use = vec![0; num_slots];
        for (k, seg) in segments.iter().enumerate() {
            for &i in &seg.inputs {
                last_use[i] = k;
            }
        }
        for i in head_inputs {
            last_use[i] = segments.len();
        }
        Self {
            segments,
            head_inputs,
            num_slots,
            last_use,
        }
    }

    /// The program of `model`.
    pub fn of(model: &Ggpt) -> Self {
        let enc: Vec<usize> = model.enc.iter().map(|s| s.blocks.len()).collect();
        let dec: Vec<usize> = model.dec.iter().map(|s| s.blocks.len()).collect();
        Self::new(&enc, &dec)
    }
}

impl Ggpt {
    /// Forward of a prepared batch.
    pub fn forward(&self, batch: &PreparedBatch) -> GgptOutput {
        self.forward_recorded(batch, &mut Recorder::disabled())
    }

    /// Forward recording the fixture-named intermediates into `rec` (when enabled): the
    /// segments of [`Program`] in order, each slot dropped after its last reader.
    pub fn forward_recorded(&self, batch: &PreparedBatch, rec: &mut Recorder) -> GgptOutput {
        let program = Program::of(self);
        let mut slots: Vec<Option<Tensor<2>>> = vec![None; program.num_slots];
        let device = batch.coord.device();
        let take =
            |slots: &mut Vec<Option<Tensor<2>>>, k: usize, inputs: &[usize]| -> Vec<Tensor<2>> {
                let args: Vec<Tensor<2>> = inputs
                    .iter()
                    .map(|&i| {
                        slots[i]
                            .clone()
                            .unwrap_or_else(|| Tensor::zeros([0, 0], &device))
                    })
                    .collect();
                for &i in inputs {
                    if program.last_use[i] == k {
                        slots[i] = None;
                    }
                }
                args
            };
        for (k, seg) in program.segments.iter().enumerate() {
            let args = take(&mut slots, k, &seg.inputs);
            for (o, t) in seg
                .outputs
                .iter()
                .zip(self.run_segment(batch, seg.op, &args, rec))
            {
                slots[*o] = Some(t);
            }
        }
        // `take` returns one tensor per slot of `head_inputs` (two)
        let head = take(&mut slots, program.segments.len(), &program.head_inputs);
        self.run_head(batch, head[0].clone(), head[1].clone(), rec)
    }

    /// Runs one segment: `inputs` in the order of [`Segment::inputs`], returns the
    /// tensors of [`Segment::outputs`]. Shapes as in the module table; recording under the
    /// fixture names when `rec` is enabled.
    pub fn run_segment(
        &self,
        batch: &PreparedBatch,
        op: Op,
        inputs: &[Tensor<2>],
        rec: &mut Recorder,
    ) -> Vec<Tensor<2>> {
        self.run_segment_keeping_core(batch, op, inputs, rec).0
    }

    /// [`Self::run_segment`], also returning the intermediate that the host backward of a
    /// block part takes instead of recomputing it: for an attention part ([`BlockPart::Attn`])
    /// the attention before its output projection ([`Block::attn_part_with_core`]), for a CPE
    /// part the sparse conv's output ([`Block::cpe_part_with_conv`]), both `[N, C]`.
    pub fn run_segment_keeping_core(
        &self,
        batch: &PreparedBatch,
        op: Op,
        inputs: &[Tensor<2>],
        rec: &mut Recorder,
    ) -> (Vec<Tensor<2>>, Option<Tensor<2>>) {
        let arg = |i: usize| inputs[i].clone();
        match op {
            Op::Embed => {
                let types = Tensor::stack::<2>(
                    vec![self.ff_type_embed.val(), self.dlt_type_embed.val()],
                    0,
                );
                let type_rows = types.select(0, batch.type_index.clone());
                let feat = Tensor::cat(vec![type_rows, batch.feat_no_embed.clone()], 1);
                rec.record(|| "input.feat".into(), &feat);
                rec.record(|| "input.coord".into(), &batch.coord);
                (vec![feat], None)
            }
            Op::Stem => {
                let x = self.embedding.forward(arg(0));
                rec.record(|| "embedding.out".into(), &x);
                (vec![x], None)
            }
            Op::Down(s) => {
                let pool = s.checked_sub(1).and_then(|p| batch.levels[p].pool.as_ref());
                let out = match (&self.enc[s].down, pool) {
                    (Some(down), Some(prev)) => {
                        down.forward(arg(0), prev, rec, &format!("enc{s}.down"))
                    }
                    _ => arg(0),
                };
                (vec![out], None)
            }
            Op::Block { stage, block, part } => {
                let (blocks, level) = self.stage_blocks(batch, stage);
                let prefix = stage.name();
                let last_name = if stage == Stage::Dec(0) {
                    "backbone.out".to_string()
                } else {
                    format!("{prefix}.out")
                };
                let b = &blocks[block];
                let name = format!("{prefix}.block{block}");
                let (out, core) = match part {
                    BlockPart::Cpe => {
                        let (out, conv) = b.cpe_part_with_conv(arg(0), arg(1), level, rec, &name);
                        (out, Some(conv))
                    }
                    BlockPart::Attn => {
                        let (out, core) = b.attn_part_with_core(arg(0), level, rec, &name);
                        (out, Some(core))
                    }
                    BlockPart::Mlp => (b.mlp_part(arg(0), rec, &name), None),
                };
                if part == BlockPart::Mlp && block + 1 == blocks.len() {
                    rec.record(|| last_name, &out);
                }
                (vec![out], core)
            }
            Op::Up(s) => match batch.levels[s].pool.as_ref() {
                Some(pool) => {
                    let (u, proj_skip) = self.dec[s].up.forward(
                        arg(0),
                        arg(1),
                        pool.cluster.clone(),
                        rec,
                        &format!("dec{s}.up"),
                    );
                    (vec![u, proj_skip], None)
                }
                // levels 0..=3 always pool (PreparedBatch::new checks it)
                None => (vec![arg(1), arg(1)], None),
            },
        }
    }

    /// The blocks of `stage` and the prepared tables of its level.
    pub fn stage_blocks<'a>(
        &'a self,
        batch: &'a PreparedBatch,
        stage: Stage,
    ) -> (&'a [Block], &'a PreparedLevel) {
        match stage {
            Stage::Enc(s) => (&self.enc[s].blocks, &batch.levels[s]),
            Stage::Dec(s) => (&self.dec[s].blocks, &batch.levels[s]),
        }
    }

    /// The head segment: `y [N_0, D_0]` (decoder output) and `feat [N_0, 218]` -> outputs.
    pub fn run_head(
        &self,
        batch: &PreparedBatch,
        y: Tensor<2>,
        feat: Tensor<2>,
        rec: &mut Recorder,
    ) -> GgptOutput {
        // Row blocks bound the [N, D_0 + 218] / [N, W] intermediates on large chunks.
        let [_, d0] = y.dims();
        let width = (d0 + feat.dims()[1]).max(self.head.fc1.weight.dims()[1]);
        let both = Tensor::cat(vec![y, feat], 1);
        let h = map_row_blocks(both, width, |rows| self.head.forward(rows));
        rec.record(|| "head.pre_activation".into(), &h);
        let (tokens_xyz, tokens_conf) = head_outputs(h.clone(), batch.coord.clone());
        GgptOutput {
            tokens_xyz,
            tokens_conf,
            pre_activation: h,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn released_program_writes_each_slot_once_and_reads_every_slot() {
        let p = Program::new(&[2, 2, 2, 6, 2], &[2, 2, 2, 2]);
        // embed, stem, 4 downs, 14 enc blocks x 3, 4 ups, 8 dec blocks x 3
        assert_eq!(p.segments.len(), 2 + 4 + 42 + 4 + 24);
        // every slot is written once before it is read, and read at least once
        let mut written = vec![false; p.num_slots];
        let mut read = vec![false; p.num_slots];
        for seg in &p.segments {
            for &i in &seg.inputs {
                assert!(written[i], "slot {i} read before written by {:?}", seg.op);
                read[i] = true;
            }
            for &o in &seg.outputs {
                assert!(!written[o], "slot {o} written twice");
                written[o] = true;
            }
        }
        for i in p.head_inputs {
            assert!(written[i]);
            read[i] = true;
        }
        assert!(read.iter().all(|&r| r), "an unread slot");
        // the feature slot lives until the head; the skip of enc0 is read by dec0's unpooling
        assert_eq!(p.last_use[FEAT_SLOT], p.segments.len());
        let dec0_up = p.segments.iter().position(|s| s.op == Op::Up(0)).unwrap();
        assert_eq!(p.last_use[p.segments[dec0_up].inputs[1]], dec0_up);
    }
}
