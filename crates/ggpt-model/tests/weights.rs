//! Checkpoint loading: official `.pth` / `.safetensors` strictly, rejection messages, burnpack.
#![allow(clippy::unwrap_used)] // tests unwrap: a failure is the test failing

mod common;

use burn::tensor::Device;
use common::*;
use ggpt_model::infer::prepare_chunks;
use ggpt_model::weights::{load_checkpoint, num_trainable_params, save_burnpack};
use ggpt_model::{Ggpt, GgptConfig, ModelError};
use safetensors::tensor::TensorView;
use safetensors::{Dtype, SafeTensors};

#[allow(deprecated)]
fn device() -> Device {
    Device::ndarray()
}

fn outputs_of(model: &Ggpt, device: &Device) -> Vec<f32> {
    let chunks = fixture_chunks();
    let batch = prepare_chunks(&GgptConfig::small(), &chunks[1..], device).expect("plan");
    let out = model.forward(&batch);
    let mut v = values(&out.tokens_xyz);
    v.extend(values(&out.tokens_conf));
    v
}

#[test]
fn parameter_counts_match_spec() {
    let device = device();
    assert_eq!(
        num_trainable_params(&Ggpt::new(&GgptConfig::small(), &device)),
        623_772
    );
    assert_eq!(
        num_trainable_params(&Ggpt::new(&GgptConfig::released(), &device)),
        53_409_828
    );
}

#[test]
fn pth_and_safetensors_load_strictly_and_agree() {
    let device = device();
    let cfg = GgptConfig::small();
    let st = load_checkpoint(
        Ggpt::new(&cfg, &device),
        &small_dir().join("weights.safetensors"),
    )
    .expect("safetensors loads");
    let pth = load_checkpoint(Ggpt::new(&cfg, &device), &small_dir().join("weights.pth"))
        .expect("pth loads");
    let a = outputs_of(&st, &device);
    let b = outputs_of(&pth, &device);
    assert_eq!(a, b, "pth and safetensors weights give different outputs");
}

/// Writes a modified copy of the fixture safetensors and returns the load error.
fn load_modified(edit: impl Fn(&mut Vec<(String, Dtype, Vec<usize>, Vec<u8>)>)) -> ModelError {
    let bytes = read_fixture("weights.safetensors");
    let st = SafeTensors::deserialize(&bytes).expect("valid");
    let mut entries: Vec<(String, Dtype, Vec<usize>, Vec<u8>)> = st
        .tensors()
        .into_iter()
        .map(|(n, v)| (n, v.dtype(), v.shape().to_vec(), v.data().to_vec()))
        .collect();
    edit(&mut entries);
    let views: Vec<(String, TensorView<'_>)> = entries
        .iter()
        .map(|(n, d, s, b)| (n.clone(), TensorView::new(*d, s.clone(), b).expect("view")))
        .collect();
    let out = safetensors::serialize(views, None).expect("serialize");
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("edited.safetensors");
    std::fs::write(&path, out).expect("write");
    let device = device();
    match load_checkpoint(Ggpt::new(&GgptConfig::small(), &device), &path) {
        Ok(_) => panic!("modified checkpoint was accepted"),
        Err(e) => e,
    }
}

#[test]
fn missing_key_is_rejected_by_name() {
    let err = load_modified(|e| {
        e.retain(|(n, ..)| n != "backbone.backbone.enc.enc2.block1.attn.qkv.weight")
    });
    let msg = err.to_string();
    assert!(
        msg.contains("backbone.backbone.enc.enc2.block1.attn.qkv.weight"),
        "{msg}"
    );
    assert!(
        matches!(err, ModelError::CheckpointMismatch { ref missing, .. } if missing.len() == 1),
        "{msg}"
    );
}

#[test]
fn extra_key_is_rejected_by_name() {
    let err =
        load_modified(|e| e.push(("head.6.weight".into(), Dtype::F32, vec![2], vec![0u8; 8])));
    let msg = err.to_string();
    assert!(msg.contains("head.6.weight"), "{msg}");
    assert!(
        matches!(err, ModelError::CheckpointMismatch { ref unused, .. } if unused.len() == 1),
        "{msg}"
    );
}

#[test]
fn misshaped_key_is_rejected_by_name() {
    let err = load_modified(|e| {
        for (n, _, s, b) in e.iter_mut() {
            if n == "backbone.backbone.dec.dec1.block0.cpe.0.weight" {
                // [16, 3, 3, 3, 16] -> [16, 27, 16] (same bytes, wrong shape)
                *s = vec![s[0], 27, s[4]];
                let _ = b;
            }
        }
    });
    let msg = err.to_string();
    assert!(
        msg.contains("dec.1.blocks.0.cpe.conv.weight") || msg.contains("dec1.block0.cpe.0.weight"),
        "{msg}"
    );
}

#[test]
fn burnpack_roundtrip_is_exact() {
    let device = device();
    let model = small_model(&device);
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("small.bpk");
    save_burnpack(&model, &path).expect("save");
    let loaded = load_checkpoint(Ggpt::new(&GgptConfig::small(), &device), &path).expect("load");
    assert_eq!(outputs_of(&model, &device), outputs_of(&loaded, &device));
}
