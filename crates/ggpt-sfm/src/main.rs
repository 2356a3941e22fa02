//! `ggpt-sfm`: the lightweight SfM stage of GGPT as a command-line tool (see `docs/sfm.md`).
//!
//! `ggpt-sfm run --ff FILE --matches FILE --sfm-preset benchmark --out DIR` writes
//! `DIR/sfm_dlt_outputs.safetensors`, the COLMAP model `DIR/sparse/0/` (BA cameras, images and
//! BA points; `--colmap-points dlt|none` for the DLT points or none) and `DIR/summary.json`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand, ValueEnum};
use ggpt_cli::{ProgressArgs, SfmPresetArg, StageBars};
use ggpt_core::Cameras;
use ggpt_core::io::st::StFile;
use ggpt_sfm::ba::{BaOptions, CameraModel, LossFunction};
use ggpt_sfm::input::{cameras_from_flat, read_inputs};
use ggpt_sfm::masks::Preset;
use ggpt_sfm::output::{ColmapExport, ColmapPoints, write_outputs};
use ggpt_sfm::pipeline::{SfmConfig, run_sfm_correspondences_with_progress};

#[derive(Parser, Debug)]
#[command(
    name = "ggpt-sfm",
    version,
    about = "GGPT lightweight SfM: dense-match filtering, bundle adjustment, DLT triangulation"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run the SfM stage on feed-forward outputs and dense matches.
    Run(RunArgs),
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum BaSolverArg {
    /// The official pycolmap call: free gauge, no tolerances, 100 LM iterations (Ceres' path;
    /// reproduces the official cameras and costs).
    Official,
    /// The project solver of sfm.md §7.2: view 0 and one component of t_1 fixed, stops at a
    /// relative cost decrease below 1e-6 (fewer iterations; may end in a neighbouring minimum of
    /// the Cauchy cost).
    Project,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum ColmapPointsArg {
    /// The BA tracks: points refined by the bundle adjustment with their BA observations
    /// (observations reprojecting beyond --max-reproj-error px are left out, tracks need two).
    Ba,
    /// Every kept DLT track with its full track (millions of points; ~1 GB images.bin for 16
    /// views at 518x392).
    Dlt,
    /// Cameras and images only, no 3D point.
    None,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum CameraModelArg {
    /// fx, fy refined separately.
    Pinhole,
    /// One focal length.
    SimplePinhole,
}

#[derive(clap::Args, Debug)]
struct RunArgs {
    /// Feed-forward outputs: official `ff_outputs.bin`, a scene directory, or a safetensors file
    /// with `ff/images_ff`, `ff/extrinsics`, `ff/intrinsics`, `ff/points`, `ff/points_conf`.
    #[arg(long)]
    ff: PathBuf,
    /// Dense matches: raw-matcher interchange safetensors (`m{i}_warp`/`m{i}_overlap`,
    /// `m{i}_flow`/`m{i}_covisibility`, optional `sp_scores`; keys may be prefixed `match/`),
    /// a `matches/<matcher>.safetensors` file, or a scene directory.
    #[arg(long)]
    matches: PathBuf,
    /// The original images (`.jpg`/`.jpeg`/`.png`, name order, one per view): their file names
    /// name the images of the COLMAP model (default `000000.png`, ...). Cameras stay at the
    /// feed-forward resolution here; `ggpt-infer run --images` writes the splat-ready export.
    #[arg(long, value_name = "DIR")]
    images: Option<PathBuf>,
    /// SfM threshold preset (`docs/sfm.md`): `benchmark` (benchmark_sfm.yaml: BA 0.6 / 2 px,
    /// DLT 0.1 / 4 px, epipolar 4 px, angle 3°, reprojection 4 px, PINHOLE), `demo` (demo.yaml:
    /// BA 0.6 / 2 px, DLT 0.4 / 2 px, epipolar 2 px, angle 5°, reprojection 2 px,
    /// SIMPLE_PINHOLE) or `many-views` (> 50 views: BA 0.8 / 1 px, 512 tracks per view,
    /// DLT 0.4 / 1 px, angle 7°, reprojection 1 px). `--preset` is the old spelling.
    #[arg(long, alias = "preset", value_enum, default_value_t)]
    sfm_preset: SfmPresetArg,
    /// BA tracks per view (`mintrack_per_view`).
    #[arg(long)]
    mintrack_per_view: Option<usize>,
    /// BA correspondences need score > this.
    #[arg(long)]
    ba_score_thresh: Option<f64>,
    /// BA correspondences need cycle error < this (ff pixels).
    #[arg(long)]
    ba_cycle_thresh: Option<f64>,
    /// DLT correspondences need score > this.
    #[arg(long)]
    dlt_score_thresh: Option<f64>,
    /// DLT correspondences need cycle error < this (ff pixels).
    #[arg(long)]
    dlt_cycle_thresh: Option<f64>,
    /// Max epipolar distance (ff pixels).
    #[arg(long)]
    max_epipolar_error: Option<f64>,
    /// Min triangulation angle (degrees).
    #[arg(long)]
    min_tri_angle: Option<f64>,
    /// Max mean reprojection error of a DLT point (ff pixels); also the largest reprojection
    /// error of an observation of a BA point written to the COLMAP model.
    #[arg(long)]
    max_reproj_error: Option<f64>,
    /// BA camera model (default: the preset's).
    #[arg(long, value_enum)]
    camera_model: Option<CameraModelArg>,
    /// One camera per view instead of one shared camera.
    #[arg(long)]
    per_view_camera: bool,
    /// Keep the focal length(s) fixed in the BA.
    #[arg(long)]
    fixed_focal: bool,
    /// Cauchy loss scale of the BA (pixels); 0 = trivial (squared) loss.
    #[arg(long)]
    ba_loss_scale: Option<f64>,
    /// Max BA iterations (default 100).
    #[arg(long)]
    ba_max_iterations: Option<usize>,
    /// BA solver settings.
    #[arg(long, value_enum, default_value = "official")]
    ba_solver: BaSolverArg,
    /// Older official BA initialisation (the version that produced sfm_small's `ba/*`): initial
    /// focal length(s) + 0.5 px.
    #[arg(long)]
    ba_legacy_focal_offset: bool,
    /// Skip the BA and use these cameras (safetensors with `extrinsics` [N,3,4] and
    /// `intrinsics` [N,3,3], or `ba/out_extrinsics` / `ba/out_intrinsics`).
    #[arg(long)]
    cameras: Option<PathBuf>,
    /// Drop scatter observations that round outside the image (default: clamp to the border).
    #[arg(long)]
    drop_outside: bool,
    /// Reject DLT points behind an observing camera (off by default, official parity).
    #[arg(long)]
    cheirality: bool,
    /// Output directory: `sfm_dlt_outputs.safetensors`, the COLMAP model `sparse/0/`
    /// (bundle-adjusted cameras and images, points chosen by --colmap-points) and `summary.json`.
    #[arg(long)]
    out: PathBuf,
    /// 3D points of the COLMAP model `sparse/0/points3D.bin` (with their POINTS2D in
    /// images.bin).
    #[arg(long, value_enum, default_value = "ba")]
    colmap_points: ColmapPointsArg,
    /// Seed of every random choice (the stage is deterministic).
    #[arg(long, default_value_t = 42)]
    seed: u64,
    #[command(flatten)]
    progress: ProgressArgs,
}

fn read_cameras(path: &Path, n: usize) -> Result<Cameras> {
    let f = StFile::open(path)?;
    let prefix = if f.has("extrinsics") { "" } else { "ba/out_" };
    let ek = format!("{prefix}extrinsics");
    let ik = format!("{prefix}intrinsics");
    let e = f.f32_tensor(&ek)?;
    let rows = match e.shape.as_slice() {
        [m, r, 4] if *m == n && (*r == 3 || *r == 4) => *r,
        s => bail!(
            "{}: [{ek}] shape {s:?} is not [N={n}, 3, 4]",
            path.display()
        ),
    };
    let k = f.f32_tensor(&ik)?;
    f.expect_shape(&ik, &k, &[n, 3, 3])?;
    Ok(cameras_from_flat(path, n, &e.data, rows, &k.data)?)
}

fn run(args: RunArgs) -> Result<()> {
    let preset = Preset::parse(args.sfm_preset.name())?;
    let mut cfg = SfmConfig::preset(preset);
    let t = &mut cfg.thresholds;
    if let Some(v) = args.mintrack_per_view {
        t.mintrack_per_view = v;
    }
    if let Some(v) = args.ba_score_thresh {
        t.ba_score = v;
    }
    if let Some(v) = args.ba_cycle_thresh {
        t.ba_cycle = v;
    }
    if let Some(v) = args.dlt_score_thresh {
        t.dlt_score = v;
    }
    if let Some(v) = args.dlt_cycle_thresh {
        t.dlt_cycle = v;
    }
    if let Some(v) = args.max_epipolar_error {
        t.max_epipolar_error = v;
    }
    if let Some(v) = args.min_tri_angle {
        t.min_tri_angle_deg = v;
    }
    if let Some(v) = args.max_reproj_error {
        t.max_reproj_error = v;
    }
    if let Some(m) = args.camera_model {
        cfg.camera_model = match m {
            CameraModelArg::Pinhole => CameraModel::Pinhole,
            CameraModelArg::SimplePinhole => CameraModel::SimplePinhole,
        };
    }
    cfg.shared_camera = !args.per_view_camera;
    cfg.refine_focal = !args.fixed_focal;
    if let Some(s) = args.ba_loss_scale {
        cfg.ba_loss = if s > 0.0 {
            LossFunction::Cauchy { scale: s }
        } else {
            LossFunction::Trivial
        };
    }
    cfg.ba_options = match args.ba_solver {
        BaSolverArg::Official => BaOptions::official(),
        BaSolverArg::Project => BaOptions::default(),
    };
    cfg.legacy_focal_offset = args.ba_legacy_focal_offset;
    if let Some(it) = args.ba_max_iterations {
        cfg.ba_options.max_iterations = it;
    }
    cfg.scatter.drop_outside = args.drop_outside;
    cfg.cheirality = args.cheirality;
    cfg.seed = args.seed;

    let t0 = Instant::now();
    let reading = ggpt_cli::Bar::new("read", 1);
    reading.set_message("feed-forward outputs and matches");
    let (mut ff, m) = read_inputs(&args.ff, &args.matches).with_context(|| {
        format!(
            "reading --ff {} / --matches {}",
            args.ff.display(),
            args.matches.display()
        )
    })?;
    if let Some(dir) = &args.images {
        let files = ggpt_core::io::infer_folder::list_images(dir, Some(ff.dims.n))
            .with_context(|| format!("reading --images {}", dir.display()))?;
        ff.image_names = files
            .iter()
            .map(|f| f.file_name().map(|n| n.to_string_lossy().into_owned()))
            .collect::<Option<Vec<_>>>()
            .with_context(|| format!("--images {}: a file without a name", dir.display()))?;
    }
    reading.finish();
    tracing::info!(views = ff.dims.n, h = ff.dims.h, w = ff.dims.w, matchers = ?m.names, seconds = t0.elapsed().as_secs_f64(), "inputs read");
    let fixed = match &args.cameras {
        Some(p) => Some(
            read_cameras(p, ff.dims.n)
                .with_context(|| format!("reading --cameras {}", p.display()))?,
        ),
        None => None,
    };
    let mut bars = StageBars::new();
    let out = run_sfm_correspondences_with_progress(
        &ff.ff,
        &ff.images,
        &m.sets,
        m.rank_scores.as_deref(),
        &cfg,
        fixed.as_ref(),
        &mut |p| bars.report(p),
    )
    .context("running the SfM stage")?;
    bars.finish();
    let export = ColmapExport {
        points: match args.colmap_points {
            ColmapPointsArg::Ba => ColmapPoints::Ba,
            ColmapPointsArg::Dlt => ColmapPoints::Dlt,
            ColmapPointsArg::None => ColmapPoints::None,
        },
        max_reproj_error: cfg.thresholds.max_reproj_error,
        model: cfg.camera_model,
        shared: cfg.shared_camera,
    };
    let cs = write_outputs(&args.out, &out, &ff.images, &ff.image_names, &export)
        .with_context(|| format!("writing outputs to {}", args.out.display()))?;
    let s = &out.summary;
    println!(
        "ggpt-sfm: {} views {}x{}, {} BA tracks, BA cost {:.6} -> {:.6} ({}), DLT tracks {:?}, {} pixels with a DLT point, COLMAP {} points ({} observations); wrote {}",
        s.views,
        s.width,
        s.height,
        s.tracks_selected,
        s.ba.initial_cost,
        s.ba.final_cost,
        if s.ba.success {
            "ok"
        } else {
            "failed: feed-forward cameras kept"
        },
        s.dlt_tracks,
        s.points_kept,
        cs.points3d,
        cs.observations,
        args.out.display()
    );
    if !out.result.points_success {
        bail!(
            "no DLT point survived the filters (points_success = false); outputs were written to {}",
            args.out.display()
        );
    }
    Ok(())
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    let Command::Run(a) = &cli.command;
    ggpt_cli::init_logging(a.progress.bars());
    match cli.command {
        Command::Run(args) => run(args),
    }
}
