//! One training step made visible (`ggpt-train grads`): for each input case, the train-mode
//! forward, the loss `L_conf + L_id` (`pipeline.md` §11.3), the gradient of every parameter
//! under its official name, the BatchNorm running statistics after the forward and, for case 0
//! on request, the parameters after one Adam step. Each case is its own batch and starts from
//! the loaded weights, with drop path off and the configuration's BatchNorm momentum. This is the
//! training loop's own code path (`prepare_chunks` on the borrowed `TrainChunk`, `Ggpt::forward`,
//! `loss`, `trainer::adam`), so matching the official reference (`ggpt_small_train`) checks the
//! trainer itself. `docs/training.md` explains how to use it.
//!
//! Input: a safetensors with `case{K}/ff_pts [K,3]`, `ff_pts_conf [K]`, `geo_pts [K,3]`,
//! `geo_msks [K]`, `gt_pts [K,3]`, `gt_msks [K]` (masks BOOL / U8 / I32 / I64 / F32 0-1) for
//! `K = 0, 1, ...`, normalised chunk coordinates. Output names: see [`write_results`].

use std::path::Path;

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::GradientsParams;
use burn::tensor::{Device, Tensor};
use ggpt_core::io::st::{Dtype, StFile, StWriter};
use ggpt_model::{Ggpt, GgptConfig};

use crate::chunkset::TrainChunk;
use crate::error::{Result, TrainError};
use crate::loss::{HostTargets, loss};
use ggpt_core::chunk_input::ChunkInput;

/// One named f32 tensor (official name, PyTorch layout).
#[derive(Debug, Clone, PartialEq)]
pub struct NamedTensor {
    /// Official state-dict name.
    pub name: String,
    /// Shape.
    pub shape: Vec<usize>,
    /// Row-major values.
    pub values: Vec<f32>,
}

/// Everything one case produces.
#[derive(Debug, Clone)]
pub struct CaseResult {
    /// `L`, `L_conf`, `L_id`.
    pub loss: [f32; 3],
    /// `[K, 3]` train-mode dense outputs.
    pub ff_pts_out: Vec<f32>,
    /// `[K]` train-mode dense confidences.
    pub ff_pts_conf_out: Vec<f32>,
    /// `dL/dθ` of every trainable parameter.
    pub grads: Vec<NamedTensor>,
    /// Running statistics after the forward (`<bn>.running_mean`, `<bn>.running_var`).
    pub bn_after: Vec<NamedTensor>,
    /// Parameters after one Adam step, when requested.
    pub after_adam: Option<Vec<NamedTensor>>,
}

fn format_err(path: &Path, message: String) -> TrainError {
    TrainError::Format {
        path: path.to_path_buf(),
        message,
    }
}

/// Reads every `case{K}/...` of an input file as a training chunk (pixels `0..K`, centre 0,
/// radius 1: the values are used as given).
pub fn read_cases(path: &Path) -> Result<Vec<TrainChunk>> {
    let st = StFile::open(path)?;
    let mut cases = Vec::new();
    for k in 0.. {
        let p = format!("case{k}/");
        if !st.has(&format!("{p}ff_pts")) {
            break;
        }
        let f32s = |name: &str| -> Result<(Vec<usize>, Vec<f32>)> {
            let key = format!("{p}{name}");
            let dtype = st.dtype(&key)?;
            if dtype != Dtype::F32 {
                return Err(format_err(
                    path,
                    format!("{key}: expected F32, found {dtype:?}"),
                ));
            }
            let t = st.f32_tensor(&key)?;
            Ok((t.shape, t.data))
        };
        let mask = |name: &str| -> Result<(Vec<usize>, Vec<bool>)> {
            let t = st.mask_tensor(&format!("{p}{name}"))?;
            Ok((t.shape, t.data))
        };
        let (s, ff) = f32s("ff_pts")?;
        let n = match s.as_slice() {
            [n, 3] => *n,
            _ => {
                return Err(format_err(
                    path,
                    format!("{p}ff_pts: shape {s:?}, expected [K, 3]"),
                ));
            }
        };
        let points = |name: &str| -> Result<Vec<[f32; 3]>> {
            let (s, v) = f32s(name)?;
            if s != [n, 3] {
                return Err(format_err(
                    path,
                    format!("{p}{name}: shape {s:?}, expected [{n}, 3]"),
                ));
            }
            if let Some(x) = v.iter().find(|x| !x.is_finite()) {
                return Err(format_err(path, format!("{p}{name}: non-finite value {x}")));
            }
            Ok(v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
        };
        let per_token = |s: Vec<usize>, name: &str| {
            if s == [n] {
                Ok(())
            } else {
                Err(format_err(
                    path,
                    format!("{p}{name}: shape {s:?}, expected [{n}]"),
                ))
            }
        };
        let (s, ff_conf) = f32s("ff_pts_conf")?;
        per_token(s, "ff_pts_conf")?;
        let (s, geo_msk) = mask("geo_msks")?;
        per_token(s, "geo_msks")?;
        let (s, gt_msk) = mask("gt_msks")?;
        per_token(s, "gt_msks")?;
        let ff_pts = ff.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
        let chunk = TrainChunk {
            scene: 0,
            center: [0.0; 3],
            radius: 1.0,
            pixels: (0..n as u32).collect(),
            input: ChunkInput {
                ff_pts,
                ff_conf,
                geo_pts: points("geo_pts")?,
                geo_msk,
            },
            gt_pts: points("gt_pts")?,
            gt_msk,
        };
        chunk
            .validate()
            .map_err(|m| format_err(path, format!("case{k}: {m}")))?;
        cases.push(chunk);
    }
    if cases.is_empty() {
        return Err(format_err(path, "no case0/ff_pts tensor".into()));
    }
    Ok(cases)
}

/// Official name and PyTorch layout of a parameter's values: rank-2 tensors are Burn `Linear`
/// weights `[in, out]`, transposed to `[out, in]`; everything else is stored as is.
fn official_layout(burn_path: &str, shape: Vec<usize>, values: Vec<f32>) -> NamedTensor {
    let name = ggpt_model::weights::official_key(burn_path);
    if let [r, c] = shape[..] {
        let mut t = vec![0.0; values.len()];
        for i in 0..r {
            for j in 0..c {
                t[j * r + i] = values[i * c + j];
            }
        }
        return NamedTensor {
            name,
            shape: vec![c, r],
            values: t,
        };
    }
    NamedTensor {
        name,
        shape,
        values,
    }
}

/// Collects the gradient of every parameter of `model` from `grads`, named officially.
struct GradNamer<'a> {
    grads: &'a GradientsParams,
    path: Vec<String>,
    out: Vec<NamedTensor>,
    error: Option<TrainError>,
}

