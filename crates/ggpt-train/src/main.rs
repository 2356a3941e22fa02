//! `ggpt-train`: prepare chunk sets, train the GGPT network, evaluate and export it.
//!
//! Without arguments it builds a small synthetic chunk set and trains the tiny configuration
//! on it for a few steps (a demonstration of the whole loop, seconds to a few minutes on CPU).

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use burn::module::Module;
use clap::{Args, Parser, Subcommand};
use ggpt_model::model_dir::{MODEL_WEIGHTS_FILE, load_model, resolve_model};
use ggpt_scene::chunk_settings::{ChunkingSettings, resolve_chunking};
use ggpt_model::{Ggpt, GgptConfig};
use ggpt_scene::chunker::ChunkParams;
use ggpt_scene::driver::RefineOptions;
use ggpt_train::chunkset::{ChunkSet, ChunkSetWriter, SceneEntry, Split};
use ggpt_train::evaluate::{HeldOutScene, evaluate_scene};
use ggpt_train::prepare::{PrepareParams, SynthSpec, official_scene, prepare_scene, synthetic_scene};
use ggpt_train::trainer::{self, LrSchedule, MetricsLine, Recompute, RunContext, TrainOptions};
use indicatif::{ProgressBar, ProgressStyle};

/// Train GGPT on curated chunk sets (synthetic or official per-sequence data).
#[derive(Parser, Debug)]
#[command(name = "ggpt-train", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    /// Output directory of the no-argument demonstration run.
    #[arg(long, default_value = "ggpt-train-default")]
    out: PathBuf,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Build a chunk set (sharded safetensors + manifest) from synthetic scenes and/or official
    /// per-sequence directories.
    Prepare(PrepareArgs),
    /// Train on a chunk set.
    Train(TrainArgs),
    /// Evaluate a model on the held-out (val) scenes of a chunk set: whole-scene refinement
    /// through the scene pipeline, AUC@5/10 cm of the feed-forward input vs the refined points.
    Eval(EvalArgs),
    /// Export a checkpoint as official `model.safetensors` + `model_config.json`.
    Export(ExportArgs),
    /// Plot `metrics.jsonl` as a PNG training curve.
    Plot(PlotArgs),
    /// One training step made visible, for verification against a reference: per input case
    /// (its own batch, from the loaded weights, train mode, drop path 0) the loss terms, the
    /// train-mode outputs, the gradient of every parameter under its official name and the
    /// BatchNorm running statistics after the forward; optionally the parameters after one
    /// Adam step from case 0. See docs/training.md.
    Grads(GradsArgs),
}

/// Chunk sampler options shared by `prepare` and `eval` (pipeline.md §5). `eval` takes a flag
/// that is not given from the model folder's `inference.json`, then from the official default.
#[derive(Args, Debug, Clone, Default)]
struct ChunkingArgs {
    /// Chunk half-size as a fraction of the scene radius R [default: 0.2].
    #[arg(long)]
    chunk_size: Option<f64>,
    /// Pixel cap of a chunk: the cube shrinks by 0.9 while above [default: 400000].
    #[arg(long)]
    max_pixels: Option<usize>,
    /// Minimum DLT pixels of an accepted chunk [default: 100].
    #[arg(long)]
    min_dlt: Option<usize>,
    /// Minimum pixels of an accepted chunk [default: 10000].
    #[arg(long)]
    min_pixels: Option<usize>,
}

/// The `ggpt-train` flag of a [`ChunkingSettings`] field (`max_pixels` -> `--max-pixels`), for
/// messages.
fn chunking_flag(field: &str) -> String {
    format!("--{}", field.replace('_', "-"))
}

impl ChunkingArgs {
    fn settings(&self) -> ChunkingSettings {
        ChunkingSettings { chunk_size: self.chunk_size, max_pixels: self.max_pixels, min_dlt: self.min_dlt, min_pixels: self.min_pixels }
    }
    /// The flags over the official defaults (`prepare`).
    fn params(&self) -> Result<ChunkParams> {
        Ok(resolve_chunking(&ChunkParams::default(), None, &self.settings(), chunking_flag)?.params)
    }
}

/// Synthetic scene options (`ggpt-synth`) shared by `prepare` and `eval`.
#[derive(Args, Debug, Clone)]
struct SynthArgs {
    /// First synthetic seed (scene i gets first_seed + i).
    #[arg(long, default_value_t = 1000)]
    first_seed: u64,
    /// Views per synthetic scene; a list (`4,8`) is cycled over the scenes (after the kinds:
    /// scene `i` gets kind `i % kinds` and views `(i / kinds) % views`).
    #[arg(long, value_delimiter = ',', default_value = "4")]
    views: Vec<usize>,
    /// Synthetic ff width (multiple of 14).
    #[arg(long, default_value_t = 154)]
    width: usize,
    /// Synthetic ff height (multiple of 14).
    #[arg(long, default_value_t = 112)]
    height: usize,
    /// Synthetic scene kinds, alternated by seed (`room`, `object`).
    #[arg(long, value_delimiter = ',', default_value = "room,object")]
    kinds: Vec<String>,
}

impl SynthArgs {
    /// The spec of synthetic scene `i`.
    fn spec(&self, i: usize) -> Result<SynthSpec> {
        if self.kinds.is_empty() {
            bail!("--kinds is empty");
        }
        if self.views.is_empty() || self.views.iter().any(|&v| v < 2) {
            bail!("--views {:?}: every entry must be at least 2 (SfM needs two views)", self.views);
        }
        let kind = parse_kind(&self.kinds[i % self.kinds.len()])?;
        let views = self.views[(i / self.kinds.len()) % self.views.len()];
        Ok(SynthSpec { kind, views, width: self.width, height: self.height, seed: self.first_seed + i as u64 })
    }
}

