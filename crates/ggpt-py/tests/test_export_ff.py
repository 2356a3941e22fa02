"""`scripts/export_ff.py`'s array conversion and preprocessing sizes on synthetic arrays (the
script itself needs a model and is not run in CI)."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

import ggpt_rs as ggpt
from conftest import REPO

spec = importlib.util.spec_from_file_location("export_ff", REPO / "scripts" / "export_ff.py")
export_ff = importlib.util.module_from_spec(spec)
spec.loader.exec_module(export_ff)


def test_preprocessed_size_follows_the_official_demo():
    assert export_ff.preprocessed_size(1920, 1080) == (518, 294, False)
    assert export_ff.preprocessed_size(1080, 1920) == (518, 294, True)
    assert export_ff.preprocessed_size(518, 392) == (518, 392, False)
    w, h, _ = export_ff.preprocessed_size(4000, 3000)
    assert w == 518 and h % 14 == 0


def test_vggt_outputs_to_npz_arrays_read_back(tmp_path):
    s, h, w = 3, 14, 28
    rng = np.random.default_rng(0)
    ext = np.tile(np.eye(3, 4), (1, s, 1, 1)).astype(np.float64)
    ext[0, :, 2, 3] = [0.0, 0.1, 0.2]
    k = np.tile(np.array([[20.0, 0, w / 2], [0, 20.0, h / 2], [0, 0, 1]]), (1, s, 1, 1))
    pred = {
        "extrinsic": ext,
        "intrinsic": k,
        "depth": rng.uniform(1, 2, (1, s, h, w)).astype(np.float16),  # no trailing axis, half
        "depth_conf": rng.uniform(1, 5, (1, s, h, w)),
        "world_points": rng.normal(size=(1, s, h, w, 3)).astype(np.float32),
        "world_points_conf": rng.uniform(1, 5, (1, s, h, w)).astype(np.float32),
        "images": rng.uniform(0, 1, (1, s, h, w, 3)).astype(np.float32),  # channels last
        "pose_enc": np.zeros((1, s, 9)),
    }
    arrays = export_ff.vggt_outputs_to_arrays(pred)
    assert arrays["depth"].shape == (s, h, w, 1) and arrays["images"].shape == (s, 3, h, w)
    assert all(a.dtype == np.float32 for a in arrays.values())
    np.savez(tmp_path / "predictions.npz", **arrays)
    ff = ggpt.FeedForward.from_vggt(np.load(tmp_path / "predictions.npz"))
    assert (ff.num_views, ff.height, ff.width) == (s, h, w)
    np.testing.assert_allclose(ff.images, pred["images"][0], atol=0)
    np.testing.assert_allclose(ff.cam_from_world, ext[0].astype(np.float32), atol=0)
    pts = ggpt.FeedForward.from_vggt(np.load(tmp_path / "predictions.npz"), branch="points")
    assert np.array_equal(pts.points, pred["world_points"][0])
    with pytest.raises(ValueError, match="batch of 2"):
        export_ff.vggt_outputs_to_arrays({**pred, "depth": np.zeros((2, s, h, w))})
    with pytest.raises(ValueError, match="pose_encoding_to_extri_intri"):
        export_ff.vggt_outputs_to_arrays({k: v for k, v in pred.items() if k != "extrinsic"})
