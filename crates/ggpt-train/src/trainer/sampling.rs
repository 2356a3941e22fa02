//! Per-step seeds and the batch drawn at each step: `batch_size` distinct scenes, one random
//! chunk of each, all seeded from `(seed, step)`.

use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};

use crate::chunkset::TrainChunk;

/// Mixes the run seed and a step into a 64-bit seed (SplitMix64 finaliser).
pub fn step_seed(seed: u64, step: u64, salt: u64) -> u64 {
    let mut z =
        seed ^ step.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ salt.wrapping_mul(0xD1B5_4A32_D192_ED03);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Indices of the chunks of step `step`: `batch_size` distinct scenes (random order), one random
/// chunk of each; scenes repeat only when there are fewer scenes than `batch_size`.
pub fn batch_indices(
    by_scene: &[Vec<usize>],
    batch_size: usize,
    seed: u64,
    step: u64,
) -> Vec<usize> {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(step_seed(seed, step, 1));
    let scenes: Vec<usize> = (0..by_scene.len())
        .filter(|&s| !by_scene[s].is_empty())
        .collect();
    let mut out = Vec::with_capacity(batch_size);
    while out.len() < batch_size && !scenes.is_empty() {
        let mut order = scenes.clone();
        order.shuffle(&mut rng);
        for s in order.into_iter().take(batch_size - out.len()) {
            let list = &by_scene[s];
            out.push(list[rng.random_range(0..list.len())]);
        }
    }
    out
}

/// Chunk indices grouped by `TrainChunk::scene` (index = scene).
pub fn by_scene_of(chunks: &[TrainChunk]) -> Vec<Vec<usize>> {
    let num_scenes = chunks.iter().map(|c| c.scene + 1).max().unwrap_or(0);
    let mut by_scene = vec![Vec::new(); num_scenes];
    for (i, c) in chunks.iter().enumerate() {
        by_scene[c.scene].push(i);
    }
    by_scene
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn batches_draw_distinct_scenes_and_are_deterministic() {
        let by_scene = vec![vec![0, 1], vec![2], vec![], vec![3, 4, 5]];
        let b = batch_indices(&by_scene, 3, 42, 5);
        assert_eq!(b, batch_indices(&by_scene, 3, 42, 5));
        let scene_of = |i: usize| by_scene.iter().position(|l| l.contains(&i)).unwrap();
        let mut scenes: Vec<usize> = b.iter().map(|&i| scene_of(i)).collect();
        scenes.sort();
        assert_eq!(scenes, vec![0, 1, 3]);
        // more chunks than scenes: scenes repeat only then
        assert_eq!(batch_indices(&by_scene, 5, 42, 5).len(), 5);
        // the draw changes with the step
        assert!((0..20).any(|t| batch_indices(&by_scene, 3, 42, t) != b));
    }
}
