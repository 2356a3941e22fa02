//! Memory-efficient gradients by segment recomputation (activation checkpointing,
//! `docs/training.md`).
//!
//! Plain autodiff keeps every intermediate of the forward until the backward: ~1.4 MB per token
//! for the released configuration. Here the forward runs once without a graph, keeping only
//! the slot tensors of [`Program`] (block inputs, the two residual states inside each block,
//! skips, `feat`: a few KB per token). Then the backward walks the segments in reverse. Each
//! segment is re-run under autodiff from its stored inputs, made leaves, and back-propagated
//! with the surrogate loss `Σ_j <y_j, g_j>`, where `g_j` is the already known gradient of its
//! output `y_j`. That yields the gradients of its parameters and of its inputs, exactly those of
//! the whole graph (the chain rule, split at the slots). So the peak holds one segment's graph,
//! not the network's.
//!
//! Two kinds of state must not change when a segment is re-run:
//! * BatchNorm running statistics are updated by the forward only
//!   ([`norm::without_running_updates`] during the re-runs); the batch statistics themselves
//!   are recomputed identically.
//! * Drop-path masks: the thread's host mask RNG ([`drop_path::seed_drop_path`]) is saved before
//!   each segment and restored before its re-run, so the same masks are drawn. After the step
//!   it is left where the forward left it, as after a plain step. An unseeded thread (device
//!   RNG) is seeded for the step from one draw of the device RNG.
//!
//! On CPU devices the attention and xCPE parts are differentiated on the host
//! ([`crate::block::Block::attn_part_backward`], [`crate::block::Block::cpe_part_backward`]);
//! the forward also keeps the attention before its projection and the sparse conv's output
//! (`[N, C]` per attention and CPE part), so that the backward does not recompute them. Every
//! other segment (the MLP parts included) is re-run under autodiff, where the kernel layer's
//! ops (GELU, LayerNorm, row gathers, attention core, sparse conv) bring their own backwards.
//!
//! Cost: one extra forward per step (no graph), against a graph bounded by the largest segment.

use burn::module::Module;
use burn::optim::GradientsParams;
use burn::tensor::{Device, Distribution, Tensor};

use crate::drop_path::{self, MaskRngState};
use crate::model::{Ggpt, GgptOutput};
use crate::norm;
use crate::prepared::PreparedBatch;
use crate::profile;
use crate::readback::read_tensor_f32;
use crate::recorder::Recorder;
use crate::segments::{BlockPart, Op, Program};

/// The gradients of `objective(model.forward(batch))` with respect to every parameter of
/// `model`, computed by segment recomputation (module docs), and what `objective` returned
/// beside its loss.
///
/// `model` must live on an autodiff device in training mode. `objective` receives the
/// train-mode outputs (tracked) and returns the scalar `[1]` to differentiate plus any value,
/// e.g. the loss terms read back; an error from it aborts before any backward. BatchNorm
/// running statistics are updated once, as by a plain forward. The gradients equal those of
/// `GradientsParams::from_grads(loss.backward(), model)` after a plain forward up to float
/// summation order.
pub fn recomputed_gradients<T, E>(
    model: &Ggpt,
    batch: &PreparedBatch,
    objective: impl FnOnce(GgptOutput) -> Result<(Tensor<1>, T), E>,
) -> Result<(GradientsParams, T), E> {
    let outer = drop_path::mask_rng_state();
    let own_seed = !outer.is_seeded() && has_active_drop_path(model);
    if own_seed {
        drop_path::seed_drop_path(Some(device_seed(batch)));
    }
    let mut after_forward = None;
    let result = run(model, batch, objective, &mut after_forward);
    match (own_seed, after_forward) {
        (false, Some(state)) => drop_path::restore_mask_rng(&state),
        _ => drop_path::restore_mask_rng(&outer),
    }
    result
}

