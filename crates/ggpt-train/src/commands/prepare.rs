//! `ggpt-train prepare`: a chunk set from synthetic scenes and/or official directories.

use anyhow::{Context, Result, bail};
use ggpt_cli::{Bar, ChunkingArgs};
use ggpt_scene::chunk_settings::resolve_chunking;
use ggpt_scene::chunker::ChunkParams;
use ggpt_train::chunkset::{ChunkSetWriter, SceneEntry, Split};
use ggpt_train::prepare::{PrepareParams, PreparedScene, prepare_scene};
use ggpt_train::scene_source::{SceneSource, official_scene, synthetic_scene};

use crate::cli::PrepareArgs;

/// The sampler of `prepare`: the flags over the official defaults.
fn chunk_params(c: &ChunkingArgs) -> Result<ChunkParams> {
    Ok(resolve_chunking(
        &ChunkParams::default(),
        None,
        &c.settings(),
        ChunkingArgs::flag,
    )?
    .params)
}

/// Runs `prepare`.
pub fn run(a: &PrepareArgs) -> Result<()> {
    let params = PrepareParams {
        chunks_per_scene: a.chunks_per_scene,
        chunking: chunk_params(&a.chunking)?,
        seed: a.seed,
        ..PrepareParams::default()
    };
    let provenance = serde_json::json!({
        "tool": format!("ggpt-train {}", env!("CARGO_PKG_VERSION")),
        "params": params,
        "synthetic": {"train": a.synthetic_train, "val": a.synthetic_val, "first_seed": a.synth.first_seed, "views": a.synth.views,
                      "width": a.synth.width, "height": a.synth.height, "kinds": a.synth.kinds, "regime": a.synth.regime},
        "official": a.official,
    });
    let mut w = ChunkSetWriter::new(&a.out, a.shard_chunks, provenance)?;
    let n_syn = a.synthetic_train + a.synthetic_val;
    let n_val_off = ((a.official.len() as f64) * a.val_fraction).round() as usize;
    let total = n_syn + a.official.len();
    if total == 0 {
        bail!("nothing to prepare: give --synthetic-train/--synthetic-val and/or --official DIRS");
    }
    let bar = Bar::new("prepare", total as u64);
    let mut counts = [0usize; 2];
    for i in 0..n_syn {
        let spec = a.synth.spec(i)?;
        let split = if i < a.synthetic_train {
            Split::Train
        } else {
            Split::Val
        };
        let (scene, sfm) =
            synthetic_scene(&spec).with_context(|| format!("synthetic scene {spec:?}"))?;
        let prep = prepare_scene(&scene, &sfm, &params)
            .with_context(|| format!("preparing {}", scene.name))?;
        let source = SceneSource::Synthetic(spec);
        add_scene(&mut w, &scene, split, prep, source, &mut counts)?;
        bar.inc(1);
    }
    for (j, dir) in a.official.iter().enumerate() {
        let split = if j + n_val_off >= a.official.len() {
            Split::Val
        } else {
            Split::Train
        };
        let (scene, sfm) =
            official_scene(dir).with_context(|| format!("reading {}", dir.display()))?;
        let prep = prepare_scene(&scene, &sfm, &params)
            .with_context(|| format!("preparing {}", dir.display()))?;
        let source = SceneSource::Official(dir.clone());
        add_scene(&mut w, &scene, split, prep, source, &mut counts)?;
        bar.inc(1);
    }
    bar.finish();
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

fn add_scene(
    w: &mut ChunkSetWriter,
    scene: &ggpt_core::Scene,
    split: Split,
    prep: PreparedScene,
    source: SceneSource,
    counts: &mut [usize; 2],
) -> Result<()> {
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
