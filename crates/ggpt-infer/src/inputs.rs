//! The inputs of `ggpt-infer run` given as files (`--ff FILE --matches PATH [--images DIR]`)
//! instead of a scene folder: a feed-forward prediction in any layout of
//! `ggpt_core::io::feedforward` (VGGT's `predictions.npz`, MapAnything, Pi3, `ff.npz`, the
//! official `ff_outputs.bin`), dense matches (a folder of `<matcher>.safetensors`, one such
//! file, the raw-matcher layout of `docs/sfm.md`, or a scene folder's), and the original images.

use std::path::{Path, PathBuf};

use ggpt_core::io::feedforward::FfReadOptions;
use ggpt_core::io::infer_folder::{image_sizes, list_images, read_images};
use ggpt_core::{Dims, MatchSet, Scene};
use ggpt_sfm::input::{read_ff_with, read_matches};

use crate::{InferError, Result};

/// The original images of a run (`--images DIR`): the files in name order (one per view), and
/// their sizes `(H, W)`.
#[derive(Debug, Clone, PartialEq)]
pub struct OriginalImages {
    /// The image files.
    pub files: Vec<PathBuf>,
    /// `(H, W)` of each, from its header.
    pub sizes: Vec<(usize, usize)>,
}

/// The images of `dir` (`.jpg`, `.jpeg`, `.png`, name order); `n` of them when given.
pub fn original_images(dir: &Path, n: Option<usize>) -> Result<OriginalImages> {
    let files = list_images(dir, n)?;
    let sizes = image_sizes(&files)?;
    Ok(OriginalImages { files, sizes })
}

/// The dense matches at `path` for a scene of `dims`, as `MatchSet`s (ff pixels, `[t, s]`):
/// any layout of [`ggpt_sfm::input::read_matches`] (a matches folder, one file, a scene folder).
pub fn read_match_sets(path: &Path, dims: Dims) -> Result<Vec<MatchSet>> {
    let m = read_matches(path, dims)?;
    let mut rank = m.rank_scores;
    Ok(m.names
        .into_iter()
        .zip(m.sets)
        .map(|(name, c)| MatchSet {
            matcher: name,
            pred_matches: c.matches,
            pred_scores: c.scores,
            pred_cycle_error: Some(c.cycle),
            rank_scores: rank.take(),
        })
        .collect())
}

/// The scene of `--ff FILE --matches PATH [--images DIR]`: named after the feed-forward file
/// (its stem), images from the prediction, else decoded from `images` and resized to the ff
/// resolution.
pub fn scene_from_files(
    ff: &Path,
    matches: &Path,
    images: Option<&OriginalImages>,
    opts: &FfReadOptions,
) -> Result<Scene> {
    let input = match read_ff_with(ff, opts) {
        Ok(i) => i,
        // a prediction without images: decode the originals instead
        Err(ggpt_sfm::SfmError::Format { key, .. }) if key == "images" && images.is_some() => {
            let r = ggpt_core::io::feedforward::read_feed_forward_file(ff, opts)?;
            let files = images.map(|i| i.files.as_slice()).unwrap_or_default();
            if files.len() != r.dims.n {
                return Err(InferError::Invalid(format!(
                    "{} images for the {} views of {}",
                    files.len(),
                    r.dims.n,
                    ff.display()
                )));
            }
            ggpt_sfm::input::FfInput {
                name: ff
                    .file_stem()
                    .map_or_else(|| "scene".into(), |s| s.to_string_lossy().into_owned()),
                dims: r.dims,
                images: read_images(files, r.dims)?,
                ff: r.ff,
                image_names: Vec::new(),
            }
        }
        Err(e) => return Err(e.into()),
    };
    let sets = read_match_sets(matches, input.dims)?;
    let scene = Scene {
        name: input.name,
        dims: input.dims,
        images: input.images,
        gt: None,
        ff: Some(input.ff),
        sfm: None,
        matches: sets,
    };
    scene.validate()?;
    Ok(scene)
}
