"""Progress reporting: the compiled module calls ``callback(stage, done, total, detail)``."""

from __future__ import annotations

from typing import Any, Callable, Optional, Union

ProgressCallback = Callable[[str, int, int, str], Any]
ProgressArg = Union[bool, None, ProgressCallback]


class TqdmProgress:
    """One tqdm bar per stage (``sfm``: its steps, ``refine``: chunks)."""

    def __init__(self, tqdm: Any) -> None:
        self._tqdm = tqdm
        self._bars: dict[str, Any] = {}

    def __call__(self, stage: str, done: int, total: int, detail: str) -> None:
        bar = self._bars.get(stage)
        if bar is None:
            bar = self._tqdm(total=total, desc=stage, leave=False)
            self._bars[stage] = bar
        if bar.total != total:
            bar.total = total
        bar.n = done
        if detail:
            bar.set_postfix_str(detail, refresh=False)
        bar.refresh()
        if done >= total:
            bar.close()

    def close(self) -> None:
        for bar in self._bars.values():
            bar.close()
        self._bars.clear()


def resolve(progress: ProgressArg) -> tuple[Optional[ProgressCallback], Optional[TqdmProgress]]:
    """``True``: a tqdm bar when tqdm is importable (else none); ``False`` / ``None``: none; a
    callable: called as ``callback(stage, done, total, detail)`` — raising from it stops the
    call at its next check and the exception propagates."""
    if progress is True:
        try:
            from tqdm.auto import tqdm
        except ImportError:
            return None, None
        bars = TqdmProgress(tqdm)
        return bars, bars
    if progress is False or progress is None:
        return None, None
    if callable(progress):
        return progress, None
    raise TypeError(f"progress: expected a bool or a callable, got {type(progress).__name__}")
