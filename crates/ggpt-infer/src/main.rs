//! `ggpt-infer`: run the GGPT network.
//!
//! Subcommands:
//! * `run` — whole-scene refinement of a scene directory (SfM first when the scene has only
//!   feed-forward outputs and matches), with export, evaluation and error maps (`docs/inference.md`);
//! * `demo` — synthetic scene -> SfM -> refinement with the shipped model -> AUC table;
//! * `chunk` — run the network on prepared chunk records (safetensors in, safetensors out).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand, ValueEnum};
use ggpt_cli::{
    ChunkingArgs, DeviceArgs, ModelArgs, ProgressArgs, RegimeArg, SceneKindArg, SfmPresetArg,
    StageBars,
};
use ggpt_core::io::feedforward::{FfReadOptions, VggtBranch};
use ggpt_eval::format_refinement_table as format_table;
use ggpt_infer::Refiner;
use ggpt_infer::demo::{DemoOptions, run_demo};
use ggpt_infer::inputs::{original_images, scene_from_files};
use ggpt_infer::pipeline::{RunOptions, RunReport, save_run};
use ggpt_infer::rss::{StageLog, StageTiming};
use ggpt_infer::run_output;
use ggpt_model::chunk_io::{chunk_outputs_to_bytes, read_chunk_inputs};
use ggpt_model::device::device_from_name;
use ggpt_model::infer::prepare_chunks;
use ggpt_model::model_dir::resolve_model;
use ggpt_model::weights::load_checkpoint;
use ggpt_model::{Ggpt, GgptConfig};
use ggpt_scene::driver::RefineOptions;
use ggpt_scene::export::{ColmapExportOptions, ExportOptions};
use ggpt_scene::fusion::FusionMode;
use ggpt_sfm::masks::Preset;
use tracing::info;

/// GGPT inference.
#[derive(Parser, Debug)]
#[command(name = "ggpt-infer", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Refine a whole scene: reads a scene directory (project format, official
    /// `ff_outputs.bin` + `sfm_dlt_outputs.bin` [+ `gt.bin`], or `images/` + `ff.npz` +
    /// `matches/` [+ `sfm.npz`]); runs the SfM stage first when the scene has no SfM result;
    /// writes refined points (safetensors, npy), PLY, COLMAP, config/meta JSON, and with ground
    /// truth an evaluation JSON and per-view error maps into `--out`.
    Run(RunArgs),
    /// Synthetic end-to-end demo: generates a scene with ggpt-synth, runs SfM and refinement
    /// with the shipped model (`models/ggpt-synth-small/`), prints the AUC table before/after.
    Demo(DemoArgs),
    /// Run the network on chunk records: reads `chunk{c}/ff_pts`, `ff_pts_conf`, `geo_pts`,
    /// `geo_msks` (normalised chunk coordinates) and writes `chunk{c}/ff_pts_out`,
    /// `ff_pts_conf_out`, `geo_pts_out`, `geo_pts_conf_out`, `tokens_xyz_out`, `tokens_conf_out`.
    /// Each chunk is one forward (batch size 1, as the official inference); timing per chunk
    /// goes to stderr.
    Chunk(ChunkArgs),
}

/// Options of `ggpt-infer chunk`.
#[derive(Args, Debug)]
struct ChunkArgs {
    /// The network: `--weights` (official `.pth` / `.safetensors` or a project `.bpk`) with
    /// `--model-config FILE` or `--preset NAME`.
    #[command(flatten)]
    model: ModelArgs,
    /// Input chunk records (safetensors).
    #[arg(long)]
    input: PathBuf,
    /// Output file (safetensors), written atomically.
    #[arg(long)]
    output: PathBuf,
    #[command(flatten)]
    device: DeviceArgs,
    /// Run all chunks in one batched forward instead of one forward per chunk.
    #[arg(long)]
    batched: bool,
}

/// `--fusion`: how overlapping chunks are fused (`ggpt_scene::fusion::FusionMode`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
enum FusionArg {
    /// The official plain mean.
    Mean,
    /// Confidence-weighted mean (an extension).
    Confidence,
}

