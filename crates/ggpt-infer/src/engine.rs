//! The library entry point of whole-scene refinement, shared by `ggpt-infer run`, `ggpt-infer
//! demo` and the Python package: a loaded model on a device with its own thread count
//! ([`Refiner::load`]), and the refinement of a scene into memory ([`Refiner::refine`]) that the
//! caller may then write with [`crate::pipeline::save_run`].
//!
//! Frames and units: scenes in the feed-forward frame (cameras `cam_from_world`, OpenCV axes, K
//! in ff pixels with the pixel-centre convention); refined points in the SfM frame (scene
//! units).

use burn::tensor::Device;
use ggpt_core::{Progress, Scene};
use ggpt_model::ChunkOutput;
use ggpt_model::device::device_from_name;
use ggpt_model::infer::prepare_chunks;
use ggpt_model::model_dir::{ModelSpec, load_model};
use ggpt_model::plan::ChunkInput;
use ggpt_scene::chunk_settings::{ResolvedChunking, resolve_chunking};

use crate::pipeline::{RefinedRun, RunOptions, refine_run};
use crate::refiner::BurnRefiner;
use crate::rss::StageLog;
use crate::{InferError, Result};

/// A loaded GGPT network ready to refine scenes: the model, its device and the thread pool its
/// CPU kernels run on.
pub struct Refiner {
    spec: ModelSpec,
    device_name: String,
    net: BurnRefiner,
    /// `Some` when a thread count was asked for: every call runs inside this pool (the CPU
    /// backends' rayon work follows the pool of the calling thread). `None`: the caller's pool.
    pool: Option<rayon::ThreadPool>,
}

impl std::fmt::Debug for Refiner {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Refiner")
            .field("weights", &self.spec.weights)
            .field("device", &self.device_name)
            .field("threads", &self.threads())
            .finish()
    }
}

impl Refiner {
    /// Loads `spec` (strictly: every tensor of the checkpoint must match the configuration) on
    /// the device named `device` (`cpu`, `flex`, `ndarray`, `wgpu[:N]`, `cuda[:N]`, see
    /// `ggpt_model::device::device_from_name`). `threads > 0` runs every call of this refiner on
    /// a pool of that many threads (flex / gemm kernels; the ndarray backend's matrix products
    /// read `MATMUL_NUM_THREADS` instead); `0` uses the calling thread's pool.
    pub fn load(spec: ModelSpec, device: &str, threads: usize) -> Result<Self> {
        let pool = match threads {
            0 => None,
            t => Some(
                rayon::ThreadPoolBuilder::new()
                    .num_threads(t)
                    .thread_name(|i| format!("ggpt-cpu-{i}"))
                    .build()
                    .map_err(|e| {
                        InferError::Invalid(format!("cannot create a pool of {t} threads: {e}"))
                    })?,
            ),
        };
        let dev: Device = device_from_name(device)?;
        let model = match &pool {
            Some(p) => p.install(|| load_model(&spec, &dev))?,
            None => load_model(&spec, &dev)?,
        };
        let net = BurnRefiner::new(model, spec.config.clone(), dev)?.with_rss_stages(true);
        Ok(Refiner {
            spec,
            device_name: device.to_string(),
            net,
            pool,
        })
    }

    /// The model that was loaded.
    pub fn spec(&self) -> &ModelSpec {
        &self.spec
    }

    /// The device name given to [`Refiner::load`].
    pub fn device_name(&self) -> &str {
        &self.device_name
    }

    /// Threads of the pool the calls run on.
    pub fn threads(&self) -> usize {
        self.pool.as_ref().map_or_else(
            rayon::current_num_threads,
            rayon::ThreadPool::current_num_threads,
        )
    }

    /// Runs `f` on this refiner's pool (or on the caller's when it has none).
    fn install<R: Send>(pool: Option<&rayon::ThreadPool>, f: impl FnOnce() -> R + Send) -> R {
        match pool {
            Some(p) => p.install(f),
            None => f(),
        }
    }

