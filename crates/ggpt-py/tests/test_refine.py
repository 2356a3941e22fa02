"""`refine` against `ggpt-infer run` on the same scene and seed: same refined points, coverage,
evaluation and output files."""

from __future__ import annotations

import numpy as np
from safetensors.numpy import load_file

import ggpt_rs as ggpt
from conftest import CHUNK_KWARGS, read_json


def test_refine_equals_the_cli(synth_scene, cli_run, tmp_path):
    scene = ggpt.read_scene(synth_scene)
    assert scene.gt is not None and len(scene.matches) == 2 and scene.sfm is None
    out = ggpt.refine(scene.ff, scene.matches, model="shipped", seed=42, progress=False, **CHUNK_KWARGS)
    cli = load_file(cli_run / "refined.safetensors")
    n, h, w = 4, 126, 168
    assert out.points.shape == (n, h, w, 3) and out.points.dtype == np.float32
    assert float(np.abs(out.points - cli["points"]).max()) <= 1e-5
    assert float(np.abs(out.confidence - cli["confidence"]).max()) <= 1e-5
    assert np.array_equal(out.covered, cli["covered"].astype(bool))
    assert out.covered.mean() > 0.3, "the parity scene must refine most pixels"
    # the SfM stage ran here as in the CLI: same cameras
    meta = read_json(cli_run / "meta.json")
    stats = out.stats
    assert stats["counts"]["chunks"] == meta["counts"]["chunks"] > 0
    assert out.cam_from_world.shape == (n, 3, 4) and out.K.shape == (n, 3, 3)
    assert out.sfm.camera_success and out.sfm.summary["ba"]["success"]

    # evaluation: the numbers of the CLI's evaluation.json
    ev = out.evaluate(scene)
    cli_ev = read_json(cli_run / "evaluation.json")
    for part in ("ff", "refined"):
        for k in ("auc_1", "auc_3", "auc_5", "auc_10"):
            assert abs(ev[part][k] - cli_ev[part][k]) <= 1e-6, (part, k)
    assert ggpt.evaluate(out, scene)["refined"]["auc_5"] == ev["refined"]["auc_5"]

    # save: the files of `ggpt-infer run`
    saved = out.save(tmp_path / "py", error_maps=False)
    assert (saved / "sparse" / "0").is_dir()
    py_meta = read_json(saved / "meta.json")
    # the CLI's scene folder had ground truth (evaluation.json); refine(ff, matches) has none
    assert py_meta["files"] == [f for f in meta["files"] if f != "evaluation.json"]
    py = load_file(saved / "refined.safetensors")
    assert set(py) == set(cli)
    for k in cli:
        assert np.array_equal(py[k], cli[k]), k
    config = read_json(saved / "config.json")
    assert config["command"] == "python" and config["refine"]["chunk_seed"] == 42
    assert config["chunking"]["min_pixels"] == {"value": 300, "origin": "flag"}
    assert not list(saved.rglob("*.tmp*")), "no temporary file left"


def test_refine_from_a_scene_and_with_a_given_sfm(synth_scene, cli_run, tmp_path):
    scene = ggpt.read_scene(synth_scene)
    a = ggpt.refine(scene, model=ggpt.Model("shipped"), seed=42, progress=False, **CHUNK_KWARGS)
    b = ggpt.refine(scene.ff, sfm=a.sfm, seed=42, progress=False, **CHUNK_KWARGS)
    assert np.array_equal(a.points, b.points)
    assert "chunks" in repr(a)
    # from a scene with ground truth, save writes the evaluation too, as `ggpt-infer run`
    saved = a.save(tmp_path / "a", error_maps=False)
    assert read_json(saved / "meta.json")["files"] == read_json(cli_run / "meta.json")["files"]
    assert read_json(saved / "evaluation.json")["refined"]["auc_5"] == a.evaluate()["refined"]["auc_5"]


def test_matches_layouts_agree(synth_scene):
    """The same matches given source-target (as `match_dense` returns them) or target-source."""
    scene = ggpt.read_scene(synth_scene)
    m = load_file(synth_scene / "matches" / "synthetic-a.safetensors")
    ts = ggpt.Matches(m["pred_matches"], m["pred_scores"], kind="ff_pixels", layout="target_source", name="a")
    st = ggpt.Matches(
        np.swapaxes(m["pred_matches"], 0, 1),
        np.swapaxes(m["pred_scores"], 0, 1),
        kind="ff_pixels",
        layout="source_target",
        name="a",
    )
    sfm_a = ggpt.run_sfm(scene.ff, [ts], seed=7, progress=False)
    sfm_b = ggpt.run_sfm(scene.ff, [st], seed=7, progress=False)
    assert np.array_equal(sfm_a.mask, sfm_b.mask)
    assert np.array_equal(sfm_a.points, sfm_b.points)
    assert sfm_a.mask.any()
