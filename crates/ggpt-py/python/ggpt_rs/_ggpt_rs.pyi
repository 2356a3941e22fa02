"""Type stubs of the compiled module ``ggpt_rs._ggpt_rs`` (shapes in brackets; ``N`` views at the
feed-forward resolution ``h x w``; pixel-centre convention; ``cam_from_world`` OpenCV axes)."""

import os
import pathlib
from typing import Any, Callable, Mapping, Optional, Sequence

import numpy as np
import numpy.typing as npt

__version__: str

ArrayLike = Any  # a numpy array (float32 / float64 / uint8 / bool) or a torch tensor
ProgressCallback = Callable[[str, int, int, str], Any]
F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
Bool = npt.NDArray[np.bool_]

class Model:
    """A GGPT network on a device: ``weights`` = ``"shipped"``, a ``.pth`` / ``.safetensors`` /
    ``.bpk`` file or a model folder; ``preset``: ``released`` / ``small`` / ``tiny``.

    The first ``Model`` of a process applies ``ggpt-infer``'s glibc malloc settings (freed
    tensor buffers reused from the heap); ``GGPT_RS_MALLOC_TUNING=0`` keeps the process's own."""

    def __init__(
        self,
        weights: str | os.PathLike[str] = "shipped",
        model_config: Optional[str | os.PathLike[str]] = None,
        preset: Optional[str] = None,
        device: str = "cpu",
        threads: int = 0,
    ) -> None: ...
    @property
    def weights(self) -> str: ...
    @property
    def shipped(self) -> bool: ...
    @property
    def device(self) -> str: ...
    @property
    def threads(self) -> int: ...
    @property
    def config(self) -> dict[str, Any]: ...
    def forward_chunks(
        self, chunks: Sequence[Mapping[str, ArrayLike]], batched: bool = False
    ) -> list[dict[str, F32]]:
        """Inputs: ``ff_pts [K, 3]``, ``ff_pts_conf [K]``, ``geo_pts [K, 3]``, ``geo_msks [K]``;
        outputs: ``ff_pts_out [K, 3]``, ``ff_pts_conf_out [K]``, ``geo_pts_out [K, 3]``,
        ``geo_pts_conf_out [K]``, ``tokens_xyz_out [T, 3]``, ``tokens_conf_out [T]``."""

class FeedForward:
    """A feed-forward prediction: points ``[N, h, w, 3]``, conf ``[N, h, w]``,
    ``cam_from_world [N, 3, 4]``, ``K [N, 3, 3]``, optional images ``[N, h, w, 3]`` in [0, 1]."""

    def __init__(
        self,
        points: ArrayLike,
        conf: ArrayLike,
        cam_from_world: ArrayLike,
        K: ArrayLike,
        images: Optional[ArrayLike] = None,
    ) -> None: ...
    @staticmethod
    def from_arrays(
        arrays: Mapping[str, ArrayLike],
        format: Optional[str] = None,
        branch: str = "depth",
        K: Optional[ArrayLike] = None,
        origin: str = "arrays",
    ) -> FeedForward: ...
    @staticmethod
    def from_vggt(predictions: Mapping[str, ArrayLike], branch: str = "depth") -> FeedForward: ...
    @staticmethod
    def from_mapanything(
        outputs: Sequence[Mapping[str, ArrayLike]] | Mapping[str, ArrayLike],
    ) -> FeedForward: ...
    @staticmethod
    def from_pi3(outputs: Mapping[str, ArrayLike], K: Optional[ArrayLike] = None) -> FeedForward: ...
    @property
    def points(self) -> F32: ...
    @property
    def conf(self) -> F32: ...
    @property
    def cam_from_world(self) -> F64: ...
    @property
    def K(self) -> F64: ...
    @property
    def images(self) -> Optional[F32]: ...
    @property
    def num_views(self) -> int: ...
    @property
    def height(self) -> int: ...
    @property
    def width(self) -> int: ...
    @property
    def format(self) -> str: ...

class Matches:
    """Dense matches of one matcher for all ordered view pairs. ``kind``: ``roma`` (warp
    ``[N, N, Hm, Wm, 2]`` normalised, certainty ``[N, N, Hm, Wm]``), ``ufm`` (flow
    ``[N, N, 2, Ho, Wo]``, covisibility ``[N, N, Ho, Wo]``), ``pixels`` (matcher-pixel warp) or
    ``ff_pixels`` (``[N, N, h, w, 2]`` in ff pixels); ``layout``: ``source_target`` (raw
    ``match_dense``) or ``target_source`` (official ``pred_matches``)."""

    def __init__(
        self,
        matches: ArrayLike,
        scores: ArrayLike,
        *,
        kind: str = "roma",
        layout: str = "source_target",
        name: str = "matcher",
        rank_scores: Optional[ArrayLike] = None,
    ) -> None: ...
    @property
    def name(self) -> str: ...
    @property
    def kind(self) -> str: ...
    @property
    def layout(self) -> str: ...

class SfmResult:
    @property
    def points(self) -> F32: ...
    @property
    def mask(self) -> Bool: ...
    @property
    def cam_from_world(self) -> F64: ...
    @property
    def K(self) -> F64: ...
    @property
    def camera_success(self) -> bool: ...
    @property
    def points_success(self) -> bool: ...
    @property
    def summary(self) -> Optional[dict[str, Any]]: ...

class Scene:
    @property
    def name(self) -> str: ...
    @property
    def ff(self) -> Optional[FeedForward]: ...
    @property
    def matches(self) -> list[Matches]: ...
    @property
    def sfm(self) -> Optional[SfmResult]: ...
    @property
    def gt(self) -> Optional[dict[str, Any]]: ...
    @property
    def images(self) -> F32: ...

class RefinedScene:
    @property
    def points(self) -> F32: ...
    @property
    def confidence(self) -> F32: ...
    @property
    def covered(self) -> Bool: ...
    @property
    def aligned_ff_points(self) -> F32: ...
    @property
    def cam_from_world(self) -> F64: ...
    @property
    def K(self) -> F64: ...
    @property
    def sfm(self) -> SfmResult: ...
    @property
    def stats(self) -> dict[str, Any]: ...
    def save(
        self,
        out: str | os.PathLike[str],
        *,
        conf_quantile: float = ...,
        max_points: int = ...,
        colmap: bool = True,
        colmap_text: bool = False,
        colmap_points: bool = True,
        colmap_max_points: int = ...,
        colmap_resolution: Optional[tuple[int, int]] = None,
        colmap_simple_pinhole: bool = False,
        voxel_size: Optional[float] = None,
        splat: bool = True,
        images: Optional[str | os.PathLike[str]] = None,
        error_maps: bool = True,
        error_map_max_cm: float = ...,
    ) -> pathlib.Path: ...
    def evaluate(self, gt: Optional[Scene] = None) -> dict[str, Any]: ...

def read_scene(path: str | os.PathLike[str]) -> Scene: ...
def run_sfm(
    ff: FeedForward,
    matches: Sequence[Matches],
    *,
    preset: str = "demo",
    seed: int = 42,
    progress: Optional[ProgressCallback] = None,
) -> SfmResult: ...
def refine(
    model: Model,
    ff: Optional[FeedForward] = None,
    matches: Optional[Sequence[Matches]] = None,
    *,
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
    progress: Optional[ProgressCallback] = None,
) -> RefinedScene: ...