fn run<T, E>(
    model: &Ggpt,
    batch: &PreparedBatch,
    objective: impl FnOnce(GgptOutput) -> Result<(Tensor<1>, T), E>,
    after_forward: &mut Option<MaskRngState>,
) -> Result<(GradientsParams, T), E> {
    let program = Program::of(model);
    let device = batch.coord.device().without_autodiff();
    let mut rec = Recorder::disabled();
    let host_kernels = crate::kernels::runs_on_host(&batch.coord);
    // 1. Forward without a graph: parameters detached (BatchNorm and drop path still in
    //    training mode), slot values kept without autodiff.
    let frozen = model.clone().no_grad();
    let mut values: Vec<Option<Tensor<2>>> = vec![None; program.num_slots];
    let mut rng_before = Vec::with_capacity(program.segments.len());
    // per segment, what its host backward takes instead of recomputing it (CPU devices: the
    // attention before its projection, the sparse conv's output)
    let mut kept: Vec<Option<Tensor<2>>> = vec![None; program.segments.len()];
    for (k, seg) in program.segments.iter().enumerate() {
        rng_before.push(drop_path::mask_rng_state());
        let args: Vec<Tensor<2>> = seg
            .inputs
            .iter()
            .map(|&i| slot(&values, i, &device).autodiff())
            .collect();
        let (outs, core) = profile::scope(
            || format!("step.forward.{}", op_kind(seg.op)),
            || frozen.run_segment_keeping_core(batch, seg.op, &args, &mut rec),
        );
        if host_kernels {
            kept[k] = core.map(Tensor::without_autodiff);
        }
        for (&o, t) in seg.outputs.iter().zip(outs) {
            values[o] = Some(t.without_autodiff());
        }
    }
    drop(frozen);
    *after_forward = Some(drop_path::mask_rng_state());

    // 2. The head and the objective under autodiff, then every segment in reverse.
    let mut acc = GradientsParams::new();
    let mut slot_grads: Vec<Option<Tensor<2>>> = vec![None; program.num_slots];
    let [y_slot, feat_slot] = program.head_inputs;
    let (y, feat) = (
        leaf(&values, y_slot, &device),
        leaf(&values, feat_slot, &device),
    );
    let (loss, extra) = profile::scope(
        || "step.head_and_loss".to_string(),
        || objective(model.run_head(batch, y.clone(), feat.clone(), &mut rec)),
    )?;
    let mut grads = profile::scope(|| "step.backward.head".to_string(), || loss.backward());
    add_slot_grad(&mut slot_grads, y_slot, y.grad_remove(&mut grads));
    add_slot_grad(&mut slot_grads, feat_slot, feat.grad_remove(&mut grads));
    crate::grads::collect(model, &mut grads, &mut acc);
    drop(grads);

    for (k, seg) in program.segments.iter().enumerate().rev() {
        let _timer = profile::Timer::start(|| format!("step.backward.{}", op_kind(seg.op)));
        let out_grads: Vec<Option<Tensor<2>>> =
            seg.outputs.iter().map(|&o| slot_grads[o].take()).collect();
        for &o in &seg.outputs {
            // every reader of the outputs came later and has been processed
            values[o] = None;
        }
        if out_grads.iter().all(Option::is_none) {
            continue;
        }
        // one leaf per distinct input slot (`[x, x]` shares one)
        let mut leaves: Vec<(usize, Tensor<2>)> = Vec::with_capacity(seg.inputs.len());
        for &i in &seg.inputs {
            if !leaves.iter().any(|(j, _)| *j == i) {
                leaves.push((i, leaf(&values, i, &device)));
            }
        }
        let args: Vec<Tensor<2>> = seg
            .inputs
            .iter()
            .filter_map(|i| leaves.iter().find(|(j, _)| j == i).map(|(_, t)| t.clone()))
            .collect();
        drop_path::restore_mask_rng(&rng_before[k]);
        if let (Op::Block { stage, block, part }, [Some(g)]) = (seg.op, out_grads.as_slice()) {
            // CPU devices: the xCPE and attention parts differentiated on the host from what the
            // graph-free forward kept (the conv output, the attention core): no re-run of
            // those. The MLP parts, and every part on other devices, re-run under autodiff
            // (below), where the kernel layer's ops bring their own backwards (host kernels
            // on the CPU; the attention core's score-bounded backward on CubeCL).
            let (blocks, level) = model.stage_blocks(batch, stage);
            let b = &blocks[block];
            let input = |j: usize| slot(&values, seg.inputs[j], &device);
            let d = match (part, host_kernels) {
                (BlockPart::Cpe, true) => {
                    b.cpe_part_backward(input(1), kept[k].take(), g.clone(), level)
                }
                (BlockPart::Attn, true) => {
                    b.attn_part_backward(input(0), g.clone(), level, kept[k].take())
                }
                (BlockPart::Mlp, _) | (_, false) => None,
            };
            if let Some(d) = d {
                for (&i, g) in seg.inputs.iter().zip(d.inputs) {
                    add_slot_grad(&mut slot_grads, i, Some(g));
                }
                d.vectors
                    .into_iter()
                    .for_each(|(id, g)| crate::grads::accumulate(&mut acc, id, g));
                d.matrices
                    .into_iter()
                    .for_each(|(id, g)| crate::grads::accumulate(&mut acc, id, g));
                d.kernels
                    .into_iter()
                    .for_each(|(id, g)| crate::grads::accumulate(&mut acc, id, g));
                continue;
            }
            drop_path::restore_mask_rng(&rng_before[k]);
            if part == BlockPart::Mlp
                && let [i] = seg.inputs.as_slice()
            {
                // row-wise: re-run and differentiate one row block at a time, so the graph
                // holds one block's hidden activations (the drop-path mask draws one value per
                // row in order, so the blocks draw the forward's mask)
                let x = slot(&values, *i, &device);
                let rows = mlp_rerun_rows(b.mlp.fc1.weight.dims()[1], x.dims()[1]);
                let d_x = mlp_rows_backward(model, batch, seg.op, x, g, rows, &mut acc);
                add_slot_grad(&mut slot_grads, *i, Some(d_x));
                continue;
            }
        }
        let outs =
            norm::without_running_updates(|| model.run_segment(batch, seg.op, &args, &mut rec));
        drop(args);
        let surrogate = outs
            .into_iter()
            .zip(out_grads)
            .filter_map(|(y, g)| g.map(|g| (y * g.autodiff()).sum()))
            .reduce(|a, b| a + b);
        let Some(surrogate) = surrogate else { continue };
        let mut grads = surrogate.backward();
        for (i, t) in &leaves {
            add_slot_grad(&mut slot_grads, *i, t.grad_remove(&mut grads));
        }
        crate::grads::collect(model, &mut grads, &mut acc);
    }
    Ok((acc, extra))
}