impl From<FusionArg> for FusionMode {
    fn from(f: FusionArg) -> Self {
        match f {
            FusionArg::Mean => FusionMode::Mean,
            FusionArg::Confidence => FusionMode::ConfidenceWeighted,
        }
    }
}

/// `--colmap-points`: the `points3D` of the exported COLMAP model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
enum ColmapPointsArg {
    /// The confidence-filtered refined points, a seeded subset of at most
    /// `--colmap-max-points`.
    Refined,
    /// Cameras and images only.
    None,
}

/// Options shared by `run` and `demo`.
#[derive(Args, Debug)]
struct CommonArgs {
    #[command(flatten)]
    device: DeviceArgs,
    /// Fusion of overlapping chunks.
    #[arg(long, value_enum, default_value_t = FusionArg::Mean)]
    fusion: FusionArg,
    /// PLY confidence filter: keep pixels with confidence >= this quantile of all confidences.
    #[arg(long, default_value_t = ggpt_scene::export::DEFAULT_CONF_QUANTILE)]
    conf_quantile: f64,
    /// Maximum number of points in the PLY files (seeded uniform subset).
    #[arg(long, default_value_t = ggpt_scene::export::DEFAULT_MAX_POINTS)]
    max_points: usize,
    /// Token budget of one network forward (several chunks per forward up to this; a larger
    /// chunk runs alone). Bounds the memory.
    #[arg(long, default_value_t = ggpt_scene::driver::DEFAULT_MAX_TOKENS_PER_FORWARD)]
    max_tokens_per_forward: usize,
    /// Chunk sampler flags; a flag that is not given comes from the model folder's
    /// `inference.json`, else the official default.
    #[command(flatten)]
    chunking: ChunkingArgs,
    /// SfM threshold preset when the SfM stage runs.
    #[arg(long, value_enum, default_value_t)]
    sfm_preset: SfmPresetArg,
    /// With no DLT point at all (empty guidance), export the unrefined feed-forward points
    /// (confidence 0) instead of failing.
    #[arg(long)]
    allow_unrefined: bool,
    /// Write the COLMAP model as text instead of binary.
    #[arg(long)]
    colmap_text: bool,
    /// `points3D` of the COLMAP model.
    #[arg(long, value_enum, default_value_t = ColmapPointsArg::Refined)]
    colmap_points: ColmapPointsArg,
    /// Maximum number of COLMAP `points3D` (seeded uniform subset of the filtered points).
    #[arg(long, default_value_t = ggpt_scene::export::DEFAULT_COLMAP_MAX_POINTS)]
    colmap_max_points: usize,
    /// Resolution of the COLMAP / `transforms.json` cameras: `ff` (the feed-forward resolution,
    /// or each `--images` file's own) or `WIDTHxHEIGHT` for every view (focal lengths and the
    /// principal point scaled per axis).
    #[arg(long, default_value = "ff", value_name = "ff|WxH")]
    colmap_resolution: String,
    /// COLMAP `SIMPLE_PINHOLE` cameras (one focal length) instead of `PINHOLE`.
    #[arg(long)]
    colmap_simple_pinhole: bool,
    /// Keep one refined point per cube of this side (scene units, SfM frame) in the PLY files
    /// and the COLMAP points (the most confident), before `--max-points`.
    #[arg(long, value_name = "SIDE")]
    voxel_size: Option<f64>,
    /// Skip the splat-ready part beside `sparse/0`: `images/` and nerfstudio's
    /// `transforms.json`.
    #[arg(long)]
    no_splat: bool,
    /// Skip the per-view PNG error maps (written only when the scene has ground truth).
    #[arg(long)]
    no_error_maps: bool,
    /// Upper end of the error-map colour scale (cm).
    #[arg(long, default_value_t = ggpt_eval::error_maps::DEFAULT_ERROR_MAP_MAX_CM)]
    error_map_max_cm: f64,
    #[command(flatten)]
    progress: ProgressArgs,
}