#[derive(Args, Debug)]
struct PrepareArgs {
    /// Output chunk-set directory.
    #[arg(long)]
    out: PathBuf,
    /// Synthetic training scenes to generate (seeds first_seed, first_seed + 1, ...).
    #[arg(long, default_value_t = 0)]
    synthetic_train: usize,
    /// Synthetic validation (held-out) scenes, seeds following the training seeds.
    #[arg(long, default_value_t = 0)]
    synthetic_val: usize,
    #[command(flatten)]
    synth: SynthArgs,
    /// Official per-sequence directories (gt.bin, ff_outputs.bin, sfm_dlt_outputs.bin).
    #[arg(long, num_args = 1..)]
    official: Vec<PathBuf>,
    /// Fraction of the official directories held out for validation (split by scene, the last ones).
    #[arg(long, default_value_t = 0.1)]
    val_fraction: f64,
    /// Chunks drawn per scene.
    #[arg(long, default_value_t = 16)]
    chunks_per_scene: usize,
    /// Chunks per shard.
    #[arg(long, default_value_t = 64)]
    shard_chunks: usize,
    /// Seed of the RANSAC and chunk draws (combined with each scene name).
    #[arg(long, default_value_t = 42)]
    seed: u64,
    #[command(flatten)]
    chunking: ChunkingArgs,
}

#[derive(Args, Debug, Clone)]
struct TrainArgs {
    /// Chunk-set directory (from `prepare`).
    #[arg(long)]
    data: PathBuf,
    /// Output directory (metrics.jsonl, config.json, checkpoints/).
    #[arg(long)]
    out: PathBuf,
    /// Model configuration: preset `released`, `small`, `tiny`, or a model-config JSON file.
    #[arg(long, default_value = "small")]
    config: String,
    /// Maximum drop-path rate (network.md §11.3; overrides the config's 0.3).
    #[arg(long)]
    drop_path: Option<f64>,
    /// BatchNorm momentum of the running statistics (PyTorch convention; overrides the
    /// config's 0.01). Short runs want a larger value (e.g. 0.1): with 0.01 the running
    /// statistics that evaluation uses need several hundred steps to follow the weights.
    #[arg(long)]
    bn_momentum: Option<f64>,
    /// Total optimisation steps.
    #[arg(long, default_value_t = 1000)]
    steps: u64,
    /// Chunks per forward (paper: 24).
    #[arg(long, default_value_t = 4)]
    batch_size: usize,
    /// Adam learning rate (paper: 1e-4).
    #[arg(long, default_value_t = 1e-4)]
    lr: f64,
    /// Learning-rate schedule.
    #[arg(long, value_enum, default_value_t = LrSchedule::Constant)]
    lr_schedule: LrSchedule,
    /// Linear warm-up steps of the cosine schedule.
    #[arg(long, default_value_t = 0)]
    warmup_steps: u64,
    /// Clip the global gradient norm to this value (off by default).
    #[arg(long)]
    clip_grad_norm: Option<f64>,
    /// Seed of initialisation, batches and drop path.
    #[arg(long, default_value_t = 42)]
    seed: u64,
    /// Write a checkpoint every N steps (and always at exit).
    #[arg(long, default_value_t = 100)]
    save_every: u64,
    /// Validate on held-out chunks every N steps (0: only at the end).
    #[arg(long, default_value_t = 100)]
    val_every: u64,
    /// Validation chunks used (at most).
    #[arg(long, default_value_t = 64)]
    val_chunks: usize,
    /// Token budget of one validation forward.
    #[arg(long, default_value_t = 200_000)]
    val_max_tokens: usize,
    /// Checkpoints kept on disk.
    #[arg(long, default_value_t = 3)]
    keep_checkpoints: usize,
    /// Compute device: `cpu` (fastest CPU backend), `ndarray`, `flex`, `wgpu`.
    #[arg(long, default_value = "cpu")]
    device: String,
    /// Data-parallel replicas, one per listed device, main device first (e.g. `cpu,cpu` or
    /// `wgpu:0,wgpu:1`): the batch is split across them, gradients are averaged on the main
    /// device (docs/training.md). Overrides --device. Default: one replica on --device (on
    /// resume: the devices recorded in the checkpoint).
    #[arg(long, value_delimiter = ',')]
    devices: Option<Vec<String>>,
    /// Gradient accumulation: micro-batches per replica and step (the batch is split into
    /// replicas x K parts; BatchNorm sees each part's statistics). Default 1 (on resume: the
    /// checkpoint's).
    #[arg(long)]
    grad_accum: Option<usize>,
    /// Gradient computation: `segments` (default) re-runs each block segment in the backward
    /// and keeps only block-boundary tensors (a few KB per token: the released configuration
    /// trains 100k-token chunks in ~10 GB); `off` keeps every intermediate (plain autodiff,
    /// ~1.4 MB per token released). Same gradients up to float rounding (docs/training.md).
    /// Default `segments` (on resume: the checkpoint's).
    #[arg(long, value_enum)]
    recompute: Option<Recompute>,
    /// Resume: a bare `--resume` (or `--resume latest`) takes the newest complete checkpoint in
    /// `--out`; `--resume DIR` that checkpoint directory.
    #[arg(long, num_args = 0..=1, default_missing_value = RESUME_LATEST, value_name = "DIR|latest")]
    resume: Option<PathBuf>,
    /// Initialise from an official checkpoint (.pth / .safetensors / .bpk) for fine-tuning.
    #[arg(long)]
    init_from: Option<PathBuf>,
    /// Write `model.safetensors` + `model_config.json` of the final model into this directory.
    #[arg(long)]
    export_to: Option<PathBuf>,
}