/// Floats of one row block's MLP graph in the re-run ([`mlp_rows_backward`]): 16 MiB of f32.
pub const MLP_RERUN_BLOCK_FLOATS: usize = 4 * 1024 * 1024;

/// Rows per block of the MLP re-run for `hidden` and `c` channels: a block's graph holds about
/// `2 hidden + 4 C` floats per row, at most [`MLP_RERUN_BLOCK_FLOATS`] (at least one row).
fn mlp_rerun_rows(hidden: usize, c: usize) -> usize {
    (MLP_RERUN_BLOCK_FLOATS / (2 * hidden + 4 * c).max(1)).max(1)
}

/// The gradient of the MLP segment `op` (`x [N, C] -> x + DropPath(MLP(LN2(x)))`, row-wise)
/// for the output gradient `g [N, C]`, re-run under autodiff `rows` rows at a time: returns the
/// gradient of `x` and adds the parameter gradients into `acc`.
fn mlp_rows_backward(
    model: &Ggpt,
    batch: &PreparedBatch,
    op: Op,
    x: Tensor<2>,
    g: &Tensor<2>,
    rows: usize,
    acc: &mut GradientsParams,
) -> Tensor<2> {
    let [n, c] = x.dims();
    let rows = rows.max(1);
    let mut rec = Recorder::disabled();
    let mut d_x = Vec::with_capacity(n.div_ceil(rows));
    let mut r0 = 0;
    while r0 < n {
        let m = rows.min(n - r0);
        let leaf = x.clone().narrow(0, r0, m).autodiff().require_grad();
        let outs = norm::without_running_updates(|| {
            model.run_segment(batch, op, std::slice::from_ref(&leaf), &mut rec)
        });
        let g_rows = g.clone().narrow(0, r0, m).autodiff();
        if let Some(y) = outs.into_iter().next() {
            let mut grads = (y * g_rows).sum().backward();
            d_x.push(
                leaf.grad_remove(&mut grads)
                    .unwrap_or_else(|| Tensor::zeros([m, c], &x.device())),
            );
            crate::grads::collect(model, &mut grads, acc);
        }
        r0 += m;
    }
    match d_x.len() {
        1 => d_x
            .pop()
            .unwrap_or_else(|| Tensor::zeros([n, c], &x.device())),
        _ => Tensor::cat(d_x, 0),
    }
}

