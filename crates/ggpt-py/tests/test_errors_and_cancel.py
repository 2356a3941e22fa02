"""Errors of `refine` / `run_sfm` and stopping a call: a progress callback that raises, Ctrl-C."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest
from safetensors.numpy import load_file

import ggpt_rs as ggpt
from conftest import CHUNK_KWARGS


@pytest.fixture(scope="module")
def scene(synth_scene):
    return ggpt.read_scene(synth_scene)


def test_no_guidance_and_bad_matches(scene, synth_scene):
    m = load_file(synth_scene / "matches" / "synthetic-a.safetensors")
    weak = ggpt.Matches(m["pred_matches"], m["pred_scores"] * 0.05, kind="ff_pixels", layout="target_source")
    with pytest.raises(ggpt.NoGuidanceError):
        ggpt.refine(scene.ff, [weak], progress=False, **CHUNK_KWARGS)
    out = ggpt.refine(scene.ff, [weak], allow_unrefined=True, progress=False, **CHUNK_KWARGS)
    assert not out.covered.any()
    wrong = ggpt.Matches(m["pred_matches"][:3, :3], m["pred_scores"][:3, :3], kind="ff_pixels")
    with pytest.raises(ggpt.InvalidInputError) as e:
        ggpt.refine(scene.ff, [wrong], progress=False)
    assert "matches[0]" in str(e.value) and "N=4" in str(e.value)
    bad = m["pred_scores"].copy()
    bad[0, 1, 5] = np.inf
    with pytest.raises(ggpt.NonFiniteError) as e:
        ggpt.Matches(m["pred_matches"], bad, kind="ff_pixels")
    assert e.value.array == "scores" and e.value.index == 1 * 21168 + 5
    with pytest.raises(ggpt.InvalidInputError):
        ggpt.refine(scene.ff, progress=False)
    with pytest.raises(ggpt.InvalidInputError):
        ggpt.Matches(m["pred_matches"], m["pred_scores"], kind="sift")


def test_a_raising_callback_stops_after_the_first_forward(scene, tmp_path):
    reports = []

    def stop(stage, done, total, detail):
        reports.append((stage, done))
        if stage == "refine" and done >= 1:
            raise KeyboardInterrupt("stop")

    with pytest.raises(KeyboardInterrupt):
        ggpt.refine(scene, seed=42, progress=stop, max_tokens_per_forward=2000, **CHUNK_KWARGS)
    refine_reports = [r for r in reports if r[0] == "refine"]
    assert refine_reports[-1][1] >= 1 and len(refine_reports) == 1, refine_reports
    assert any(r[0] == "sfm" for r in reports)

    class Custom(Exception):
        pass

    def custom(stage, done, total, detail):
        if stage == "sfm" and detail == "bundle adjustment":
            raise Custom("from the callback")

    with pytest.raises(Custom):
        ggpt.run_sfm(scene.ff, scene.matches, progress=custom)
    assert not (tmp_path / "out").exists()


def test_ctrl_c_interrupts_a_running_refinement(scene):
    t0 = time.monotonic()
    ggpt.refine(scene, seed=42, progress=False, max_tokens_per_forward=2000, **CHUNK_KWARGS)
    full = time.monotonic() - t0
    sent = []

    def ctrl_c_during_bundle_adjustment(stage, done, total, detail):
        # Ctrl-C at a known point of the run (a timer could fire inside a network forward, where
        # nothing polls, or after a fast SfM stage is over), while its stop checks still come
        if detail == "bundle adjustment" and not sent:
            sent.append(time.monotonic())
            os.kill(os.getpid(), signal.SIGINT)

    t0 = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        ggpt.refine(
            scene,
            seed=42,
            progress=ctrl_c_during_bundle_adjustment,
            max_tokens_per_forward=2000,
            **CHUNK_KWARGS,
        )
    assert sent, "the run reported no bundle adjustment"
    assert time.monotonic() - t0 < full, "the interrupted call ran as long as a whole one"