impl ModuleVisitor for GradNamer<'_> {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.path.push(name.to_string());
    }

    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.path.pop();
    }

    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let path = self.path.join(".");
        // BatchNorm running statistics are module state, not parameters: they have no gradient.
        if path.ends_with(".running_mean") || path.ends_with(".running_var") || self.error.is_some()
        {
            return;
        }
        let Some(g) = self.grads.get::<D>(param.id) else {
            self.error = Some(TrainError::Invalid(format!(
                "parameter {path} received no gradient"
            )));
            return;
        };
        let shape = g.dims().to_vec();
        match ggpt_model::readback::read_tensor_f32(&g, &path) {
            Ok(values) => self.out.push(official_layout(&path, shape, values)),
            Err(e) => self.error = Some(e.into()),
        }
    }
}

/// The gradient of every trainable parameter of `model`, officially named, in module order.
pub fn named_gradients(model: &Ggpt, grads: &GradientsParams) -> Result<Vec<NamedTensor>> {
    let mut namer = GradNamer {
        grads,
        path: Vec::new(),
        out: Vec::new(),
        error: None,
    };
    model.visit(&mut namer);
    match namer.error {
        Some(e) => Err(e),
        None => Ok(namer.out),
    }
}

/// Every parameter of `model` (no BatchNorm running statistics), officially named.
pub fn named_parameters(model: &Ggpt) -> Result<Vec<NamedTensor>> {
    let dict = crate::export::official_state_dict(model, 0)?;
    let mut out = Vec::new();
    for (name, dtype, shape, bytes) in dict {
        if dtype != Dtype::F32 || name.ends_with(".running_mean") || name.ends_with(".running_var")
        {
            continue;
        }
        let values = bytes
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        out.push(NamedTensor {
            name,
            shape,
            values,
        });
    }
    Ok(out)
}