#[derive(Args, Debug)]
struct EvalArgs {
    /// Chunk-set directory whose val scenes are evaluated (synthetic scenes are regenerated
    /// from their recorded spec, official ones read from their directory).
    #[arg(long, required_unless_present = "synthetic_scenes", conflicts_with = "synthetic_scenes")]
    data: Option<PathBuf>,
    /// Evaluate on this many freshly generated synthetic scenes instead (seeds `--first-seed`,
    /// `+1`, ...; choose seeds no training set used).
    #[arg(long)]
    synthetic_scenes: Option<usize>,
    #[command(flatten)]
    synth: SynthArgs,
    /// Model: a directory with model.safetensors + model_config.json (+ optional
    /// inference.json), a run or checkpoint directory (state.json + model.bpk), or a weight file
    /// with `--config`.
    #[arg(long)]
    model: PathBuf,
    /// Model config (preset or JSON) when `--model` is a bare weight file.
    #[arg(long)]
    config: Option<String>,
    /// Compute device.
    #[arg(long, default_value = "cpu")]
    device: String,
    /// Token budget of one forward.
    #[arg(long, default_value_t = 200_000)]
    max_tokens_per_forward: usize,
    /// Write the per-scene results here (JSON).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Chunk-level validation instead of whole scenes: the network on the first N recorded
    /// val chunks of `--data` (as during training; fast), AUC@5/10 cm of input vs refined.
    #[arg(long, requires = "data")]
    chunk_level: Option<usize>,
    #[command(flatten)]
    chunking: ChunkingArgs,
}

#[derive(Args, Debug)]
struct ExportArgs {
    /// Checkpoint directory (state.json + model.bpk), or a run directory (newest checkpoint).
    #[arg(long)]
    checkpoint: PathBuf,
    /// Output model folder: model.safetensors (official keys), model_config.json and, when the
    /// training chunk set is readable, inference.json with its chunk sampler settings.
    #[arg(long)]
    out_dir: PathBuf,
    /// Re-estimate the BatchNorm running statistics before exporting: this many training-mode
    /// forwards (no update, drop path off) over batches of the training split, averaged
    /// ("precise BN"; 0 = keep the checkpoint's running statistics).
    #[arg(long, default_value_t = 0)]
    bn_recalibrate_batches: usize,
    /// Chunks per recalibration forward (default: the run's batch size).
    #[arg(long)]
    bn_recalibrate_batch_size: Option<usize>,
}

#[derive(Args, Debug)]
struct GradsArgs {
    /// Weights: official `.pth` / `.safetensors`, or a burnpack `.bpk` of this project.
    #[arg(long)]
    weights: PathBuf,
    /// Model configuration JSON (the official `model_config` object, or a file with a
    /// `model_config` key such as a fixture manifest). Conflicts with `--preset`.
    #[arg(long, conflicts_with = "preset")]
    model_config: Option<PathBuf>,
    /// Built-in configuration: `released`, `small` (fixture) or `tiny`.
    #[arg(long)]
    preset: Option<String>,
    /// Input cases (safetensors): `case{K}/ff_pts`, `ff_pts_conf`, `geo_pts`, `geo_msks`,
    /// `gt_pts`, `gt_msks`, normalised chunk coordinates.
    #[arg(long)]
    input: PathBuf,
    /// Output (safetensors, written atomically): `case{K}/loss`, `l_conf`, `l_id`,
    /// `ff_pts_out`, `ff_pts_conf_out`, `grad/<name>`, `bn_after/<name>.running_mean|running_var`
    /// and, with --adam-step-lr, `case0/after_adam/<name>`.
    #[arg(long)]
    output: PathBuf,
    /// Compute device: `cpu`, `ndarray`, `flex` or `wgpu`.
    #[arg(long, default_value = "cpu")]
    device: String,
    /// After the case-0 backward, take one Adam step (betas 0.9 / 0.999, eps 1e-8, PyTorch
    /// semantics, the trainer's optimiser) with this learning rate.
    #[arg(long)]
    adam_step_lr: Option<f64>,
}

#[derive(Args, Debug)]
struct PlotArgs {
    /// metrics.jsonl of a run.
    #[arg(long)]
    metrics: PathBuf,
    /// Output PNG: one figure, training loss on top and (when the run has val lines)
    /// held-out chunk AUC@5/AUC@10 below, on a shared step axis.
    #[arg(long)]
    out: PathBuf,
    /// Moving-average window of the training loss.
    #[arg(long, default_value_t = 25)]
    smooth: usize,
    /// Image width in pixels.
    #[arg(long, default_value_t = 1000)]
    width: u32,
    /// Height of each panel in pixels (the image is one or two panels high).
    #[arg(long, default_value_t = 400)]
    panel_height: u32,
}