/// `--ff-branch`: which VGGT head gives the points.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ValueEnum)]
enum FfBranchArg {
    /// `depth` unprojected with the predicted cameras (the official demo's `vggt-depth`).
    #[default]
    Depth,
    /// The point head `world_points` (`vggt-point`).
    Points,
}

/// Options of `ggpt-infer run`.
#[derive(Args, Debug)]
struct RunArgs {
    /// Scene directory (or give `--ff` and `--matches`).
    #[arg(long, required_unless_present = "ff", conflicts_with = "ff")]
    scene: Option<PathBuf>,
    /// Feed-forward outputs instead of a scene: VGGT's `predictions.npz`, MapAnything / Pi3
    /// outputs saved as `.npz`, a project `ff.npz`, the official `ff_outputs.bin` (the layout is
    /// detected from the keys; docs/formats.md).
    #[arg(long, requires = "matches", value_name = "FILE")]
    ff: Option<PathBuf>,
    /// Dense matches for `--ff`: a folder of `<matcher>.safetensors`, one such file, or the
    /// raw-matcher layout (docs/sfm.md).
    #[arg(long, value_name = "PATH")]
    matches: Option<PathBuf>,
    /// VGGT's branch of `--ff`.
    #[arg(long, value_enum, default_value_t)]
    ff_branch: FfBranchArg,
    /// The original images (`.jpg`/`.jpeg`/`.png`, name order = view order): their names and
    /// sizes go into the COLMAP model and `transforms.json` (cameras at each image's own
    /// resolution) and they are linked into `<out>/images/`; with `--ff` also the colours when
    /// the prediction has no images.
    #[arg(long, value_name = "DIR")]
    images: Option<PathBuf>,
    /// The network (`--weights` is required).
    #[command(flatten)]
    model: ModelArgs,
    /// Output folder.
    #[arg(long)]
    out: PathBuf,
    /// Seed of RANSAC, SfM and export subsampling (default 42); when given, it also replaces
    /// the per-scene chunk seed crc32(scene name).
    #[arg(long)]
    seed: Option<u64>,
    #[command(flatten)]
    common: CommonArgs,
}

/// Options of `ggpt-infer demo`.
#[derive(Args, Debug)]
struct DemoArgs {
    /// Number of views.
    #[arg(long, default_value_t = 8)]
    views: usize,
    /// Seed of the scene generator, RANSAC, SfM and export.
    #[arg(long, default_value_t = 42)]
    seed: u64,
    /// Scene family.
    #[arg(long, value_enum, default_value_t)]
    kind: SceneKindArg,
    /// Simulation regime: `benchmark` (matcher failure modes, structured feed-forward error,
    /// the paper's ranges) or `easy` (the first, dense and clean regime; docs/synthetic.md).
    #[arg(long, value_enum, default_value_t)]
    regime: RegimeArg,
    /// Feed-forward width (multiple of 14).
    #[arg(long, default_value_t = 518)]
    width: usize,
    /// Feed-forward height (multiple of 14).
    #[arg(long, default_value_t = 392)]
    height: usize,
    /// Output folder (the scene goes to `<out>/scene`).
    #[arg(long, default_value = "ggpt_demo")]
    out: PathBuf,
    /// The network (default: the shipped `models/ggpt-synth-small/`, embedded in the binary).
    #[command(flatten)]
    model: ModelArgs,
    #[command(flatten)]
    common: CommonArgs,
}

fn configure_threads(threads: usize) -> Result<()> {
    if threads > 0 {
        // SAFETY: called before any other thread of this process exists (the thread pools of
        // the backends are created lazily afterwards); matrixmultiply reads it once.
        unsafe { std::env::set_var("MATMUL_NUM_THREADS", threads.to_string()) };
    }
    ggpt_model::device::init_cpu_threads(threads).context("configuring the thread pool")
}

