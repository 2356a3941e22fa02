"""Shared fixtures of the ggpt_rs tests: the repository, the shared reference fixtures, the
command-line binaries of the same checkout (built by `cargo test`), and a synthetic scene
refined once through `ggpt-infer run` for the parity tests."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]

# The parity scene: small enough for a debug build, chunk settings that accept chunks at this
# resolution (the shipped model's inference.json is sized for 518 x 392).
SCENE_ARGS = ["--seed", "5", "--views", "4", "--width", "168", "--height", "126", "--regime", "easy"]
CHUNK_ARGS = ["--min-chunk-pixels", "300", "--min-chunk-dlt", "40"]
CHUNK_KWARGS = {"min_chunk_pixels": 300, "min_chunk_dlt": 40}


def _must_exist(path: Path, what: str) -> Path:
    if not path.exists():
        pytest.fail(f"{what} not found: {path}", pytrace=False)
    return path


@pytest.fixture(scope="session")
def fixtures() -> Path:
    """`../shared/fixtures` beside the checkout (or `$GGPT_FIXTURES`); missing fails."""
    return _must_exist(
        Path(os.environ.get("GGPT_FIXTURES", REPO.parent / "shared" / "fixtures")),
        "shared fixtures",
    )


@pytest.fixture(scope="session")
def bin_dir() -> Path:
    """The checkout's binaries (`$GGPT_BIN_DIR`, default `target/debug`)."""
    d = Path(os.environ.get("GGPT_BIN_DIR", REPO / "target" / "debug"))
    for name in ("ggpt-synth", "ggpt-infer"):
        _must_exist(d / name, f"binary {name} (run `cargo test` or `cargo build` first)")
    return d


def run(cmd: list[str | os.PathLike[str]]) -> subprocess.CompletedProcess[str]:
    out = subprocess.run([os.fspath(c) for c in cmd], capture_output=True, text=True)
    if out.returncode != 0:
        pytest.fail(f"{cmd[0]} failed ({out.returncode}):\n{out.stderr[-4000:]}", pytrace=False)
    return out


@pytest.fixture(scope="session")
def synth_scene(tmp_path_factory: pytest.TempPathFactory, bin_dir: Path) -> Path:
    """A 4-view synthetic scene directory (project format, with ground truth)."""
    d = tmp_path_factory.mktemp("scene") / "s5"
    run([bin_dir / "ggpt-synth", *SCENE_ARGS, "--out", d])
    return d


@pytest.fixture(scope="session")
def cli_run(tmp_path_factory: pytest.TempPathFactory, bin_dir: Path, synth_scene: Path) -> Path:
    """`ggpt-infer run --seed 42` of the synthetic scene with the shipped model."""
    out = tmp_path_factory.mktemp("cli") / "out"
    run(
        [
            bin_dir / "ggpt-infer",
            "run",
            "--scene",
            synth_scene,
            "--weights",
            "shipped",
            "--seed",
            "42",
            "--device",
            "cpu",
            "--no-progress",
            "--no-error-maps",
            *CHUNK_ARGS,
            "--out",
            out,
        ]
    )
    return out


def read_json(path: Path) -> dict:
    return json.loads(path.read_text())