fn bar(len: u64, msg: &str) -> ProgressBar {
    let pb = ProgressBar::new(len);
    pb.set_style(
        ProgressStyle::with_template("{prefix} [{elapsed_precise}] {bar:30} {pos}/{len} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    pb.set_prefix(msg.to_string());
    pb.enable_steady_tick(Duration::from_millis(500));
    pb
}

fn parse_kind(s: &str) -> Result<ggpt_synth::SceneKind> {
    match s {
        "room" => Ok(ggpt_synth::SceneKind::Room),
        "object" => Ok(ggpt_synth::SceneKind::Object),
        o => bail!("unknown scene kind '{o}' (room, object)"),
    }
}

fn prepare(a: &PrepareArgs) -> Result<()> {
    let params = PrepareParams { chunks_per_scene: a.chunks_per_scene, chunking: a.chunking.params()?, seed: a.seed, ..PrepareParams::default() };
    let provenance = serde_json::json!({
        "tool": format!("ggpt-train {}", env!("CARGO_PKG_VERSION")),
        "params": params,
        "synthetic": {"train": a.synthetic_train, "val": a.synthetic_val, "first_seed": a.synth.first_seed, "views": a.synth.views,
                      "width": a.synth.width, "height": a.synth.height, "kinds": a.synth.kinds},
        "official": a.official,
    });
    let mut w = ChunkSetWriter::new(&a.out, a.shard_chunks, provenance)?;
    let n_syn = a.synthetic_train + a.synthetic_val;
    let n_val_off = ((a.official.len() as f64) * a.val_fraction).round() as usize;
    let total = n_syn + a.official.len();
    if total == 0 {
        bail!("nothing to prepare: give --synthetic-train/--synthetic-val and/or --official DIRS");
    }
    let pb = bar(total as u64, "prepare");
    let mut counts = [0usize; 2];
    for i in 0..n_syn {
        let spec = a.synth.spec(i)?;
        let split = if i < a.synthetic_train { Split::Train } else { Split::Val };
        let (scene, sfm) = synthetic_scene(&spec).with_context(|| format!("synthetic scene {spec:?}"))?;
        let prep = prepare_scene(&scene, &sfm, &params).with_context(|| format!("preparing {}", scene.name))?;
        let source = format!("synthetic:{}", serde_json::to_string(&spec)?);
        add_scene(&mut w, &scene, split, prep, source, &mut counts)?;
        pb.inc(1);
    }
    for (j, dir) in a.official.iter().enumerate() {
        let split = if j + n_val_off >= a.official.len() { Split::Val } else { Split::Train };
        let (scene, sfm) = official_scene(dir).with_context(|| format!("reading {}", dir.display()))?;
        let prep = prepare_scene(&scene, &sfm, &params).with_context(|| format!("preparing {}", dir.display()))?;
        add_scene(&mut w, &scene, split, prep, format!("official:{}", dir.display()), &mut counts)?;
        pb.inc(1);
    }
    pb.finish_and_clear();
    let m = w.finish()?;
    println!(
        "chunk set {}: {} scenes, {} train chunks, {} val chunks, {} shards",
        a.out.display(),
        m.scenes.len(),
        counts[0],
        counts[1],
        m.shards.len()
    );
    Ok(())
}

fn add_scene(w: &mut ChunkSetWriter, scene: &ggpt_core::Scene, split: Split, prep: ggpt_train::prepare::PreparedScene, source: String, counts: &mut [usize; 2]) -> Result<()> {
    let idx = w.add_scene(SceneEntry {
        name: scene.name.clone(),
        split,
        views: scene.dims.n,
        height: scene.dims.h,
        width: scene.dims.w,
        metres_per_unit: prep.metres_per_unit,
        source,
    });
    for mut c in prep.chunks {
        c.scene = idx;
        w.add_chunk(c)?;
        counts[usize::from(split == Split::Val)] += 1;
    }
    Ok(())
}

fn model_config(spec: &str) -> Result<GgptConfig> {
    let p = Path::new(spec);
    if p.is_file() {
        Ok(GgptConfig::from_json_file(p)?)
    } else {
        Ok(GgptConfig::preset(spec)?)
    }
}

static STOP: AtomicBool = AtomicBool::new(false);

extern "C" fn on_sigint(_: libc::c_int) {
    STOP.store(true, Ordering::SeqCst);
}

fn install_ctrl_c(flag: &Arc<AtomicBool>) {
    // SAFETY: the handler only stores into an atomic (async-signal-safe).
    unsafe {
        libc::signal(libc::SIGINT, on_sigint as *const () as libc::sighandler_t);
        libc::signal(libc::SIGTERM, on_sigint as *const () as libc::sighandler_t);
    }
    let f = flag.clone();
    std::thread::spawn(move || {
        loop {
            if STOP.load(Ordering::SeqCst) {
                f.store(true, Ordering::SeqCst);
                break;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    });
}

/// Value of a bare `--resume`: the newest complete checkpoint in `--out`.
const RESUME_LATEST: &str = "latest";

fn train(a: &TrainArgs) -> Result<()> {
    if a.grad_accum == Some(0) {
        bail!("--grad-accum 0: must be at least 1");
    }
    let data = ChunkSet::open(&a.data)?;
    let device_names: Vec<String> = match &a.devices {
        Some(list) if list.is_empty() => bail!("--devices: empty list"),
        Some(list) => list.clone(),
        None => vec![a.device.clone()],
    };
    let device = ggpt_model::device::device_from_name(&device_names[0])?;
    let ad = device.clone().autodiff();
    let resume_dir = match &a.resume {
        None => None,
        Some(p) if p.as_os_str() == RESUME_LATEST => {
            let list = trainer::list_checkpoints(&a.out)?;
            Some(list.last().map(|(_, d)| d.clone()).with_context(|| format!("--resume: no checkpoint in {}", a.out.display()))?)
        }
        Some(p) => Some(p.clone()),
    };
    let (model, optim, start, opts) = if let Some(dir) = resume_dir {
        let (m, o, st) = trainer::load_checkpoint(&dir, &ad)?;
        let mut opts = st.options.clone();
        opts.steps = a.steps; // allow extending a run
        if let Some(list) = &a.devices
            && *list != opts.devices
        {
            tracing::warn!("--devices {} differs from the checkpoint's {:?}: the trajectory changes", list.join(","), opts.devices);
            opts.devices = list.clone();
        }
        if let Some(k) = a.grad_accum
            && k != opts.grad_accum
        {
            tracing::warn!("--grad-accum {k} differs from the checkpoint's {}: the trajectory changes", opts.grad_accum);
            opts.grad_accum = k;
        }
        if let Some(r) = a.recompute
            && r != opts.recompute
        {
            tracing::info!("--recompute {r:?} differs from the checkpoint's {:?}: gradients change only by float rounding", opts.recompute);
            opts.recompute = r;
        }
        tracing::info!("resumed from {} at step {}", dir.display(), st.step);
        (m, o, st.step, opts)
    } else {
        let mut cfg = model_config(&a.config)?;
        if let Some(dp) = a.drop_path {
            cfg.drop_path = dp;
        }
        if let Some(m) = a.bn_momentum {
            if !(m > 0.0 && m <= 1.0) {
                bail!("--bn-momentum {m}: must be in (0, 1]");
            }
            cfg.bn_momentum = m;
        }
        device.seed(a.seed);
        let mut m = Ggpt::new(&cfg, &device);
        if let Some(init) = &a.init_from {
            m = ggpt_model::weights::load_checkpoint(m, init).with_context(|| format!("--init-from {}", init.display()))?;
        }
        let opts = TrainOptions {
            model: cfg,
            steps: a.steps,
            batch_size: a.batch_size.max(1),
            lr: a.lr,
            lr_schedule: a.lr_schedule,
            warmup_steps: a.warmup_steps,
            clip_grad_norm: a.clip_grad_norm,
            seed: a.seed,
            save_every: a.save_every,
            val_every: a.val_every,
            val_chunks: a.val_chunks,
            val_max_tokens: a.val_max_tokens,
            keep_checkpoints: a.keep_checkpoints,
            grad_accum: a.grad_accum.unwrap_or(1),
            devices: if a.devices.is_some() { device_names.clone() } else { Vec::new() },
            recompute: a.recompute.unwrap_or_default(),
        };
        (m.fork(&ad).train(), trainer::adam(), 0, opts)
    };
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let cfg_path = a.out.join("config.json");
    // the replicas: the recorded devices (a resumed run keeps its own), else --device
    let replica_names: Vec<String> = if opts.devices.is_empty() { vec![a.device.clone()] } else { opts.devices.clone() };
    let replicas: Vec<burn::tensor::Device> = replica_names
        .iter()
        .map(|n| ggpt_model::device::device_from_name(n).map(|d| d.autodiff()))
        .collect::<std::result::Result<_, _>>()?;
    let ad = replicas[0].clone();
    let parts = replicas.len() * opts.grad_accum.max(1);
    if opts.batch_size < parts {
        bail!("--batch-size {} is smaller than {} replica(s) x --grad-accum {}: every micro-batch needs a chunk", opts.batch_size, replicas.len(), opts.grad_accum);
    }
    let batchnorm = if parts == 1 {
        "batch statistics over all chunks of one forward".to_string()
    } else {
        format!(
            "batch statistics per micro-batch: the batch of {} chunks is split into {} replica(s) x {} micro-batch(es) of about {} chunks; \
             running statistics updated sequentially within a replica and averaged over replicas",
            opts.batch_size,
            replicas.len(),
            opts.grad_accum,
            opts.batch_size / parts
        )
    };
    let run_cfg = serde_json::json!({"options": opts, "data": a.data, "device": replica_names[0], "replicas": replica_names,
        "grad_accum": opts.grad_accum, "recompute": opts.recompute, "init_from": a.init_from,
        "parameters": ggpt_model::weights::num_trainable_params(&model),
        "batchnorm": batchnorm});
    ggpt_core::io::atomic::write_json_atomic(&cfg_path, &run_cfg)?;
    tracing::info!("training {} parameters on {} ({} steps from {start})", ggpt_model::weights::num_trainable_params(&model), a.device, opts.steps);
    let stop = Arc::new(AtomicBool::new(false));
    install_ctrl_c(&stop);
    let pb = bar(opts.steps, "train");
    pb.set_position(start);
    let mut on_step = |l: &MetricsLine| {
        pb.set_position(l.step);
        pb.set_message(format!(
            "loss {:.4} (conf {:.4}, id {:.4}) {:.2} chunks/s {:.0} tok/s",
            l.loss,
            l.loss_conf.unwrap_or(f64::NAN),
            l.loss_id.unwrap_or(f64::NAN),
            l.chunks_per_s,
            l.tokens_per_s
        ));
    };
    let res = trainer::run(&opts, RunContext { out: &a.out, data: &data, device: ad, replicas, model, optim, start_step: start, stop, on_step: &mut on_step })?;
    pb.finish_and_clear();
    if res.interrupted {
        println!("interrupted at step {}: checkpoint written to {}", res.steps, trainer::checkpoint_dir(&a.out, res.steps).display());
    } else {
        println!("trained {} steps; checkpoint {}", res.steps, trainer::checkpoint_dir(&a.out, res.steps).display());
    }
    if let Some(v) = &res.validation {
        println!(
            "held-out chunks: AUC@5 input {:.1} -> refined {:.1}; AUC@10 {:.1} -> {:.1} (val loss {:.4})",
            v.input_auc5, v.refined_auc5, v.input_auc10, v.refined_auc10, v.loss
        );
    }
    if let Some(dir) = &a.export_to {
        let chunking = ggpt_train::export::training_chunking(&data.manifest.provenance);
        ggpt_train::export::export_model_dir(&res.model, res.steps, &opts.model, chunking, dir)?;
        println!("exported {}", dir.display());
    }
    Ok(())
}


/// The sampler settings a model was trained with, and the file they come from.
type ModelChunking = Option<(PathBuf, Option<ChunkingSettings>)>;

/// A model from any of the forms `eval` accepts, with its configuration and, for a model folder,
/// its `inference.json` (a checkpoint's sampler settings come from its chunk set's manifest).
fn load_model_any(path: &Path, config: Option<&str>, device: &burn::tensor::Device) -> Result<(Ggpt, GgptConfig, ModelChunking)> {
    let checkpoint = if path.join("state.json").is_file() {
        Some(path.to_path_buf())
    } else if path.is_dir() && !path.join(MODEL_WEIGHTS_FILE).is_file() {
        trainer::list_checkpoints(path)?.last().map(|(_, d)| d.clone())
    } else {
        None
    };
    if let Some(dir) = checkpoint {
        let (m, _, st) = trainer::load_checkpoint(&dir, device)?;
        let chunking = ChunkSet::open(&st.data).ok().map(|set| (st.data.clone(), ggpt_train::export::training_chunking(&set.manifest.provenance)));
        return Ok((m, st.options.model, chunking));
    }
    let spec = match config {
        None => resolve_model(path, None, None)?,
        Some(c) if Path::new(c).is_file() => resolve_model(path, Some(Path::new(c)), None)?,
        Some(preset) => resolve_model(path, None, Some(preset))?,
    };
    let m = load_model(&spec, device)?;
    let chunking = spec.inference.map(|i| (i.path, i.settings.chunking));
    Ok((m, spec.config, chunking))
}

/// A scene to evaluate: a recorded chunk-set scene or a fresh synthetic one.
enum EvalScene {
    Recorded(SceneEntry),
    Synthetic(SynthSpec),
}

impl EvalScene {
    fn load(&self) -> Result<(ggpt_core::Scene, ggpt_core::SfmResult)> {
        match self {
            EvalScene::Synthetic(spec) => Ok(synthetic_scene(spec)?),
            EvalScene::Recorded(s) => {
                if let Some(js) = s.source.strip_prefix("synthetic:") {
                    let spec: SynthSpec = serde_json::from_str(js).with_context(|| format!("scene {}: synthetic spec", s.name))?;
                    Ok(synthetic_scene(&spec)?)
                } else if let Some(dir) = s.source.strip_prefix("official:") {
                    Ok(official_scene(Path::new(dir))?)
                } else {
                    bail!("scene {}: unknown source '{}'", s.name, s.source)
                }
            }
        }
    }
}

fn eval(a: &EvalArgs) -> Result<()> {
    let device = ggpt_model::device::device_from_name(&a.device)?;
    let (model, cfg, model_chunking) = load_model_any(&a.model, a.config.as_deref(), &device)?;
    if let (Some(n), Some(dir)) = (a.chunk_level, &a.data) {
        let data = ChunkSet::open(dir)?;
        let mut val = data.load_split(Split::Val)?;
        val.truncate(n);
        if val.is_empty() {
            bail!("{}: no val chunk", dir.display());
        }
        let v = ggpt_train::evaluate::validate_chunks(&model, &cfg, &val, &data.manifest.scenes, &device, a.max_tokens_per_forward)?;
        println!(
            "{} val chunks: AUC@5 input {:.1} -> refined {:.1} ({:+.1}); AUC@10 {:.1} -> {:.1} ({:+.1}); val loss {:.4}",
            v.chunks,
            v.input_auc5,
            v.refined_auc5,
            v.refined_auc5 - v.input_auc5,
            v.input_auc10,
            v.refined_auc10,
            v.refined_auc10 - v.input_auc10,
            v.loss
        );
        if let Some(out) = &a.out {
            let j = serde_json::json!({"chunk_level": v, "model": a.model, "data": dir});
            ggpt_core::io::atomic::write_json_atomic(out, &j)?;
        }
        return Ok(());
    }
    // flag > the model's training sampler (inference.json / chunk-set manifest) > default
    let layer = model_chunking.as_ref().map(|(path, c)| (path.as_path(), c.as_ref()));
    let resolved = resolve_chunking(&ChunkParams::default(), layer, &a.chunking.settings(), chunking_flag)?;
    tracing::info!("chunk sampler: {}", resolved.describe());
    let chunking = resolved.params;
    let mut refiner = ggpt_infer::refiner::BurnRefiner::new(model.valid().fork(&device), cfg.clone(), device.clone())?;
    let opts = RefineOptions { chunking: chunking.clone(), max_tokens_per_forward: a.max_tokens_per_forward, ..RefineOptions::default() };
    let scenes: Vec<EvalScene> = match (&a.data, a.synthetic_scenes) {
        (_, Some(n)) => (0..n).map(|i| a.synth.spec(i).map(EvalScene::Synthetic)).collect::<Result<_>>()?,
        (Some(dir), None) => {
            let data = ChunkSet::open(dir)?;
            let val: Vec<EvalScene> = data.manifest.scenes.into_iter().filter(|s| s.split == Split::Val).map(EvalScene::Recorded).collect();
            if val.is_empty() {
                bail!("{}: no val scene", dir.display());
            }
            val
        }
        (None, None) => bail!("give --data DIR or --synthetic-scenes N"),
    };
    if scenes.is_empty() {
        bail!("no scene to evaluate");
    }
    let pb = bar(scenes.len() as u64, "eval");
    let mut results: Vec<HeldOutScene> = Vec::new();
    for s in &scenes {
        let (scene, sfm) = s.load()?;
        let r = evaluate_scene(&scene, &sfm, &mut refiner, &opts).with_context(|| format!("evaluating {}", scene.name))?;
        pb.inc(1);
        pb.println(format!(
            "{:<28} ff AUC@5 {:5.1} AUC@10 {:5.1} | refined AUC@5 {:5.1} AUC@10 {:5.1} | DLT AUC@5 {} | covered {:.2} | {} chunks",
            r.name,
            r.ff_auc5,
            r.ff_auc10,
            r.refined_auc5,
            r.refined_auc10,
            r.sfm_auc5.map_or("    -".to_string(), |v| format!("{v:5.1}")),
            r.covered,
            r.chunks
        ));
        results.push(r);
    }
    pb.finish_and_clear();
    let n = results.len() as f64;
    let mean = |f: fn(&HeldOutScene) -> f64| results.iter().map(f).sum::<f64>() / n;
    let sfm: Vec<f64> = results.iter().filter_map(|r| r.sfm_auc5).collect();
    let sfm_mean = (!sfm.is_empty()).then(|| sfm.iter().sum::<f64>() / sfm.len() as f64);
    let summary = serde_json::json!({
        "scenes": results.len(),
        "ff_auc5": mean(|r| r.ff_auc5), "ff_auc10": mean(|r| r.ff_auc10),
        "refined_auc5": mean(|r| r.refined_auc5), "refined_auc10": mean(|r| r.refined_auc10),
        "sfm_auc5": sfm_mean,
    });
    println!(
        "mean over {} held-out scenes: AUC@5 {:.1} -> {:.1} ({:+.1}), AUC@10 {:.1} -> {:.1} ({:+.1})",
        results.len(),
        mean(|r| r.ff_auc5),
        mean(|r| r.refined_auc5),
        mean(|r| r.refined_auc5) - mean(|r| r.ff_auc5),
        mean(|r| r.ff_auc10),
        mean(|r| r.refined_auc10),
        mean(|r| r.refined_auc10) - mean(|r| r.ff_auc10)
    );
    if let Some(out) = &a.out {
        let v = serde_json::json!({"summary": summary, "scenes": results, "model": a.model, "data": a.data,
            "synthetic": a.synthetic_scenes.map(|n| serde_json::json!({"scenes": n, "first_seed": a.synth.first_seed, "views": a.synth.views,
                "width": a.synth.width, "height": a.synth.height, "kinds": a.synth.kinds})),
            "chunking": chunking});
        ggpt_core::io::atomic::write_json_atomic(out, &v)?;
    }
    Ok(())
}

fn export(a: &ExportArgs) -> Result<()> {
    let device = ggpt_model::device::device_from_name("cpu")?;
    let dir = if a.checkpoint.join("state.json").is_file() {
        a.checkpoint.clone()
    } else {
        trainer::list_checkpoints(&a.checkpoint)?.last().map(|(_, d)| d.clone()).with_context(|| format!("no checkpoint in {}", a.checkpoint.display()))?
    };
    let (mut model, _, st) = trainer::load_checkpoint(&dir, &device)?;
    let set = ChunkSet::open(&st.data);
    if a.bn_recalibrate_batches > 0 {
        let set = set.as_ref().map_err(|e| anyhow::anyhow!("--bn-recalibrate-batches needs the training chunk set {}: {e}", st.data.display()))?;
        let chunks = set.load_split(Split::Train)?;
        let batch = a.bn_recalibrate_batch_size.unwrap_or(st.options.batch_size);
        tracing::info!("re-estimating BatchNorm statistics over {} batches of {batch} training chunks", a.bn_recalibrate_batches);
        model = trainer::recalibrate_batch_norm(model, &st.options.model, &chunks, batch, a.bn_recalibrate_batches, st.options.seed, &device.clone().autodiff())?;
    }
    let chunking = match &set {
        Ok(set) => ggpt_train::export::training_chunking(&set.manifest.provenance),
        Err(e) => {
            tracing::warn!("training chunk set {} unreadable ({e}): no inference.json written", st.data.display());
            None
        }
    };
    ggpt_train::export::export_model_dir(&model, st.step, &st.options.model, chunking, &a.out_dir)?;
    // strict reload check
    ggpt_model::weights::load_checkpoint(Ggpt::new(&st.options.model, &device), &a.out_dir.join(MODEL_WEIGHTS_FILE)).context("strict reload of the export")?;
    println!("exported step {} to {} (strict reload ok)", st.step, a.out_dir.display());
    Ok(())
}

fn plot(a: &PlotArgs) -> Result<()> {
    use ggpt_train::plot::{FigureOptions, read_metrics, write_figure};
    let m = read_metrics(&a.metrics)?;
    // the run directory's name (metrics.jsonl lives in the run directory)
    let run_label = a.metrics.parent().and_then(|d| d.file_name()).map(|n| n.to_string_lossy().into_owned());
    let o = FigureOptions { smooth: a.smooth, width: a.width, panel_height: a.panel_height, run_label };
    let s = write_figure(&a.out, &m, &o).with_context(|| format!("plotting {}", a.metrics.display()))?;
    println!(
        "{}: {}x{} PNG; top: training loss (light red: per step, bold red: moving average over {} steps), steps {:.0}..{:.0}, loss {:.4}..{:.4}, last average {:.4} at step {:.0}",
        a.out.display(),
        s.width,
        s.height,
        a.smooth.max(1),
        s.steps.0,
        s.steps.1,
        s.loss.0,
        s.loss.1,
        s.last_loss_avg.1,
        s.last_loss_avg.0
    );
    match (s.auc, s.last_val) {
        (Some(r), Some(v)) => println!(
            "  bottom: held-out chunk AUC (%) over {} val lines, AUC@5 input (grey) vs refined (blue), AUC@10 dashed/lighter; AUC {:.1}..{:.1}; last (step {:.0}): AUC@5 {:.1} -> {:.1}, AUC@10 {:.1} -> {:.1}",
            m.val.len(),
            r.0,
            r.1,
            v.step,
            v.input_auc5,
            v.refined_auc5,
            v.input_auc10,
            v.refined_auc10
        ),
        _ => println!("  no validation line (kind \"val\") yet: loss panel only"),
    }
    Ok(())
}

fn default_run(out: &Path) -> Result<()> {
    println!("ggpt-train without arguments: building a small synthetic chunk set and training the tiny configuration");
    println!("(see `ggpt-train --help` for the real commands)");
    let data = out.join("chunkset");
    let prep = PrepareArgs {
        out: data.clone(),
        synthetic_train: 3,
        synthetic_val: 1,
        synth: SynthArgs { first_seed: 1, views: vec![3], width: 98, height: 70, kinds: vec!["room".into(), "object".into()] },
        official: Vec::new(),
        val_fraction: 0.0,
        chunks_per_scene: 4,
        shard_chunks: 64,
        seed: 42,
        chunking: ChunkingArgs { chunk_size: None, max_pixels: Some(1500), min_dlt: Some(20), min_pixels: Some(200) },
    };
    let t = Instant::now();
    prepare(&prep)?;
    tracing::info!("prepared in {:.1} s", t.elapsed().as_secs_f64());
    train(&TrainArgs {
        data,
        out: out.join("run"),
        config: "tiny".into(),
        drop_path: None,
        bn_momentum: None,
        steps: 20,
        batch_size: 2,
        lr: 1e-3,
        lr_schedule: LrSchedule::Constant,
        warmup_steps: 0,
        clip_grad_norm: None,
        seed: 42,
        save_every: 10,
        val_every: 10,
        val_chunks: 8,
        val_max_tokens: 200_000,
        keep_checkpoints: 2,
        device: "cpu".into(),
        devices: None,
        grad_accum: None,
        recompute: None,
        resume: None,
        init_from: None,
        export_to: None,
    })
}

/// Pins Burn's default device (`BURN_DEVICE`, unless the user set it) to the backend of the
/// requested device, so that a CPU run touches no GPU API: Burn 0.22.1 restores the optimizer
/// state of `--resume` on `Device::default()`, which is a wgpu adapter when wgpu is compiled in
/// (a Vulkan probe, and XDG_RUNTIME_DIR errors on headless machines).
fn grads(a: &GradsArgs) -> Result<()> {
    if let Some(lr) = a.adam_step_lr
        && !(lr.is_finite() && lr > 0.0)
    {
        bail!("--adam-step-lr {lr}: must be a finite number > 0");
    }
    let cfg = match (&a.model_config, &a.preset) {
        (Some(path), _) => GgptConfig::from_json_file(path)?,
        (None, Some(name)) => GgptConfig::preset(name)?,
        (None, None) => bail!("give --model-config FILE or --preset released|small|tiny"),
    };
    let plain = ggpt_model::device::device_from_name(&a.device)?;
    let device = plain.clone().autodiff();
    let fresh = ggpt_model::weights::load_checkpoint(Ggpt::new(&cfg, &plain), &a.weights).with_context(|| format!("loading weights {}", a.weights.display()))?;
    let cases = ggpt_train::grads::read_cases(&a.input).with_context(|| format!("reading {}", a.input.display()))?;
    let bar = ProgressBar::new(cases.len() as u64);
    bar.set_style(ProgressStyle::with_template("{bar:30} {pos}/{len} cases [{elapsed_precise}]").unwrap_or_else(|_| ProgressStyle::default_bar()));
    let mut results = Vec::with_capacity(cases.len());
    for (k, case) in cases.iter().enumerate() {
        let lr = if k == 0 { a.adam_step_lr } else { None };
        let r = ggpt_train::grads::run_case(&fresh, &cfg, case, &device, lr).with_context(|| format!("case {k}"))?;
        tracing::info!("case {k}: {} tokens, L {:.6} (L_conf {:.6}, L_id {:.6}), {} gradients", case.num_tokens(), r.loss[0], r.loss[1], r.loss[2], r.grads.len());
        results.push(r);
        bar.inc(1);
    }
    bar.finish_and_clear();
    ggpt_train::grads::write_results(&a.output, &results).with_context(|| format!("writing {}", a.output.display()))?;
    println!("{}", a.output.display());
    Ok(())
}

fn pin_default_device(device: &str) {
    if std::env::var_os("BURN_DEVICE").is_none()
        && let Some(name) = ggpt_model::device::default_device_env_name(device)
    {
        // SAFETY: called at the start of `main`, before any other thread exists.
        unsafe { std::env::set_var("BURN_DEVICE", name) };
    }
}

fn main() -> Result<()> {
    ggpt_model::device::tune_allocator();
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")))
        .init();
    let cli = Cli::parse();
    pin_default_device(match &cli.command {
        Some(Command::Train(a)) => a.devices.as_ref().and_then(|d| d.first()).unwrap_or(&a.device),
        Some(Command::Eval(a)) => &a.device,
        Some(Command::Grads(a)) => &a.device,
        _ => "cpu",
    });
    match &cli.command {
        None => default_run(&cli.out),
        Some(Command::Prepare(a)) => prepare(a),
        Some(Command::Train(a)) => train(a),
        Some(Command::Eval(a)) => eval(a),
        Some(Command::Export(a)) => export(a),
        Some(Command::Plot(a)) => plot(a),
        Some(Command::Grads(a)) => grads(a),
    }
}
