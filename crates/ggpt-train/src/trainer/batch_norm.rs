//! Re-estimation of the BatchNorm running statistics of a trained model ("precise BN").

use burn::module::Module;
use burn::tensor::Device;
use ggpt_model::{Ggpt, GgptConfig};

use super::{batch_indices, by_scene_of, step_seed};
use crate::chunkset::TrainChunk;
use crate::error::Result;

/// Re-estimates the BatchNorm running statistics of a trained model ("precise BN"): `batches`
/// forwards in training mode over batches drawn as in training (`batch_indices` with its own
/// seed stream), no parameter update, drop path off, with momentum `1 / (k + 1)` at the `k`-th
/// forward, so that each running mean / variance ends as the plain average of the per-batch
/// statistics instead of an exponential average of the last ~1/momentum steps. The momentum is
/// reset to `cfg.bn_momentum` afterwards. `device` must be an autodiff device. The returned
/// model is meant for evaluation and export (its drop path is off).
pub fn recalibrate_batch_norm(
    model: Ggpt,
    cfg: &GgptConfig,
    chunks: &[TrainChunk],
    batch_size: usize,
    batches: usize,
    seed: u64,
    device: &Device,
) -> Result<Ggpt> {
    if chunks.is_empty() || batches == 0 {
        return Ok(model);
    }
    let by_scene = by_scene_of(chunks);
    // Training mode on the autodiff device selects BatchNorm's batch-statistics path; without
    // gradients no graph is recorded, so a forward costs inference memory.
    let mut model = model.fork(device).train().no_grad();
    model.set_drop_path(0.0);
    for k in 0..batches {
        for bn in model.batch_norms_mut() {
            bn.momentum = 1.0 / (k as f64 + 1.0);
        }
        let idx = batch_indices(
            &by_scene,
            batch_size.max(1),
            step_seed(seed, k as u64, 3),
            k as u64,
        );
        let group: Vec<&TrainChunk> = idx.iter().filter_map(|&i| chunks.get(i)).collect();
        let batch = ggpt_model::infer::prepare_chunks(cfg, &group, device)?;
        // the forward updates the running statistics; its outputs are not needed
        let out = model.forward(&batch);
        drop(out);
    }
    for bn in model.batch_norms_mut() {
        bn.momentum = cfg.bn_momentum;
    }
    Ok(model)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::chunkset::Split;
    use crate::trainer::test_util::{cpu, fresh, options, rng_lock, toy_set};

    #[test]
    fn batch_norm_recalibration_replaces_the_running_statistics_deterministically() {
        let _rng = rng_lock();
        let dir = tempfile::tempdir().unwrap();
        let data = toy_set(dir.path());
        let chunks = data.load_split(Split::Train).unwrap();
        let o = options(1);
        let ad = cpu().autodiff();
        let stats = |m: &mut Ggpt| -> Vec<f32> {
            m.batch_norms_mut()
                .iter()
                .flat_map(|bn| {
                    let mut v = bn
                        .running_mean
                        .value()
                        .into_data()
                        .convert::<f32>()
                        .try_to_vec::<f32>()
                        .unwrap();
                    v.extend(
                        bn.running_var
                            .value()
                            .into_data()
                            .convert::<f32>()
                            .try_to_vec::<f32>()
                            .unwrap(),
                    );
                    v
                })
                .collect()
        };
        let mut before = fresh(&o, &ad);
        let s0 = stats(&mut before);
        let mut a =
            recalibrate_batch_norm(fresh(&o, &ad), &o.model, &chunks, 2, 3, 11, &ad).unwrap();
        let mut b =
            recalibrate_batch_norm(fresh(&o, &ad), &o.model, &chunks, 2, 3, 11, &ad).unwrap();
        let (sa, sb) = (stats(&mut a), stats(&mut b));
        assert_eq!(sa, sb, "same seed, same statistics");
        assert_eq!(sa.len(), s0.len());
        assert!(
            sa.iter().zip(&s0).filter(|(x, y)| x != y).count() > sa.len() / 2,
            "running statistics replaced"
        );
        assert!(
            a.batch_norms_mut()
                .iter()
                .all(|bn| bn.momentum == o.model.bn_momentum),
            "momentum restored"
        );
        // one batch with momentum 1 equals a plain training-mode forward with momentum 1
        let mut c =
            recalibrate_batch_norm(fresh(&o, &ad), &o.model, &chunks, 2, 1, 11, &ad).unwrap();
        let mut d = fresh(&o, &ad);
        d.set_drop_path(0.0);
        for bn in d.batch_norms_mut() {
            bn.momentum = 1.0;
        }
        let idx = batch_indices(&by_scene_of(&chunks), 2, step_seed(11, 0, 3), 0);
        let inputs: Vec<_> = idx.iter().map(|&i| chunks[i].to_input()).collect();
        let _ = d.forward(&ggpt_model::infer::prepare_chunks(&o.model, &inputs, &ad).unwrap());
        let (sc, sd) = (stats(&mut c), stats(&mut d));
        let max = sc
            .iter()
            .zip(&sd)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        assert!(max < 1e-6, "max |difference| {max:e}");
    }
}
