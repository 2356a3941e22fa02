"""ggpt_rs: GGPT refinement of feed-forward 3D reconstruction (VGGT, Pi3, MapAnything) with
dense matches (RoMa, UFM), implemented in Rust (the ggpt-rs repository), with no spconv,
flash-attn, torch-scatter or pycolmap.

Conventions (as in the Rust libraries, ``docs/conventions.md``):

* arrays are numpy, C order; inputs may be float32 or float64 (torch tensors are accepted and
  converted with ``.detach().cpu().numpy()``); a leading batch dimension of 1 is removed;
* points ``[N, h, w, 3]``, confidences ``[N, h, w]``, pixels ``(x, y)`` with the pixel-centre
  convention (the top-left pixel's centre is ``(0, 0)``), at the feed-forward resolution;
* cameras: ``cam_from_world`` ``[N, 3, 4]`` (``X_cam = R X_world + t``, OpenCV axes: x right,
  y down, z forward) and ``K`` ``[N, 3, 3]`` in pixels;
* refined points live in the SfM frame (the bundle-adjusted cameras' frame, scene units).

Example::

    import ggpt_rs as ggpt
    ff = ggpt.FeedForward.from_vggt(predictions)          # the dict VGGT returns
    m = ggpt.Matches(warp, certainty, layout="source_target", name="romav2-base")
    out = ggpt.refine(ff, [m], model="shipped", seed=42)
    out.points, out.confidence, out.covered, out.cam_from_world, out.K
    out.save("out/")                                      # the files of `ggpt-infer run`
"""

from __future__ import annotations

import functools
import os
from typing import Any, Mapping, Optional, Sequence, Union

from . import _ggpt_rs
from ._ggpt_rs import (
    FeedForward,
    Matches,
    Model,
    RefinedScene,
    Scene,
    SfmResult,
    __version__,
    read_scene,
)
from ._progress import ProgressArg, resolve as _resolve_progress
from .exceptions import (
    FormatError,
    GgptError,
    InvalidInputError,
    ModelError,
    NoGuidanceError,
    NonFiniteError,
    SfmError,
)

__all__ = [
    "FeedForward",
    "Matches",
    "Model",
    "RefinedScene",
    "Scene",
    "SfmResult",
    "read_scene",
    "run_sfm",
    "refine",
    "evaluate",
    "GgptError",
    "InvalidInputError",
    "NonFiniteError",
    "NoGuidanceError",
    "SfmError",
    "ModelError",
    "FormatError",
    "__version__",
]

ModelArg = Union[Model, str, "os.PathLike[str]"]
FeedForwardArg = Union[FeedForward, Scene, Mapping[str, Any]]


@functools.lru_cache(maxsize=2)
def _cached_model(weights: str, device: str, threads: int) -> Model:
    return Model(weights, device=device, threads=threads)


def _model(model: ModelArg, device: str, threads: int) -> Model:
    if isinstance(model, Model):
        return model
    return _cached_model(os.fspath(model), device, threads)


def _feed_forward(ff: Any) -> Any:
    """A ``FeedForward`` (or ``Scene``) as given; a mapping of arrays read with the layout its
    keys name (VGGT, MapAnything, Pi3, ggpt-rs ``ff.npz``)."""
    if ff is None or isinstance(ff, (FeedForward, Scene)):
        return ff
    if hasattr(ff, "keys"):
        return FeedForward.from_arrays(ff, origin="feed-forward arrays")
    raise TypeError(
        f"ff: expected a FeedForward, a Scene or a dict of arrays, got {type(ff).__name__}"
    )


def run_sfm(
    ff: FeedForwardArg,
    matches: Sequence[Matches],
    *,
    preset: str = "demo",
    seed: int = 42,
    progress: ProgressArg = True,
) -> SfmResult:
    """The SfM stage (``ggpt-sfm run``): match filtering and ensembling, bundle adjustment,
    epipolar filter, DLT and scatter. ``preset``: ``demo`` (default), ``benchmark`` (the
    official thresholds) or ``many-views``. Returns the DLT point map (SfM frame) and the
    bundle-adjusted cameras. The GIL is released while it runs; Ctrl-C raises
    ``KeyboardInterrupt`` between steps and BA iterations."""
    ff = _feed_forward(ff)
    if isinstance(ff, Scene):
        ff = ff.ff
    callback, bars = _resolve_progress(progress)
    try:
        return _ggpt_rs.run_sfm(ff, list(matches), preset=preset, seed=seed, progress=callback)
    finally:
        if bars is not None:
            bars.close()


