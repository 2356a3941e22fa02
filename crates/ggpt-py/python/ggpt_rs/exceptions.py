"""Typed exceptions of ggpt_rs, raised by the compiled module from the Rust libraries' errors.

Every exception derives from :class:`GgptError`; the ones about bad input also derive from
:class:`ValueError`. Attributes that do not apply are ``None``.
"""

from __future__ import annotations

from typing import Any

__all__ = [
    "GgptError",
    "InvalidInputError",
    "NonFiniteError",
    "NoGuidanceError",
    "SfmError",
    "ModelError",
    "FormatError",
]


class GgptError(Exception):
    """Base class of every ggpt_rs error. ``path``: the file involved, if any."""

    path: str | None

    def __init__(self, message: str, **attrs: Any) -> None:
        super().__init__(message)
        self.path = None
        for key, value in attrs.items():
            setattr(self, key, value)


class InvalidInputError(GgptError, ValueError):
    """Arrays of the wrong shape, dtype or size, inconsistent views, bad options."""


class NonFiniteError(InvalidInputError):
    """A NaN or infinity in an input array.

    ``array``: the array's name, ``index``: the flat (C-order) index of the first bad value,
    ``value``: that value, ``path``: the file or the object the array came from.
    """

    array: str | None
    index: int | None
    value: float | None

    def __init__(self, message: str, **attrs: Any) -> None:
        self.array = None
        self.index = None
        self.value = None
        super().__init__(message, **attrs)


class NoGuidanceError(GgptError):
    """The SfM stage produced no DLT point, so there is nothing to refine (pass
    ``allow_unrefined=True`` to get the aligned feed-forward points instead)."""


class SfmError(GgptError):
    """The SfM stage failed on valid input (degenerate geometry)."""


class ModelError(GgptError):
    """A model could not be loaded: missing, truncated or mismatched weights, a bad
    configuration or ``inference.json``."""


class FormatError(InvalidInputError):
    """A file (or a dict of arrays) is malformed or unreadable: a missing key, a wrong shape or
    dtype. ``path``: the file (or what the arrays are), ``key``: the tensor / array / field
    (empty when the problem is the file as a whole)."""

    key: str | None

    def __init__(self, message: str, **attrs: Any) -> None:
        self.key = None
        super().__init__(message, **attrs)
