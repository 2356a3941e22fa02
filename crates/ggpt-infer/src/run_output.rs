//! The run folder (`pipeline.md` §9): [`RunOutput`] is the one writer of a run's output folder,
//! and these are its file names. Every file of a run goes through it: the export files of
//! `ggpt_scene::export` (PLY, npy / npz, COLMAP), `config.json`, `refined.safetensors`,
//! `evaluation.json`, `error_maps/view_*.png`, and `meta.json`, written once, at the end.

use std::path::{Path, PathBuf};

use ggpt_core::io::atomic::write_json_atomic;
use ggpt_core::io::st::StWriter;
use ggpt_core::{Scene, SfmResult};
use ggpt_scene::driver::RefinedScene;
use ggpt_scene::export::{ExportOptions, ExportSummary, export_scene};
use image::RgbImage;

use crate::{InferError, Result};

/// Refined arrays in safetensors (`refined.safetensors`, [`RunOutput::write_refined`]).
pub const REFINED_SAFETENSORS: &str = "refined.safetensors";
/// Evaluation report (`evaluation.json`, [`RunOutput::write_evaluation`]).
pub const EVALUATION_JSON: &str = "evaluation.json";
/// Folder of the per-view error maps (`error_maps/view_{i:03}.png`,
/// [`RunOutput::write_error_maps`]).
pub const ERROR_MAP_DIR: &str = "error_maps";
/// Run configuration (`config.json`, [`RunOutput::write_config`]).
pub const CONFIG_JSON: &str = "config.json";
/// Run metadata (`meta.json`, written once by [`RunOutput::finish`]).
pub const META_JSON: &str = "meta.json";

/// Serialises `refined.safetensors`: `points` f32 `[N,h,w,3]` (SfM frame), `confidence` f32
/// `[N,h,w]`, `covered` bool `[N,h,w]`, `aligned_ff_points` f32 `[N,h,w,3]` (the pre-aligned
/// feed-forward points, SfM frame), `cam_from_world` f64 `[N,3,4]`, `K` f64 `[N,3,3]` (SfM
/// cameras, ff pixels, pixel-centre convention); metadata `frame = sfm`. `path` names errors.
fn refined_safetensors_bytes(
    path: &Path,
    refined: &RefinedScene,
    sfm: &SfmResult,
) -> Result<Vec<u8>> {
    let d = refined.dims;
    let mut w = StWriter::new();
    w.f32("points", &[d.n, d.h, d.w, 3], &refined.points);
    w.f32("confidence", &[d.n, d.h, d.w], &refined.conf);
    w.bool("covered", &[d.n, d.h, d.w], &refined.covered);
    w.f32(
        "aligned_ff_points",
        &[d.n, d.h, d.w, 3],
        &refined.aligned_ff,
    );
    w.extrinsics("cam_from_world", &sfm.cameras.cam_from_world);
    w.intrinsics("K", &sfm.cameras.intrinsics);
    let meta = [("frame", "sfm"), ("format", "ggpt-rs refined point map")]
        .map(|(k, v)| (k.to_string(), v.to_string()));
    Ok(w.finish(path, Some(meta.into_iter().collect()))?)
}

/// The one writer of a run's output folder (`pipeline.md` §9): it owns the directory and its
/// file names, writes every file of a run atomically — the export files ([`RunOutput::export`]),
/// `config.json`, `refined.safetensors`, `evaluation.json`, the error maps — and `meta.json`
/// exactly once, at the end ([`RunOutput::finish`]). Values computed elsewhere (the evaluation
/// report, the rendered error maps) are handed over ready to serialise.
#[derive(Debug)]
pub struct RunOutput {
    dir: PathBuf,
    files: Vec<String>,
}

impl RunOutput {
    /// Creates `dir` (and its parents) if needed; a failure is [`InferError::Write`] naming it.
    pub fn create(dir: &Path) -> Result<Self> {
        std::fs::create_dir_all(dir).map_err(|e| InferError::Write {
            path: dir.to_path_buf(),
            message: e.to_string(),
        })?;
        Ok(RunOutput {
            dir: dir.to_path_buf(),
            files: Vec::new(),
        })
    }

    /// The output folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The result files written so far, relative to the folder, in write order (the export
    /// files, `refined.safetensors`, `evaluation.json`, `error_maps/view_*.png`; not
    /// `config.json` / `meta.json`): the `files` list of `meta.json`.
    pub fn files(&self) -> &[String] {
        &self.files
    }

