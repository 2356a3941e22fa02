//! Where a chunk-set scene came from ([`SceneSource`]), recorded in the manifest so that
//! `ggpt-train eval` can rebuild the whole scene: a synthetic scene is regenerated from its
//! spec, an official one read again from its directory.

use std::path::{Path, PathBuf};

use ggpt_core::{Scene, SfmResult};
use serde::{Deserialize, Serialize};

use crate::error::{Result, TrainError};

/// Prefix of a synthetic source in the manifest's old string form (`synthetic:<json spec>`).
const LEGACY_SYNTHETIC: &str = "synthetic:";
/// Prefix of an official source in the manifest's old string form (`official:<dir>`).
const LEGACY_OFFICIAL: &str = "official:";

/// The origin of a chunk-set scene.
///
/// Written as `{"synthetic": {spec}}`, `{"official": "dir"}` or `{"other": "text"}`; manifests
/// of earlier versions hold a string (`synthetic:<json>`, `official:<dir>`, anything else), which
/// is still read.
#[derive(Debug, Clone, PartialEq)]
pub enum SceneSource {
    /// A `ggpt-synth` scene, regenerated from its spec.
    Synthetic(SynthSpec),
    /// An official per-sequence directory (`gt.bin`, `ff_outputs.bin`, `sfm_dlt_outputs.bin`).
    Official(PathBuf),
    /// Recorded by hand or by a test: cannot be rebuilt.
    Other(String),
}

impl SceneSource {
    /// Rebuilds the scene and its SfM result (`name` is the scene's name, for messages).
    pub fn load(&self, name: &str) -> Result<(Scene, SfmResult)> {
        match self {
            SceneSource::Synthetic(spec) => synthetic_scene(spec),
            SceneSource::Official(dir) => official_scene(dir),
            SceneSource::Other(s) => Err(TrainError::Invalid(format!(
                "scene {name}: source {s:?} cannot be rebuilt (neither synthetic nor official)"
            ))),
        }
    }

    /// Reads the old string form.
    fn from_legacy(s: &str) -> std::result::Result<Self, String> {
        if let Some(js) = s.strip_prefix(LEGACY_SYNTHETIC) {
            let spec = serde_json::from_str(js)
                .map_err(|e| format!("synthetic scene source {js:?}: {e}"))?;
            Ok(SceneSource::Synthetic(spec))
        } else if let Some(dir) = s.strip_prefix(LEGACY_OFFICIAL) {
            Ok(SceneSource::Official(Path::new(dir).to_path_buf()))
        } else {
            Ok(SceneSource::Other(s.to_string()))
        }
    }
}

/// The serialised forms.
#[derive(Serialize, Deserialize)]
#[serde(untagged)]
enum Stored {
    Typed(Typed),
    Legacy(String),
}

#[derive(Serialize, Deserialize)]
#[serde(rename_all = "lowercase", deny_unknown_fields)]
enum Typed {
    Synthetic(SynthSpec),
    Official(PathBuf),
    Other(String),
}

impl Serialize for SceneSource {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        let t = match self {
            SceneSource::Synthetic(spec) => Typed::Synthetic(spec.clone()),
            SceneSource::Official(dir) => Typed::Official(dir.clone()),
            SceneSource::Other(text) => Typed::Other(text.clone()),
        };
        Stored::Typed(t).serialize(s)
    }
}

impl<'de> Deserialize<'de> for SceneSource {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        match Stored::deserialize(d)? {
            Stored::Typed(Typed::Synthetic(spec)) => Ok(SceneSource::Synthetic(spec)),
            Stored::Typed(Typed::Official(dir)) => Ok(SceneSource::Official(dir)),
            Stored::Typed(Typed::Other(text)) => Ok(SceneSource::Other(text)),
            Stored::Legacy(s) => SceneSource::from_legacy(&s).map_err(serde::de::Error::custom),
        }
    }
}

impl From<&str> for SceneSource {
    /// A source that cannot be rebuilt ([`SceneSource::Other`]).
    fn from(s: &str) -> Self {
        SceneSource::Other(s.to_string())
    }
}

