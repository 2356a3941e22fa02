"""GGPT refinement of a VGGT prediction with RoMa-style matches, from Python (docs/python.md).

Runs on a synthetic scene (exact ground truth) written the way VGGT and RoMa deliver their
outputs: the scene's feed-forward prediction as VGGT's `predictions.npz` (`extrinsic`,
`intrinsic`, `depth`, `depth_conf`, `world_points`, `world_points_conf`, `images [1, S, 3, H,
W]`), its dense matches as RoMa warps `[S, S, H, W, 2]` (normalised edge coordinates,
`[source, target]` as `match_dense` returns them) with certainties. Then refines with the
shipped model, evaluates against the ground truth and writes the outputs of `ggpt-infer run`.

    cargo run --release -p ggpt-synth -- --views 4 --out out/s1
    pip install ./crates/ggpt-py
    python examples/python/refine_vggt.py --scene out/s1 --out out/s1_py
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import ggpt_rs as ggpt


def write_vggt_predictions(scene: ggpt.Scene, path: Path) -> None:
    """The scene's feed-forward prediction in VGGT's `predictions.npz` layout."""
    ff = scene.ff
    e, k = ff.cam_from_world, ff.K
    cam = np.einsum("nij,nhwj->nhwi", e[:, :, :3], ff.points.astype(np.float64)) + e[:, None, None, :, 3]
    np.savez(
        path,
        extrinsic=e[None].astype(np.float32),
        intrinsic=k[None].astype(np.float32),
        depth=cam[None, ..., 2:3].astype(np.float32),
        depth_conf=ff.conf[None],
        world_points=ff.points[None],
        world_points_conf=ff.conf[None],
        images=np.transpose(ff.images, (0, 3, 1, 2))[None],
    )


def roma_matches(scene_dir: Path, h: int, w: int) -> list[ggpt.Matches]:
    """The scene's matchers as RoMa would give them: warp in normalised edge coordinates
    (u = 2 (x + 0.5) / w - 1) per `[source, target]` pair, at the feed-forward resolution."""
    from safetensors.numpy import load_file

    out = []
    for f in sorted((scene_dir / "matches").glob("*.safetensors")):
        m = load_file(f)
        n = m["pred_scores"].shape[0]
        xy = np.swapaxes(m["pred_matches"], 0, 1).reshape(n, n, h, w, 2)  # [t, s] -> [s, t]
        warp = np.empty_like(xy)
        warp[..., 0] = 2.0 * (xy[..., 0] + 0.5) / w - 1.0
        warp[..., 1] = 2.0 * (xy[..., 1] + 0.5) / h - 1.0
        certainty = np.swapaxes(m["pred_scores"], 0, 1).reshape(n, n, h, w)
        out.append(ggpt.Matches(warp, certainty, kind="roma", layout="source_target", name=f.stem))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", type=Path, required=True, help="a ggpt-synth scene directory")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--seed", type=int, default=42)
    a = p.parse_args()

    scene = ggpt.read_scene(a.scene)
    a.out.mkdir(parents=True, exist_ok=True)
    npz = a.out / "predictions.npz"
    write_vggt_predictions(scene, npz)

    ff = ggpt.FeedForward.from_vggt(np.load(npz), branch="points")
    matches = roma_matches(a.scene, ff.height, ff.width)
    out = ggpt.refine(ff, matches, model="shipped", seed=a.seed, name=scene.name)
    ev = out.evaluate(scene)
    print(f"{ff.num_views} views at {ff.width}x{ff.height}: {out.stats['counts']['chunks']} chunks, "
          f"{100 * out.covered.mean():.1f} % of the pixels refined")
    print(f"AUC@5 cm: feed-forward {ev['ff']['auc_5']:.2f}, refined {ev['refined']['auc_5']:.2f}")
    print("outputs in", out.save(a.out))


if __name__ == "__main__":
    main()