/// `--colmap-resolution`: `ff` -> `None`, `WIDTHxHEIGHT` -> `Some((height, width))`.
fn parse_colmap_resolution(s: &str) -> Result<Option<(usize, usize)>> {
    if s == "ff" {
        return Ok(None);
    }
    let parsed = s.split_once(['x', 'X']).and_then(|(w, h)| {
        Some((
            w.trim().parse::<usize>().ok()?,
            h.trim().parse::<usize>().ok()?,
        ))
    });
    match parsed {
        Some((w, h)) if w > 0 && h > 0 => Ok(Some((h, w))),
        _ => bail!(
            "--colmap-resolution {s:?}: expected `ff` or WIDTHxHEIGHT with positive integers (e.g. 1036x784)"
        ),
    }
}

fn run_options(c: &CommonArgs, seed: u64, chunk_seed: Option<u64>) -> Result<RunOptions> {
    if !(0.0..=1.0).contains(&c.conf_quantile) {
        bail!("--conf-quantile {} must be in [0, 1]", c.conf_quantile);
    }
    if c.max_tokens_per_forward == 0 {
        bail!("--max-tokens-per-forward must be positive");
    }
    let refine = RefineOptions {
        seed,
        chunk_seed,
        max_tokens_per_forward: c.max_tokens_per_forward,
        fusion: c.fusion.into(),
        allow_unrefined: c.allow_unrefined,
        ..RefineOptions::default()
    };
    let chunking = c.chunking.settings();
    chunking
        .validate(ChunkingArgs::flag)
        .map_err(anyhow::Error::msg)?;
    let export = ExportOptions {
        conf_quantile: c.conf_quantile,
        max_points: c.max_points,
        seed,
        colmap: Some(ColmapExportOptions {
            text: c.colmap_text,
            points: c.colmap_points == ColmapPointsArg::Refined,
            max_points: c.colmap_max_points,
            resolution: parse_colmap_resolution(&c.colmap_resolution)?,
            simple_pinhole: c.colmap_simple_pinhole,
            ..ColmapExportOptions::default()
        }),
        splat: !c.no_splat,
        voxel_size: match c.voxel_size {
            Some(v) if !(v.is_finite() && v > 0.0) => bail!("--voxel-size {v} must be positive"),
            v => v,
        },
        ..ExportOptions::default()
    };
    Ok(RunOptions {
        refine,
        chunking,
        export,
        sfm_preset: Preset::parse(c.sfm_preset.name())?,
        evaluate: true,
        error_maps: !c.no_error_maps,
        error_map_max_cm: c.error_map_max_cm,
    })
}

fn print_stages(stages: &[StageTiming]) {
    println!("{:<20} {:>10} {:>14}", "stage", "seconds", "peak RSS MiB");
    for s in stages {
        let m = s
            .peak_rss_mib
            .map_or("-".to_string(), |m| format!("{m:.0}"));
        println!("{:<20} {:>10.3} {:>14}", s.stage, s.seconds, m);
    }
}

fn print_report(r: &RunReport) {
    if let Some(e) = &r.evaluation {
        println!("{}", format_table(e));
    }
    let covered = r.refined.covered.iter().filter(|&&c| c).count();
    println!(
        "refined {} chunks in {} forwards ({} tokens), {covered} of {} pixels covered{}",
        r.refined.chunks.len(),
        r.refined.forwards,
        r.refined.total_tokens,
        r.refined.dims.pixels(),
        if r.refined.unrefined {
            " (UNREFINED: no DLT point)"
        } else if r.refined.no_chunk_fallback {
            " (no chunk accepted: aligned feed-forward points)"
        } else {
            ""
        }
    );
    print_stages(&r.stages);
    println!("outputs in {}:", r.out_dir.display());
    for f in r.export.files.iter().map(String::as_str).chain([
        run_output::REFINED_SAFETENSORS,
        run_output::CONFIG_JSON,
        run_output::META_JSON,
    ]) {
        println!("  {}", r.out_dir.join(f).display());
    }
    if r.evaluation.is_some() {
        println!(
            "  {}",
            r.out_dir.join(run_output::EVALUATION_JSON).display()
        );
        println!(
            "  {}/view_*.png (image | feed-forward error | SfM points' error | refined error)",
            r.out_dir.join(run_output::ERROR_MAP_DIR).display()
        );
    }
}

