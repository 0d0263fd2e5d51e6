"""Whitening: the square root of an objective's weights, so that weighted norms are plain ones.

One factor for every weighted residual of the objective (point observations, terms, pose-graph
edges): U = Lᵀ with UᵀU = Ω for information matrices, √w for scalar weights; then
rᵀΩr = |U r|² and the Jacobian of U r is U J.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["whiten", "whitening"]


def whitening(weight: Tensor | None, information: Tensor | None) -> Tensor | None:
    """The one whitening factor of the objective: U = Lᵀ with UᵀU = Ω = L Lᵀ (Cholesky) for
    information matrices (..., d, d) → (..., d, d), √w for scalar weights (...) → (...), None
    for unit weights; then rᵀΩr = |U r|² (w|r|² = |√w r|²). Padding must already hold safe
    values (I, 1): see :meth:`PointMapData.masked_information` and
    :func:`torchslam.objective.terms.masked_weighting`."""
    if information is not None:
        return torch.linalg.cholesky(information).transpose(-1, -2)
    if weight is not None:
        return torch.sqrt(weight)
    return None


def whiten(factor: Tensor | None, x: Tensor) -> Tensor:
    """U x for a factor of :func:`whitening` with the same leading dims as x: x (..., d, k) →
    (..., d, k) for U (..., d, d) or √w (...); x unchanged for None."""
    if factor is None:
        return x
    if factor.dim() == x.dim() - 2:
        return factor[..., None, None] * x
    return factor @ x