/// Profile key of a segment kind (`enc2.attn`, `down`, ...): [`crate::profile`] sums the
/// forward and the backward of every segment of that kind.
fn op_kind(op: Op) -> String {
    match op {
        Op::Embed => "embed".into(),
        Op::Stem => "stem".into(),
        Op::Down(_) => "down".into(),
        Op::Up(_) => "up".into(),
        Op::Block { stage, part, .. } => {
            let part = match part {
                BlockPart::Cpe => "cpe",
                BlockPart::Attn => "attn",
                BlockPart::Mlp => "mlp",
            };
            format!("{}.{part}", stage.name())
        }
    }
}

/// The stored value of slot `i`. [`Program`] has every slot written before it is read, so the
/// empty fallback is never taken.
fn slot(values: &[Option<Tensor<2>>], i: usize, device: &Device) -> Tensor<2> {
    values[i]
        .clone()
        .unwrap_or_else(|| Tensor::zeros([0, 0], device))
}

/// A fresh autodiff leaf holding the stored value of slot `i`.
fn leaf(values: &[Option<Tensor<2>>], i: usize, device: &Device) -> Tensor<2> {
    slot(values, i, device).autodiff().require_grad()
}

fn add_slot_grad(slot_grads: &mut [Option<Tensor<2>>], i: usize, g: Option<Tensor<2>>) {
    if let Some(g) = g {
        slot_grads[i] = Some(match slot_grads[i].take() {
            Some(prev) => prev + g,
            None => g,
        });
    }
}

/// Whether some block of `model` would drop paths in this forward.
fn has_active_drop_path(model: &Ggpt) -> bool {
    model
        .enc
        .iter()
        .flat_map(|s| &s.blocks)
        .chain(model.dec.iter().flat_map(|s| &s.blocks))
        .any(|b| b.drop_path.prob > 0.0 && b.drop_path.training.is_enabled())
}