/// Synthetic scene specification (`ggpt-synth`): kind, views, resolution, seed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SynthSpec {
    /// `room` or `object`.
    pub kind: ggpt_synth::SceneKind,
    /// Views.
    pub views: usize,
    /// ff width (multiple of 14).
    pub width: usize,
    /// ff height (multiple of 14).
    pub height: usize,
    /// Generator seed.
    pub seed: u64,
    /// Simulation regime; chunk sets written before regimes existed hold easy-regime scenes.
    #[serde(default = "ggpt_synth::Regime::before_regimes")]
    pub regime: ggpt_synth::Regime,
}

/// Generates a synthetic scene and runs the SfM stage (benchmark preset, seed 42) on it.
/// Returns the scene (with `sfm` set) and the SfM result.
pub fn synthetic_scene(spec: &SynthSpec) -> Result<(Scene, SfmResult)> {
    let cfg = ggpt_synth::SynthConfig {
        kind: spec.kind,
        views: spec.views,
        width: spec.width,
        height: spec.height,
        seed: spec.seed,
        ..ggpt_synth::SynthConfig::for_regime(spec.regime)
    };
    let out = ggpt_synth::generate(&cfg)?;
    let mut scene = out.scene;
    let ff = scene
        .ff
        .as_ref()
        .ok_or_else(|| TrainError::Invalid("synthetic scene without feed-forward".into()))?;
    let sfm_cfg = ggpt_sfm::pipeline::SfmConfig::preset(ggpt_sfm::masks::Preset::Benchmark);
    let sfm = ggpt_sfm::pipeline::run_sfm(ff, &scene.images, scene.dims, &scene.matches, &sfm_cfg)
        .map_err(|e| TrainError::Sfm(format!("{}: {e}", scene.name)))?
        .result;
    scene.matches.clear();
    scene.sfm = Some(sfm.clone());
    Ok((scene, sfm))
}

/// Reads an official per-sequence directory (`gt.bin`, `ff_outputs.bin`, `sfm_dlt_outputs.bin`).
pub fn official_scene(dir: &Path) -> Result<(Scene, SfmResult)> {
    let scene = ggpt_core::io::official::read_official_dir(dir)?;
    let sfm = scene
        .sfm
        .clone()
        .ok_or_else(|| TrainError::Invalid(format!("{}: no sfm_dlt_outputs.bin", dir.display())))?;
    if scene.gt.is_none() {
        return Err(TrainError::Invalid(format!(
            "{}: no gt.bin (training needs ground truth)",
            dir.display()
        )));
    }
    if scene.ff.is_none() {
        return Err(TrainError::Invalid(format!(
            "{}: no ff_outputs.bin",
            dir.display()
        )));
    }
    Ok((scene, sfm))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec() -> SynthSpec {
        SynthSpec {
            kind: ggpt_synth::SceneKind::Object,
            views: 3,
            width: 56,
            height: 42,
            seed: 7,
            regime: ggpt_synth::Regime::Benchmark,
        }
    }

    #[test]
    fn typed_form_round_trips() {
        for s in [
            SceneSource::Synthetic(spec()),
            SceneSource::Official(PathBuf::from("/data/seq 1")),
            SceneSource::Other("test".into()),
        ] {
            let j = serde_json::to_string(&s).unwrap();
            assert!(j.starts_with('{'), "{j}");
            assert_eq!(serde_json::from_str::<SceneSource>(&j).unwrap(), s);
        }
    }

    #[test]
    fn old_string_form_is_read() {
        let old = format!(
            "\"synthetic:{}\"",
            serde_json::to_string(&spec()).unwrap().replace('"', "\\\"")
        );
        assert_eq!(
            serde_json::from_str::<SceneSource>(&old).unwrap(),
            SceneSource::Synthetic(spec())
        );
        assert_eq!(
            serde_json::from_str::<SceneSource>("\"official:/a/b\"").unwrap(),
            SceneSource::Official(PathBuf::from("/a/b"))
        );
        assert_eq!(
            serde_json::from_str::<SceneSource>("\"test\"").unwrap(),
            SceneSource::Other("test".into())
        );
        let e = serde_json::from_str::<SceneSource>("\"synthetic:{bad\"").unwrap_err();
        assert!(e.to_string().contains("synthetic scene source"), "{e}");
        assert!(serde_json::from_str::<SceneSource>("{\"mystery\": 1}").is_err());
    }

    #[test]
    fn other_sources_cannot_be_rebuilt() {
        let e = SceneSource::Other("x".into()).load("s").unwrap_err();
        assert!(e.to_string().contains("cannot be rebuilt"), "{e}");
    }
}