def refine(
    ff: Optional[FeedForwardArg] = None,
    matches: Optional[Sequence[Matches]] = None,
    *,
    model: ModelArg = "shipped",
    scene: Optional[Scene] = None,
    sfm: Optional[SfmResult] = None,
    name: Optional[str] = None,
    seed: Optional[int] = None,
    fusion: str = "mean",
    chunk_size: Optional[float] = None,
    max_chunk_pixels: Optional[int] = None,
    min_chunk_dlt: Optional[int] = None,
    min_chunk_pixels: Optional[int] = None,
    max_tokens_per_forward: Optional[int] = None,
    sfm_preset: str = "demo",
    allow_unrefined: bool = False,
    device: str = "cpu",
    threads: int = 0,
    progress: ProgressArg = True,
) -> RefinedScene:
    """Refines a feed-forward prediction with GGPT: the SfM stage on ``matches`` (unless
    ``sfm`` is given), Sim(3) pre-alignment, cube chunks, the network, fusion. The same code
    and defaults as ``ggpt-infer run``:

    * ``ff``: a ``FeedForward``, a dict of arrays (VGGT / MapAnything / Pi3 layouts, detected
      from the keys), or a ``Scene`` (``read_scene``; its matches, SfM result and ground truth
      are used unless given here);
    * ``model``: a ``Model`` or what ``Model(...)`` takes (``"shipped"``, a ``.pth`` /
      ``.safetensors`` / ``.bpk`` file, a model folder), loaded on ``device`` with ``threads``
      (loaded models are cached);
    * ``seed``: RANSAC, SfM and export seed (default 42); when given it also replaces the chunk
      seed ``crc32(name)`` (``name`` defaults to the scene's, else ``"scene"``), as
      ``ggpt-infer run --seed``;
    * ``fusion``: ``mean`` (official) or ``confidence``; the chunk sampler (``chunk_size``,
      ``max_chunk_pixels``, ``min_chunk_dlt``, ``min_chunk_pixels``) defaults to the model's
      ``inference.json``, else the official values;
    * ``progress``: ``True`` (a tqdm bar when tqdm is installed), ``False``, or
      ``callback(stage, done, total, detail)``; an exception raised by the callback stops the
      run at the next network forward / BA iteration and propagates; so does Ctrl-C
      (``KeyboardInterrupt``).

    The GIL is released while the SfM and the network run.
    """
    ff = _feed_forward(ff)
    if isinstance(ff, Scene):
        if scene is not None:
            raise TypeError("give the scene once: as ff or as scene=")
        scene, ff = ff, None
    callback, bars = _resolve_progress(progress)
    try:
        return _ggpt_rs.refine(
            _model(model, device, threads),
            ff,
            None if matches is None else list(matches),
            scene=scene,
            sfm=sfm,
            name=name,
            seed=seed,
            fusion=fusion,
            chunk_size=chunk_size,
            max_chunk_pixels=max_chunk_pixels,
            min_chunk_dlt=min_chunk_dlt,
            min_chunk_pixels=min_chunk_pixels,
            max_tokens_per_forward=max_tokens_per_forward,
            sfm_preset=sfm_preset,
            allow_unrefined=allow_unrefined,
            progress=callback,
        )
    finally:
        if bars is not None:
            bars.close()


def evaluate(refined: RefinedScene, gt: Optional[Scene] = None) -> dict[str, Any]:
    """Accuracy of a refinement against ground truth (``gt``: a ``Scene`` with ground truth;
    default: the refined scene's own), as ``evaluation.json``: feed-forward, SfM and refined
    AUC@1/3/5/10 cm after a robust Sim(3) to the GT frame, camera AUCs."""
    return refined.evaluate(gt)