/// A mask seed drawn from the device RNG (deterministic under `Device::seed`).
fn device_seed(batch: &PreparedBatch) -> u64 {
    let device = batch.coord.device();
    let draw = Tensor::<1>::random(
        [2],
        Distribution::Uniform(0.0, 1.0),
        &device.without_autodiff(),
    );
    let v = read_tensor_f32(&draw, "drop-path seed").unwrap_or_default();
    let word =
        |i: usize| (f64::from(v.get(i).copied().unwrap_or(0.0)) * f64::from(u32::MAX)) as u64;
    (word(0) << 32) | word(1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::GgptConfig;
    use crate::bench::surface_chunk;
    use crate::infer::prepare_chunks;
    use crate::segments::Stage;
    use burn::module::{ModuleVisitor, Param};

    /// The tests seed and draw from the shared ndarray device RNG: one at a time.
    fn rng_lock() -> std::sync::MutexGuard<'static, ()> {
        static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
        LOCK.lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn flat(model: &Ggpt, grads: &GradientsParams) -> Vec<(String, Vec<f32>)> {
        struct Flat<'a> {
            grads: &'a GradientsParams,
            out: Vec<(String, Vec<f32>)>,
        }
        impl ModuleVisitor for Flat<'_> {
            fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
                let g = self.grads.get::<D>(param.id).map(|g| {
                    g.into_data()
                        .convert::<f32>()
                        .try_to_vec::<f32>()
                        .unwrap_or_default()
                });
                self.out.push((param.id.to_string(), g.unwrap_or_default()));
            }
        }
        let mut v = Flat {
            grads,
            out: Vec::new(),
        };
        model.visit(&mut v);
        v.out
    }

    fn running(model: &Ggpt) -> Vec<f32> {
        model
            .named_batch_norms()
            .into_iter()
            .flat_map(|(_, bn)| {
                let m = bn
                    .running_mean
                    .value_sync()
                    .into_data()
                    .try_to_vec::<f32>()
                    .unwrap_or_default();
                let v = bn
                    .running_var
                    .value_sync()
                    .into_data()
                    .try_to_vec::<f32>()
                    .unwrap_or_default();
                m.into_iter().chain(v)
            })
            .collect()
    }

    /// An objective touching both outputs, so every parameter gets a gradient.
    fn objective(out: GgptOutput) -> Result<(Tensor<1>, f32), String> {
        let l = out.tokens_xyz.powf_scalar(2.0).sum() + out.tokens_conf.log().sum().mul_scalar(0.1);
        let v = read_tensor_f32(&l, "loss").map_err(|e| e.to_string())?;
        Ok((l, v[0]))
    }

    /// The recomputed gradients (and BatchNorm statistics, and the drop-path RNG afterwards)
    /// are those of plain autodiff, in training mode with drop path on.
    #[test]
    fn recomputed_gradients_equal_plain_autodiff() {
        let _rng = rng_lock();
        let device = crate::device::device_from_name("ndarray")
            .unwrap()
            .autodiff();
        let mut cfg = GgptConfig::tiny();
        cfg.drop_path = 0.3;
        let host = device.clone().without_autodiff();
        host.seed(3);
        let mut base = Ggpt::new(&cfg, &host);
        // a non-zero last head layer (it starts at zero), so gradients reach the backbone
        let [w, _] = base.head.fc3.weight.dims();
        base.head.fc3 = burn::nn::LinearConfig::new(w, 4).init(&host);
        let base = base.fork(&device).train();
        // independent copies (own running-statistics cells)
        let plain = base.valid().fork(&device).train();
        let segmented = base.valid().fork(&device).train();
        let chunks = vec![surface_chunk(400, 1), surface_chunk(300, 2)];
        let batch = prepare_chunks(&cfg, &chunks, &device).unwrap();

        drop_path::seed_drop_path(Some(11));
        let out = plain.forward(&batch);
        let (l, want_loss) = objective(out).unwrap();
        let want = GradientsParams::from_grads(l.backward(), &plain);
        let want_rng = drop_path::mask_rng_state();

        drop_path::seed_drop_path(Some(11));
        let (got, got_loss) = recomputed_gradients(&segmented, &batch, objective).unwrap();
        let got_rng = drop_path::mask_rng_state();
        drop_path::seed_drop_path(None);

        assert!(
            (want_loss - got_loss).abs() <= 1e-6 * want_loss.abs(),
            "{want_loss} vs {got_loss}"
        );
        let (want, got) = (flat(&plain, &want), flat(&segmented, &got));
        assert_eq!(want.len(), got.len());
        let abs_max = |v: &[f32]| v.iter().fold(0.0f32, |m, x| m.max(x.abs()));
        let global = want.iter().map(|(_, w)| abs_max(w)).fold(0.0f32, f32::max);
        let mut worst = 0.0f32;
        for ((_, w), (_, g)) in want.iter().zip(&got) {
            assert_eq!(
                w.len(),
                g.len(),
                "a parameter without a gradient on one side"
            );
            let diff = w
                .iter()
                .zip(g)
                .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
            // tensors whose exact gradient is 0 hold float noise (biases of a Linear followed
            // by BatchNorm, the key third of qkv biases): measured against the largest gradient
            let max = abs_max(w).max(1e-3 * global);
            worst = worst.max(diff / max);
        }
        assert!(global > 0.0);
        assert!(
            worst <= 1e-5,
            "worst gradient difference {worst:e} relative to max"
        );
        // both sides have gradients for the same parameters (Burn registers none for a few
        // biases whose gradient is structurally zero); most parameters have one
        assert!(want.iter().filter(|(_, w)| !w.is_empty()).count() * 5 > want.len() * 4);
        let (rw, rg) = (running(&plain), running(&segmented));
        assert!(
            rw.iter().zip(&rg).all(|(a, b)| (a - b).abs() <= 1e-6),
            "running statistics differ"
        );
        assert_ne!(
            rw,
            running(&base.valid()),
            "the running statistics were updated"
        );
        assert_eq!(
            format!("{want_rng:?}"),
            format!("{got_rng:?}"),
            "the mask RNG ends where a plain forward leaves it"
        );
    }

    /// `got` has `want`'s length and every value within `2e-5` of `want`'s largest magnitude.
    fn assert_close(name: &str, want: &[f32], got: &[f32]) {
        let max = want.iter().fold(0.0f32, |m, x| m.max(x.abs())).max(1e-12);
        assert_eq!(want.len(), got.len(), "{name}: lengths");
        let worst = want
            .iter()
            .zip(got)
            .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
        assert!(
            worst <= 2e-5 * max,
            "{name}: worst difference {worst:e} of max {max:e}"
        );
    }

    /// The host backward of the CPE and attention parts equals autodiff of that part, with the
    /// intermediate kept by the forward and recomputing it, with and without an active drop
    /// path.
    #[test]
    fn host_part_backwards_equal_autodiff_of_the_part() {
        let _rng = rng_lock();
        let device = crate::device::device_from_name("ndarray")
            .unwrap()
            .autodiff();
        let host = device.clone().without_autodiff();
        let mut cfg = GgptConfig::tiny();
        cfg.drop_path = 0.3;
        host.seed(4);
        let model = Ggpt::new(&cfg, &host).fork(&device).train();
        let batch = prepare_chunks(&cfg, &[surface_chunk(300, 3)], &device).unwrap();
        let stage = Stage::Enc(1);
        let (blocks, level) = model.stage_blocks(&batch, stage);
        let active = blocks
            .iter()
            .position(|b| b.drop_path.prob > 0.0)
            .expect("a block with drop path");
        let frozen = model.clone().no_grad();
        let (frozen_blocks, _) = frozen.stage_blocks(&batch, stage);
        let c = blocks[0].norm1.gamma.val().dims()[0];
        let random = || {
            Tensor::<2>::random(
                [level.num_tokens, c],
                Distribution::Uniform(-1.0, 1.0),
                &host,
            )
        };
        let (x, x_conv, g) = (random(), random(), random());
        for block in [0, active] {
            let b = &blocks[block];
            let fb = &frozen_blocks[block];
            for part in [BlockPart::Cpe, BlockPart::Attn] {
                let label = format!("block {block} {part:?}");
                // autodiff of the part
                drop_path::seed_drop_path(Some(9));
                let (xa, xca) = (
                    x.clone().autodiff().require_grad(),
                    x_conv.clone().autodiff().require_grad(),
                );
                let mut rec = Recorder::disabled();
                let y = match part {
                    BlockPart::Cpe => {
                        b.cpe_part(xa.clone(), xca.clone(), level, &mut rec, "enc1.block")
                    }
                    BlockPart::Attn => b.attn_part(xa.clone(), level, &mut rec, "enc1.block"),
                    BlockPart::Mlp => b.mlp_part(xa.clone(), &mut rec, "enc1.block"),
                };
                let mut grads = (y * g.clone().autodiff()).sum().backward();
                let mut want_inputs =
                    vec![read_tensor_f32(&xa.grad_remove(&mut grads).unwrap(), "x").unwrap()];
                if part == BlockPart::Cpe {
                    want_inputs.push(
                        read_tensor_f32(&xca.grad_remove(&mut grads).unwrap(), "x_conv").unwrap(),
                    );
                }
                let mut want = GradientsParams::new();
                crate::grads::collect(&model, &mut grads, &mut want);
                let want = flat(&model, &want);
                // the kept intermediate, as the graph-free forward computes it
                let kept = match part {
                    BlockPart::Cpe => Some(
                        fb.cpe_part_with_conv(
                            x.clone().autodiff(),
                            x_conv.clone().autodiff(),
                            level,
                            &mut rec,
                            "enc1.block",
                        )
                        .1,
                    ),
                    BlockPart::Attn => Some(
                        fb.attn_part_with_core(x.clone().autodiff(), level, &mut rec, "enc1.block")
                            .1,
                    ),
                    BlockPart::Mlp => unreachable!("the MLP part has no host backward"),
                };
                for kept in [kept.map(Tensor::without_autodiff), None] {
                    drop_path::seed_drop_path(Some(9));
                    let d = match part {
                        BlockPart::Cpe => {
                            b.cpe_part_backward(x_conv.clone(), kept.clone(), g.clone(), level)
                        }
                        BlockPart::Attn => {
                            b.attn_part_backward(x.clone(), g.clone(), level, kept.clone())
                        }
                        BlockPart::Mlp => unreachable!("the MLP part has no host backward"),
                    }
                    .expect("host backward");
                    assert_eq!(d.inputs.len(), want_inputs.len(), "{label}");
                    for (w, got) in want_inputs.iter().zip(&d.inputs) {
                        assert_close(
                            &format!("{label} input"),
                            w,
                            &read_tensor_f32(got, "d input").unwrap(),
                        );
                    }
                    let mut acc = GradientsParams::new();
                    d.vectors
                        .into_iter()
                        .for_each(|(id, g)| crate::grads::accumulate(&mut acc, id, g));
                    d.matrices
                        .into_iter()
                        .for_each(|(id, g)| crate::grads::accumulate(&mut acc, id, g));
                    d.kernels
                        .into_iter()
                        .for_each(|(id, g)| crate::grads::accumulate(&mut acc, id, g));
                    let got = flat(&model, &acc);
                    let mut compared = 0;
                    for ((name, w), (_, got)) in want.iter().zip(&got) {
                        if !w.is_empty() {
                            assert_close(&format!("{label} {name}"), w, got);
                            compared += 1;
                        }
                    }
                    assert!(compared >= 4, "{label}: {compared} parameter gradients");
                }
            }
        }
        drop_path::seed_drop_path(None);
    }

    /// The MLP segment's row-block re-run (blocks of 7 rows) equals autodiff of the whole part,
    /// with and without an active drop path (the blocks draw the forward's mask).
    #[test]
    fn mlp_row_blocks_equal_autodiff_of_the_part() {
        let _rng = rng_lock();
        let device = crate::device::device_from_name("ndarray")
            .unwrap()
            .autodiff();
        let host = device.clone().without_autodiff();
        let mut cfg = GgptConfig::tiny();
        cfg.drop_path = 0.3;
        host.seed(6);
        let model = Ggpt::new(&cfg, &host).fork(&device).train();
        let batch = prepare_chunks(&cfg, &[surface_chunk(300, 3)], &device).unwrap();
        let stage = Stage::Enc(1);
        let (blocks, level) = model.stage_blocks(&batch, stage);
        let active = blocks
            .iter()
            .position(|b| b.drop_path.prob > 0.0)
            .expect("a block with drop path");
        let c = blocks[0].norm2.gamma.val().dims()[0];
        let random = |seed: u64| {
            host.seed(seed);
            Tensor::<2>::random(
                [level.num_tokens, c],
                Distribution::Uniform(-1.0, 1.0),
                &host,
            )
        };
        let (x, g) = (random(13), random(14));
        assert!(level.num_tokens > 3 * 7, "several row blocks");
        for block in [0, active] {
            let b = &blocks[block];
            drop_path::seed_drop_path(Some(9));
            let xa = x.clone().autodiff().require_grad();
            let mut rec = Recorder::disabled();
            let y = b.mlp_part(xa.clone(), &mut rec, "enc1.block");
            let mut grads = (y * g.clone().autodiff()).sum().backward();
            let want_x = read_tensor_f32(&xa.grad_remove(&mut grads).unwrap(), "x").unwrap();
            let mut want = GradientsParams::new();
            crate::grads::collect(&model, &mut grads, &mut want);
            let want = flat(&model, &want);

            drop_path::seed_drop_path(Some(9));
            let op = Op::Block {
                stage,
                block,
                part: BlockPart::Mlp,
            };
            let mut acc = GradientsParams::new();
            let d_x = mlp_rows_backward(&model, &batch, op, x.clone(), &g, 7, &mut acc);
            let label = format!("block {block}");
            assert_close(&label, &want_x, &read_tensor_f32(&d_x, "d x").unwrap());
            let got = flat(&model, &acc);
            let mut compared = 0;
            for ((name, w), (_, got)) in want.iter().zip(&got) {
                if !w.is_empty() {
                    assert_close(&format!("{label} {name}"), w, got);
                    compared += 1;
                }
            }
            assert_eq!(compared, 6, "{label}: LN2 (2), fc1 (2), fc2 (2)");
        }
        drop_path::seed_drop_path(None);
    }

    /// An objective error aborts before any backward and leaves the caller's RNG state.
    #[test]
    fn objective_errors_are_returned() {
        let _rng = rng_lock();
        let device = crate::device::device_from_name("ndarray")
            .unwrap()
            .autodiff();
        let cfg = GgptConfig::tiny();
        let model = Ggpt::new(&cfg, &device).train();
        let batch = prepare_chunks(&cfg, &[surface_chunk(200, 5)], &device).unwrap();
        let r = recomputed_gradients(&model, &batch, |_| Err::<(Tensor<1>, ()), _>("bad loss"));
        assert_eq!(r.err(), Some("bad loss"));
    }
}