fn run_run(args: RunArgs) -> Result<()> {
    configure_threads(args.common.device.threads)?;
    let mut opts = run_options(
        &args.common,
        args.seed.unwrap_or(ggpt_scene::driver::DEFAULT_SEED),
        args.seed,
    )?;
    opts.refine.cancel = ggpt_cli::signals::stop_token()?;
    let mut log = StageLog::new();
    log.start("load model");
    let model_args = args.model.normalized();
    let spec = resolve_model(
        model_args.require_weights()?,
        model_args.model_config.as_deref(),
        model_args.preset_name(),
    )?;
    let weights = spec.weights.clone();
    let mut refiner = Refiner::load(spec, &args.common.device.device.to_string(), 0)
        .with_context(|| format!("loading weights {}", weights.display()))?;
    log.start("load scene");
    let ff_read = FfReadOptions {
        branch: match args.ff_branch {
            FfBranchArg::Depth => VggtBranch::Depth,
            FfBranchArg::Points => VggtBranch::Points,
        },
        ..FfReadOptions::default()
    };
    let originals = args
        .images
        .as_deref()
        .map(|d| {
            original_images(d, None)
                .with_context(|| format!("reading the images of {}", d.display()))
        })
        .transpose()?;
    let (mut scene, source) = match (&args.scene, &args.ff, &args.matches) {
        (Some(dir), _, _) => (load_scene(dir)?, dir.clone()),
        (None, Some(ff), Some(m)) => {
            let scene = scene_from_files(ff, m, originals.as_ref(), &ff_read)
                .with_context(|| format!("reading {} and {}", ff.display(), m.display()))?;
            (scene, ff.clone())
        }
        _ => bail!("give --scene DIR, or --ff FILE with --matches PATH"),
    };
    if let (Some(o), Some(dir)) = (originals, &args.images) {
        if o.files.len() != scene.dims.n {
            bail!(
                "{}: {} images, the scene has {} views",
                dir.display(),
                o.files.len(),
                scene.dims.n
            );
        }
        opts.export.image_sizes = Some(o.sizes);
        opts.export.image_files = Some(o.files);
    }
    log.finish();
    info!(
        "scene {} ({} views, {}x{})",
        scene.name, scene.dims.n, scene.dims.w, scene.dims.h
    );
    let mut bars = StageBars::new();
    let run = refiner
        .refine(&mut scene, &opts, &mut log, &mut |p| bars.report(p))
        .with_context(|| format!("refining scene {}", source.display()))?;
    bars.finish();
    // the scene folder, or the files it was assembled from
    let inputs = match &args.scene {
        Some(dir) => serde_json::json!(dir),
        None => serde_json::json!({
            "ff": args.ff,
            "matches": args.matches,
            "images": args.images,
            "ff_branch": format!("{:?}", args.ff_branch).to_lowercase(),
        }),
    };
    let config = refiner.run_config("run", inputs, &opts, &run);
    let report = save_run(
        run,
        &scene,
        &opts,
        &args.out,
        &config,
        refiner.run_meta(&opts),
        &mut log,
    )
    .with_context(|| format!("writing the outputs of scene {}", source.display()))?;
    print_report(&report);
    Ok(())
}

fn load_scene(dir: &Path) -> Result<ggpt_core::Scene> {
    if !dir.is_dir() {
        bail!("scene directory not found: {}", dir.display());
    }
    ggpt_core::io::read_scene(dir).with_context(|| format!("reading scene {}", dir.display()))
}

