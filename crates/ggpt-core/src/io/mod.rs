//! File formats (`formats.md`). Every reader rejects malformed input with a [`crate::CoreError`]
//! naming the file, the key and the problem; every writer is atomic (temp file + rename).

pub mod arrays;
pub mod atomic;
pub mod colmap;
pub mod feedforward;
pub mod ggpt_eval;
pub mod infer_folder;
pub mod matches;
pub mod npy;
pub mod official;
pub mod ply;
pub mod png;
pub mod scene_dir;
pub mod st;
pub mod torch_zip;

use std::path::Path;

use crate::{CoreError, Result, Scene};

/// Layout of a directory accepted by [`read_scene`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Layout {
    /// `scene.json` + `scene.safetensors` ([`scene_dir`]).
    Project,
    /// Official `gt.bin` / `ff_outputs.bin` / `sfm_dlt_outputs.bin` (`formats.md` §3).
    Official,
    /// `images/` + `ff.npz` + `matches/` (+ `sfm.npz`) (`formats.md` §5.1).
    InferFolder,
}

/// Detects the layout of `dir` (error naming the directory when none matches). A directory with
/// `ff.npz`, `sfm.npz` or `matches/` is a §5.1 folder (which may mix in official `.bin` files);
/// otherwise `gt.bin` / `ff_outputs.bin` make it an official directory.
pub fn detect_layout(dir: &Path) -> Result<Layout> {
    if dir.join(scene_dir::MANIFEST).is_file() {
        return Ok(Layout::Project);
    }
    if dir.join("ff.npz").is_file() || dir.join("sfm.npz").is_file() || dir.join("matches").is_dir()
    {
        return Ok(Layout::InferFolder);
    }
    if dir.join("ff_outputs.bin").is_file() || dir.join("gt.bin").is_file() {
        return Ok(Layout::Official);
    }
    Err(CoreError::format(
        dir,
        "",
        "not a scene directory: expected scene.json, ff_outputs.bin / gt.bin (official layout) or ff.npz (formats.md §5.1)",
    ))
}

/// Reads a scene directory of any accepted layout, validates it fully and returns the scene.
/// Errors name the file, the key and the problem.
pub fn read_scene(dir: &Path) -> Result<Scene> {
    let scene = match detect_layout(dir)? {
        Layout::Project => scene_dir::read_project_scene(dir)?,
        Layout::Official => official::read_official_dir(dir)?,
        Layout::InferFolder => infer_folder::read_infer_folder(dir)?,
    };
    scene.validate()?;
    Ok(scene)
}