/// Runs one case from the network `fresh` (loaded weights, plain device) on the autodiff
/// `device`: train mode, drop path 0; with `adam_lr`, one Adam step (`trainer::adam`, no
/// clipping) after the backward.
pub fn run_case(
    fresh: &Ggpt,
    cfg: &GgptConfig,
    chunk: &TrainChunk,
    device: &Device,
    adam_lr: Option<f64>,
) -> Result<CaseResult> {
    // `train()` after `fork` gives the case its own running statistics (a clone shares them).
    let mut model = fresh.clone().fork(device).train();
    model.set_drop_path(0.0);
    let batch = ggpt_model::infer::prepare_chunks(cfg, &[chunk], device)?;
    let out = model.forward(&batch);
    let dense = out
        .to_chunks(&batch)?
        .into_iter()
        .next()
        .ok_or_else(|| TrainError::Invalid("no chunk output".into()))?;
    let parts = loss(
        out.tokens_xyz,
        out.tokens_conf,
        &HostTargets::new(&[chunk]).upload(device),
    );
    let values = ggpt_model::readback::read_tensor_f32(
        &Tensor::cat(vec![parts.total.clone(), parts.conf, parts.id], 0),
        "loss",
    )?;
    let loss_terms = [values[0], values[1], values[2]];
    if loss_terms.iter().any(|x| !x.is_finite()) {
        return Err(TrainError::Invalid(format!(
            "non-finite loss terms {loss_terms:?}"
        )));
    }
    let mut bn_after = Vec::new();
    for (path, bn) in model.named_batch_norms() {
        for (stat, state) in [
            ("running_mean", &bn.running_mean),
            ("running_var", &bn.running_var),
        ] {
            let t = state.value_sync();
            let name = format!("{path}.{stat}");
            let values = ggpt_model::readback::read_tensor_f32(&t, &name)?;
            bn_after.push(NamedTensor {
                name: ggpt_model::weights::official_key(&name),
                shape: t.dims().to_vec(),
                values,
            });
        }
    }
    let grads = GradientsParams::from_grads(parts.total.backward(), &model);
    let named = named_gradients(&model, &grads)?;
    let after_adam = match adam_lr {
        Some(lr) => {
            let mut optim = crate::trainer::adam();
            let stepped = optim.step(lr, model, grads);
            Some(named_parameters(&stepped)?)
        }
        None => None,
    };
    Ok(CaseResult {
        loss: loss_terms,
        ff_pts_out: dense.ff_pts_out.iter().flatten().copied().collect(),
        ff_pts_conf_out: dense.ff_pts_conf_out,
        grads: named,
        bn_after,
        after_adam,
    })
}

/// Writes the results as one F32 safetensors file (atomically): per case `case{K}/loss`,
/// `l_conf`, `l_id` (`[1]`), `ff_pts_out`, `ff_pts_conf_out`, `grad/<official name>`,
/// `bn_after/<official name>.running_mean|running_var`, and `after_adam/<official name>` where
/// an Adam step was taken.
pub fn write_results(path: &Path, results: &[CaseResult]) -> Result<()> {
    let mut w = StWriter::new();
    for (k, r) in results.iter().enumerate() {
        let p = format!("case{k}/");
        for (name, v) in [
            ("loss", r.loss[0]),
            ("l_conf", r.loss[1]),
            ("l_id", r.loss[2]),
        ] {
            w.f32(&format!("{p}{name}"), &[1], &[v]);
        }
        let k = r.ff_pts_conf_out.len();
        w.f32(&format!("{p}ff_pts_out"), &[k, 3], &r.ff_pts_out);
        w.f32(&format!("{p}ff_pts_conf_out"), &[k], &r.ff_pts_conf_out);
        for (group, list) in [
            ("grad", Some(&r.grads)),
            ("bn_after", Some(&r.bn_after)),
            ("after_adam", r.after_adam.as_ref()),
        ] {
            for t in list.into_iter().flatten() {
                w.f32(&format!("{p}{group}/{}", t.name), &t.shape, &t.values);
            }
        }
    }
    let data = w.finish(path, None)?;
    ggpt_core::io::atomic::write_bytes_atomic(path, &data)?;
    Ok(())
}

/// Official names of the biases whose gradient is exactly 0 in train mode, because every path
/// from them to the loss passes through a train-mode BatchNorm, which removes any per-channel
/// shift: the Linear before each BatchNorm (`embedding.0`, `enc{s}.down.proj`,
/// `dec{s}.up.proj.0`, `dec{s}.up.proj_skip.0`), and `mlp.0.fc2` of the last block of every stage
/// whose output only feeds such Linears (each encoder stage, into the next pooling, whose max
/// commutes with a shift, and into a decoder skip; each decoder stage but the last, into the
/// next unpooling). A reference computed in floating point holds round-off noise there, and
/// Adam's first step maps that noise to ±lr, so comparisons treat these tensors separately.
pub fn bn_invariant_biases(cfg: &GgptConfig) -> Vec<String> {
    let mut burn_paths = vec!["embedding.linear.bias".to_string()];
    for s in 1..cfg.enc_depths.len() {
        burn_paths.push(format!("enc.{s}.down.proj.bias"));
    }
    for s in 0..cfg.dec_depths.len() {
        burn_paths.push(format!("dec.{s}.up.proj.linear.bias"));
        burn_paths.push(format!("dec.{s}.up.proj_skip.linear.bias"));
    }
    for (s, &d) in cfg.enc_depths.iter().enumerate() {
        burn_paths.push(format!(
            "enc.{s}.blocks.{}.mlp.fc2.bias",
            d.saturating_sub(1)
        ));
    }
    for (s, &d) in cfg.dec_depths.iter().enumerate().skip(1) {
        burn_paths.push(format!(
            "dec.{s}.blocks.{}.mlp.fc2.bias",
            d.saturating_sub(1)
        ));
    }
    burn_paths
        .iter()
        .map(|p| ggpt_model::weights::official_key(p))
        .collect()
}