fn run_demo_cmd(args: DemoArgs) -> Result<()> {
    configure_threads(args.common.device.threads)?;
    let model = args.model.normalized();
    let opts = DemoOptions {
        views: args.views,
        seed: args.seed,
        kind: ggpt_synth::SceneKind::parse(args.kind.name())?,
        regime: ggpt_synth::Regime::parse(args.regime.name())?,
        width: args.width,
        height: args.height,
        out: args.out.clone(),
        weights: model.weights.clone(),
        model_config: model.model_config.clone(),
        preset: model.preset_name().map(String::from),
        device: args.common.device.device.to_string(),
        run: run_options(&args.common, args.seed, None)?,
    };
    let mut log = StageLog::new();
    let mut bars = StageBars::new();
    let report = run_demo(&opts, &mut log, &mut |p| bars.report(p))?;
    bars.finish();
    println!(
        "GGPT demo: synthetic {} scene ({} regime), {} views at {}x{}, model {}",
        args.kind.name(),
        args.regime.name(),
        args.views,
        args.width,
        args.height,
        if report.shipped {
            "shipped (embedded)".to_string()
        } else {
            report.weights.display().to_string()
        }
    );
    print_report(&report.run);
    let weights = if report.shipped {
        ggpt_model::model_dir::SHIPPED.to_string()
    } else {
        report.weights.display().to_string()
    };
    println!(
        "  {} (the generated scene; rerun: ggpt-infer run --scene {} --weights {weights} --out DIR)",
        report.scene_dir.display(),
        report.scene_dir.display(),
    );
    Ok(())
}

fn main() -> Result<()> {
    ggpt_model::device::tune_allocator();
    let cli = Cli::parse();
    ggpt_cli::init_logging(match &cli.command {
        Command::Run(a) => a.common.progress.bars(),
        Command::Demo(a) => a.common.progress.bars(),
        Command::Chunk(_) => true,
    });
    match cli.command {
        Command::Chunk(args) => run_chunk(args),
        Command::Run(args) => run_run(args),
        Command::Demo(args) => run_demo_cmd(args),
    }
}

fn run_chunk(args: ChunkArgs) -> Result<()> {
    configure_threads(args.device.threads)?;
    let model_args = args.model.normalized();
    let cfg = match (&model_args.model_config, model_args.preset_name()) {
        (Some(path), _) => GgptConfig::from_json_file(path)?,
        (None, Some(name)) => GgptConfig::preset(name)?,
        (None, None) => bail!("give --model-config FILE or --preset released|small|tiny"),
    };
    let weights = model_args.require_weights()?;
    let device = device_from_name(&args.device.device.to_string())?;
    let t0 = Instant::now();
    let model = load_checkpoint(Ggpt::new(&cfg, &device), weights)
        .with_context(|| format!("loading weights {}", weights.display()))?;
    info!(
        "loaded {} in {:.2} s",
        weights.display(),
        t0.elapsed().as_secs_f64()
    );
    let chunks = read_chunk_inputs(&args.input)
        .with_context(|| format!("reading {}", args.input.display()))?;
    info!("{} chunk(s) from {}", chunks.len(), args.input.display());
    let mut outputs = Vec::with_capacity(chunks.len());
    let groups: Vec<&[ggpt_model::plan::ChunkInput]> = if args.batched {
        vec![&chunks[..]]
    } else {
        chunks.chunks(1).collect()
    };
    let mut first = 0;
    for group in groups {
        let t = Instant::now();
        let batch = prepare_chunks(&cfg, group, &device)
            .with_context(|| format!("planning chunk {first}"))?;
        let t_plan = t.elapsed().as_secs_f64();
        let out = model.forward(&batch).to_chunks(&batch)?;
        let total = t.elapsed().as_secs_f64();
        let tokens: usize = batch.num_tokens;
        eprintln!(
            "chunk {first}{}: {tokens} tokens, plan {t_plan:.3} s, total {total:.3} s",
            if group.len() > 1 {
                format!("..{}", first + group.len() - 1)
            } else {
                String::new()
            }
        );
        first += group.len();
        outputs.extend(out);
    }
    let bytes = chunk_outputs_to_bytes(&outputs)?;
    ggpt_core::io::atomic::write_bytes_atomic(&args.output, &bytes)
        .with_context(|| format!("writing {}", args.output.display()))?;
    info!("wrote {}", args.output.display());
    Ok(())
}