    /// The chunk-sampler settings for this model: `opts.chunking` (explicit) over the model's
    /// `inference.json` over `opts.refine.chunking`.
    pub fn resolve_chunking(&self, opts: &RunOptions) -> Result<ResolvedChunking> {
        Ok(resolve_chunking(
            &opts.refine.chunking,
            self.spec.chunking_layer(),
            &opts.chunking,
            |f| format!("chunking.{f}"),
        )?)
    }

    /// Refines `scene` in memory (nothing is written): the SfM stage first when the scene has
    /// no SfM result (the SfM result moves from `scene.sfm` into [`RefinedRun::sfm`]), then
    /// pre-alignment, chunks, network and fusion
    /// ([`crate::pipeline::refine_run`]) with the chunk sampler of
    /// [`Refiner::resolve_chunking`]. Deterministic for a given seed (`opts.refine.seed`,
    /// `opts.refine.chunk_seed`). `opts.refine.cancel` stops it between SfM steps, BA
    /// iterations and network forwards (`Cancelled` errors of the stage that saw it).
    pub fn refine(
        &mut self,
        scene: &mut Scene,
        opts: &RunOptions,
        log: &mut StageLog,
        progress: &mut (dyn FnMut(Progress) + Send),
    ) -> Result<RefinedRun> {
        let chunking = self.resolve_chunking(opts)?;
        tracing::info!("chunk sampler: {}", chunking.describe());
        let mut opts = opts.clone();
        opts.refine.chunking = chunking.params.clone();
        let net = &mut self.net;
        let mut run = Self::install(self.pool.as_ref(), || {
            refine_run(scene, net, &opts, log, &mut |p| progress(p))
        })?;
        run.chunking = Some(chunking);
        Ok(run)
    }

    /// The `config.json` of a run of this refiner: `command` (`run`, `demo`, `python`), the
    /// scene it read (`scene`: a path or a name), the model (weights, configuration and its
    /// origin), device and threads, the resolved chunk sampler (`run.chunking`) and every option.
    pub fn run_config(
        &self,
        command: &str,
        scene: serde_json::Value,
        opts: &RunOptions,
        run: &RefinedRun,
    ) -> serde_json::Value {
        // the options as they ran: the chunk sampler resolved for this model
        let mut refine = opts.refine.clone();
        if let Some(c) = &run.chunking {
            refine.chunking = c.params.clone();
        }
        serde_json::json!({
            "command": command,
            "scene": scene,
            "weights": self.spec.weights,
            "model_config_origin": self.spec.origin,
            "model_config": self.spec.config,
            "device": self.device_name,
            "threads": self.threads(),
            "chunking": run.chunking,
            "refine": refine,
            "export": opts.export,
            "sfm_preset": opts.sfm_preset.name(),
            "error_maps": opts.error_maps,
            "error_map_max_cm": opts.error_map_max_cm,
        })
    }

    /// The `meta.json` base of a run (versions, backend, dtype, seed); the writer adds counts,
    /// stage timings and summaries.
    pub fn run_meta(&self, opts: &RunOptions) -> serde_json::Value {
        serde_json::json!({
            "ggpt_infer_version": env!("CARGO_PKG_VERSION"),
            "backend": self.device_name,
            "dtype": "f32",
            "seed": opts.refine.seed,
        })
    }

    /// Runs the network on prepared chunk records (normalised chunk coordinates, `formats.md`
    /// chunk records): one forward for all of `chunks`. Outputs in the same order.
    pub fn forward_chunks(&mut self, chunks: &[ChunkInput]) -> Result<Vec<ChunkOutput>> {
        let net = &mut self.net;
        Self::install(self.pool.as_ref(), || {
            let batch = prepare_chunks(net.config(), chunks, net.device())?;
            Ok(net.model().forward(&batch).to_chunks(&batch)?)
        })
    }
}
