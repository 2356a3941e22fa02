"""The network through `Model.forward_chunks` against the official reference outputs."""

from __future__ import annotations

import numpy as np
import pytest
from safetensors.numpy import load_file

import ggpt_rs as ggpt


def test_chunk_parity_with_the_official_small_model(fixtures):
    d = fixtures / "ggpt_small"
    model = ggpt.Model(d / "weights.pth", model_config=d / "manifest.json", device="cpu")
    assert not model.shipped and model.config["enc_channels"] == [16, 16, 24, 32, 32]
    inputs = load_file(d / "inputs.safetensors")
    reference = load_file(d / "outputs.safetensors")
    chunks = [
        {k: inputs[f"chunk{c}/{k}"] for k in ("ff_pts", "ff_pts_conf", "geo_pts", "geo_msks")}
        for c in range(2)
    ]
    outputs = model.forward_chunks(chunks)
    assert len(outputs) == 2
    for c, out in enumerate(outputs):
        for key, value in out.items():
            want = reference[f"chunk{c}/{key}"]
            assert value.dtype == np.float32 and value.shape == want.shape, key
            worst = float(np.abs(value - want).max())
            assert worst <= 1e-4, f"chunk{c}/{key}: max |diff| {worst:e}"
    # one batched forward gives the same results
    batched = model.forward_chunks(chunks, batched=True)
    for a, b in zip(outputs, batched):
        np.testing.assert_allclose(a["ff_pts_out"], b["ff_pts_out"], atol=1e-5)


def test_shipped_model_and_bad_weights(tmp_path):
    m = ggpt.Model("shipped")
    assert m.shipped and m.weights.startswith("<embedded>")
    assert "shipped" in repr(m)
    truncated = tmp_path / "model.pth"
    truncated.write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(ggpt.ModelError) as e:
        ggpt.Model(truncated, preset="small")
    assert "model.pth" in str(e.value) and e.value.path.endswith("model.pth")
    with pytest.raises(ggpt.ModelError) as e:
        ggpt.Model(tmp_path / "nope.safetensors", preset="small")
    assert "not found" in str(e.value)
    with pytest.raises(ggpt.ModelError):
        ggpt.Model("shipped", preset="released")
