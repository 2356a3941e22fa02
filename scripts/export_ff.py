#!/usr/bin/env python3
"""Runs a feed-forward reconstruction model on a folder of images and writes what `ggpt-infer run
--ff` reads (docs/images-to-splats.md): `predictions.npz` in VGGT's layout, `images/` (the input
images in the orientation the model saw, at their original resolution, for `--images`) and
`predictions.json` (names, original sizes, the preprocessing).

    python scripts/export_ff.py --images photos/ --out work/ [--model vggt|pi3|mapanything]

Preprocessing, as the official GGPT demo (`run_demo.py`, shared/spec pipeline.md §2.1): a
portrait image is transposed so that its width is at least its height; every view is resized
(bilinear) to width 518 and height `round(518 H / W / 14) * 14` of the first view's aspect.
`images/` keeps the original resolution (transposed where the model saw a transposed image), so
the cameras `ggpt-infer` writes at that resolution match it.

Models (installed separately, not by ggpt-rs): VGGT (`pip install vggt` from
facebookresearch/vggt; checkpoint `facebook/VGGT-1B`), Pi3 (`pi3`, `yyfz233/Pi3`), MapAnything
(`mapanything`, `facebook/map-anything`). The model runs in float32 on `--device` (default
`cuda` when available). Not run in CI (no model weights there); its array conversion
(`vggt_outputs_to_arrays`, `preprocessed_size`) is tested in CI on synthetic arrays
(`crates/ggpt-py/tests/test_export_ff.py`).
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path
from typing import Any, Mapping

import numpy as np

FF_WIDTH = 518
PATCH = 14
IMAGE_EXTS = {".jpg", ".jpeg", ".png"}


def preprocessed_size(width: int, height: int, target_width: int = FF_WIDTH) -> tuple[int, int, bool]:
    """`(w, h, transposed)` of the model input for an image of `width x height`: portrait images
    are transposed first; then width `target_width`, height rounded to a multiple of 14."""
    transposed = height > width
    if transposed:
        width, height = height, width
    h = max(PATCH, int(round(height * target_width / width / PATCH)) * PATCH)
    return target_width, h, transposed


def _numpy(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().float().cpu().numpy()
    return np.asarray(x)


def vggt_outputs_to_arrays(predictions: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """VGGT's outputs (after `pose_encoding_to_extri_intri`: `extrinsic`, `intrinsic`; torch or
    numpy, with or without the leading batch of 1, any float dtype) as the arrays of
    `predictions.npz`: float32, batch removed, `depth [S, H, W, 1]`, `images [S, 3, H, W]`."""
    out: dict[str, np.ndarray] = {}
    ranks = {
        "extrinsic": 3,
        "intrinsic": 3,
        "depth": 4,
        "depth_conf": 3,
        "world_points": 4,
        "world_points_conf": 3,
        "images": 4,
    }
    for key, rank in ranks.items():
        if key not in predictions:
            continue
        a = _numpy(predictions[key]).astype(np.float32)
        if key == "depth" and a.shape[-1] != 1:
            a = a[..., None]  # [(B,) S, H, W] without the trailing channel axis
        if a.ndim == rank + 1:
            if a.shape[0] != 1:
                raise ValueError(f"{key}: batch of {a.shape[0]}; export one scene at a time")
            a = a[0]
        if a.ndim != rank:
            raise ValueError(f"{key}: shape {a.shape}, expected {rank} axes (plus a batch of 1)")
        if key == "images" and a.shape[-1] == 3 and a.shape[1] != 3:
            a = np.transpose(a, (0, 3, 1, 2))
        out[key] = np.ascontiguousarray(a)
    missing = [k for k in ("extrinsic", "intrinsic") if k not in out]
    if missing:
        raise ValueError(
            f"missing {missing}: run vggt.utils.pose_enc.pose_encoding_to_extri_intri on pose_enc first"
        )
    if "depth" not in out and "world_points" not in out:
        raise ValueError("neither depth nor world_points in the predictions")
    return out


def list_images(folder: Path) -> list[Path]:
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTS)
    if not files:
        raise SystemExit(f"{folder}: no .jpg/.jpeg/.png image")
    return files


def load_views(files: list[Path]) -> tuple[np.ndarray, list[dict[str, Any]], list[Any]]:
    """Model inputs `[S, 3, h, w]` in [0, 1], the per-view records, and the oriented originals."""
    from PIL import Image

    originals = [Image.open(f).convert("RGB") for f in files]
    w0, h0 = originals[0].size
    w, h, _ = preprocessed_size(w0, h0)
    views, records, oriented = [], [], []
    for f, im in zip(files, originals):
        width, height = im.size
        transposed = height > width
        if transposed:
            im = im.transpose(Image.Transpose.TRANSPOSE)
        oriented.append(im)
        small = im.resize((w, h), Image.Resampling.BILINEAR)
        views.append(np.asarray(small, dtype=np.float32).transpose(2, 0, 1) / 255.0)
        records.append(
            {"name": f.name, "original_size": [width, height], "transposed": transposed, "size": list(im.size)}
        )
    return np.stack(views), records, oriented


def run_vggt(images: np.ndarray, device: str, checkpoint: str) -> dict[str, np.ndarray]:
    import torch
    from vggt.models.vggt import VGGT
    from vggt.utils.pose_enc import pose_encoding_to_extri_intri

    model = VGGT.from_pretrained(checkpoint).to(device).eval()
    x = torch.from_numpy(images).to(device)
    with torch.no_grad():
        pred = model(x)
    pred["extrinsic"], pred["intrinsic"] = pose_encoding_to_extri_intri(pred["pose_enc"], x.shape[-2:])
    pred["images"] = x
    return vggt_outputs_to_arrays(pred)


def run_pi3(images: np.ndarray, device: str, checkpoint: str) -> dict[str, np.ndarray]:
    import torch
    from pi3.models.pi3 import Pi3

    model = Pi3.from_pretrained(checkpoint).to(device).eval()
    x = torch.from_numpy(images).to(device)[None]
    with torch.no_grad():
        pred = model(x)
    keys = ("points", "local_points", "conf", "camera_poses")
    out = {k: _numpy(pred[k]).astype(np.float32)[0] for k in keys}
    out["images"] = images.astype(np.float32)
    return out


def run_mapanything(images: np.ndarray, device: str, checkpoint: str) -> dict[str, np.ndarray]:
    import torch
    from mapanything.models import MapAnything

    model = MapAnything.from_pretrained(checkpoint).to(device).eval()
    views = [{"img": torch.from_numpy(im)[None].to(device), "data_norm_type": ["identity"]} for im in images]
    with torch.no_grad():
        preds = model.infer(views)
    keys = ("pts3d", "conf", "intrinsics", "camera_poses")
    out = {k: np.concatenate([_numpy(p[k]).astype(np.float32) for p in preds]) for k in keys}
    out["img_no_norm"] = images.transpose(0, 2, 3, 1).astype(np.float32)
    return out


MODELS = {
    "vggt": (run_vggt, "facebook/VGGT-1B"),
    "pi3": (run_pi3, "yyfz233/Pi3"),
    "mapanything": (run_mapanything, "facebook/map-anything"),
}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--images", type=Path, required=True, help="folder of .jpg/.jpeg/.png images")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--model", choices=sorted(MODELS), default="vggt")
    p.add_argument("--checkpoint", help="model checkpoint (default: the model's public one)")
    p.add_argument("--device", default=None, help="torch device (default: cuda when available)")
    a = p.parse_args()
    import torch

    device = a.device or ("cuda" if torch.cuda.is_available() else "cpu")
    files = list_images(a.images)
    images, records, oriented = load_views(files)
    run, default_ckpt = MODELS[a.model]
    arrays = run(images, device, a.checkpoint or default_ckpt)
    a.out.mkdir(parents=True, exist_ok=True)
    np.savez(a.out / "predictions.npz", **arrays)
    img_dir = a.out / "images"
    img_dir.mkdir(exist_ok=True)
    for f, rec, im in zip(files, records, oriented):
        if rec["transposed"]:
            im.save(img_dir / f.name)
        else:
            shutil.copy2(f, img_dir / f.name)
    meta = {
        "model": a.model,
        "checkpoint": a.checkpoint or default_ckpt,
        "ff_size": [int(images.shape[3]), int(images.shape[2])],
        "views": records,
    }
    (a.out / "predictions.json").write_text(json.dumps(meta, indent=1))
    print(f"wrote {a.out / 'predictions.npz'} ({len(files)} views at {images.shape[3]}x{images.shape[2]}) and {img_dir}")


if __name__ == "__main__":
    main()
