"""Deprecated: the terms moved to :mod:`torchslam.objective.terms` (kept for one release).

``torchslam.terms.X`` still returns ``torchslam.objective.terms.X``, with a
``DeprecationWarning``; the public terms are also ``torchslam.Term``,
``torchslam.RelativePoseTerm``, ``torchslam.PosePriorTerm`` and
``torchslam.PointObservationTerm``.
"""

from __future__ import annotations

import warnings

from torchslam.objective import terms as _terms

__all__ = list(_terms.__all__)


def __getattr__(name: str) -> object:
    if name.startswith("__") or not hasattr(_terms, name):
        raise AttributeError(f"module 'torchslam.terms' has no attribute {name!r}")
    warnings.warn(
        f"torchslam.terms is deprecated and will be removed: use torchslam.objective.terms.{name}",
        DeprecationWarning,
        stacklevel=2,
    )
    return getattr(_terms, name)


def __dir__() -> list[str]:
    return sorted(set(__all__) | {"__doc__", "__name__"})