    /// Writes the export files of §9 (PLY, npy / npz, COLMAP, as `opts` selects,
    /// [`ggpt_scene::export::export_scene`]). `scene` provides the images and the unaligned
    /// feed-forward points, `sfm` the cameras and DLT points, `refined` the fused result.
    pub fn export(
        &mut self,
        scene: &Scene,
        sfm: &SfmResult,
        refined: &RefinedScene,
        opts: &ExportOptions,
    ) -> Result<ExportSummary> {
        let summary = export_scene(&self.dir, scene, sfm, refined, opts)?;
        self.files.extend(summary.files.iter().cloned());
        Ok(summary)
    }

    /// Writes the run configuration as `config.json`.
    pub fn write_config(&mut self, config: &serde_json::Value) -> Result<()> {
        write_json_atomic(&self.dir.join(CONFIG_JSON), config)?;
        Ok(())
    }

    /// Writes `refined.safetensors` (the refined arrays and the SfM cameras).
    pub fn write_refined(&mut self, refined: &RefinedScene, sfm: &SfmResult) -> Result<()> {
        let path = self.dir.join(REFINED_SAFETENSORS);
        let bytes = refined_safetensors_bytes(&path, refined, sfm)?;
        ggpt_core::io::atomic::write_bytes_atomic(&path, &bytes)?;
        self.files.push(REFINED_SAFETENSORS.into());
        Ok(())
    }

    /// Writes the evaluation report as `evaluation.json`.
    pub fn write_evaluation(&mut self, evaluation: &impl serde::Serialize) -> Result<()> {
        write_json_atomic(&self.dir.join(EVALUATION_JSON), evaluation)?;
        self.files.push(EVALUATION_JSON.into());
        Ok(())
    }

    /// Writes one PNG per view, `error_maps/view_{i:03}.png` (`maps[i]` = view `i`, rendered by
    /// [`ggpt_eval::error_maps::render_error_maps`]); returns the paths written.
    pub fn write_error_maps(&mut self, maps: &[RgbImage]) -> Result<Vec<PathBuf>> {
        let dir = self.dir.join(ERROR_MAP_DIR);
        let mut paths = Vec::with_capacity(maps.len());
        for (v, m) in maps.iter().enumerate() {
            let path = dir.join(format!("view_{v:03}.png"));
            ggpt_core::io::png::write_rgb8(
                &path,
                m.width() as usize,
                m.height() as usize,
                m.as_raw(),
            )?;
            paths.push(path);
        }
        self.files.push(format!("{ERROR_MAP_DIR}/view_*.png"));
        Ok(paths)
    }

    /// Writes `meta.json` (once: the run is complete) and returns its path.
    pub fn finish(self, meta: &serde_json::Value) -> Result<PathBuf> {
        let path = self.dir.join(META_JSON);
        write_json_atomic(&path, meta)?;
        Ok(path)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writes_the_run_files_and_meta_last() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("run");
        let mut out = RunOutput::create(&root).unwrap();
        assert_eq!(out.dir(), root);
        out.write_config(&serde_json::json!({"seed": 1})).unwrap();
        out.write_evaluation(&serde_json::json!({"auc": 0.5}))
            .unwrap();
        let map = RgbImage::from_raw(2, 1, vec![255, 0, 0, 0, 0, 255]).unwrap();
        let paths = out.write_error_maps(&[map.clone(), map]).unwrap();
        assert_eq!(paths[1], root.join(ERROR_MAP_DIR).join("view_001.png"));
        let png = image::open(&paths[0]).unwrap().to_rgb8();
        assert_eq!(png.into_raw(), vec![255, 0, 0, 0, 0, 255]);
        // config.json and meta.json are not result files
        assert_eq!(out.files(), [EVALUATION_JSON, "error_maps/view_*.png"]);
        assert!(root.join(CONFIG_JSON).is_file() && !root.join(META_JSON).exists());
        let meta = out.finish(&serde_json::json!({"seed": 42})).unwrap();
        let meta: serde_json::Value =
            serde_json::from_slice(&std::fs::read(meta).unwrap()).unwrap();
        assert_eq!(meta["seed"], 42);
    }

    #[test]
    fn an_unwritable_folder_names_itself() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("file");
        std::fs::write(&file, b"x").unwrap();
        let e = RunOutput::create(&file.join("run")).unwrap_err();
        assert!(matches!(e, InferError::Write { ref path, .. } if path.ends_with("file/run")));
    }
}
