"""Whether an alignment can be trusted: overlap, residual RMS and the conditioning of ICP.

ICP's own status only says that the iteration stopped (the RMS no longer falls); a step that
locked onto the wrong structure stops just as well. :func:`alignment_quality` measures an
alignment T (source → target frame) after the fact, on the correspondences it implies:

- ``fitness``: the fraction of source points with a target point within the gate (overlap);
- ``rms``: the RMS point-to-plane distance of those inliers (the units of the clouds);
- ``condition``: λ_min / λ_max of the point-to-plane Gauss-Newton matrix H = Σ JᵀJ with
  J = [(p × n_b)/L, n_b] (p a source point in its own frame, relative to the inliers' centroid,
  n_b the matched target normal rotated into the source frame, L the RMS arm length so that
  rotations and translations compare): near 0 when the overlap leaves a direction free (a
  corridor, a single plane); 1 for a perfectly spread set of normals;
- ``information``: the 6 × 6 information of the pose, Ω = H_p / σ² with H_p = Σ JᵀJ,
  J = [p × n_b, n_b] (right perturbation T·Exp(δ), δ = (ω, v), the body frame of the source),
  and σ the inlier RMS (floored at ``noise_floor``): what a pose graph edge built from this
  alignment weighs.

:class:`QualityThresholds` turns them into one verdict (``trusted``) with the reason it failed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from torchslam import _checks
from torchslam.registration.kdtree import KDTree
from torchslam.registration.neighbors import _host, _Matcher, _query_host, _tree

__all__ = ["AlignmentQuality", "QualityThresholds", "alignment_quality"]


@dataclass(frozen=True)
class QualityThresholds:
    """The acceptance test of an alignment (all must hold)."""

    # at least this fraction of the source points has a target point within the gate
    min_fitness: float = 0.3
    # the inlier RMS point-to-plane distance is at most this (the clouds' units); None: no test
    max_rms: float | None = None
    # λ_min / λ_max of the normalized point-to-plane matrix is at least this
    min_condition: float = 1e-3

    def __post_init__(self) -> None:
        fn = "QualityThresholds"
        _checks.check_real(fn, "min_fitness", self.min_fitness, low=0.0, high=1.0)
        if self.max_rms is not None:
            _checks.check_real(fn, "max_rms", self.max_rms, low=0.0, low_open=True)
        _checks.check_real(fn, "min_condition", self.min_condition, low=0.0, high=1.0)


@dataclass(frozen=True)
class AlignmentQuality:
    """Measures of one alignment (module docstring)."""

    fitness: float
    rms: float
    condition: float
    inliers: int
    # Ω of the source pose, (6, 6), (ω, v) order, right perturbation (module docstring)
    information: Tensor
    # None when trusted, else why not
    problem: str | None

    @property
    def trusted(self) -> bool:
        return self.problem is None


def alignment_quality(
    source: Tensor,
    target: Tensor,
    target_normals: Tensor,
    transform: Tensor,
    gate: float,
    thresholds: QualityThresholds | None = None,
    *,
    noise_floor: float = 0.0,
    tree: KDTree | None = None,
) -> AlignmentQuality:
    """Measure the alignment ``transform`` of ``source`` onto ``target`` (module docstring).

    Args:
        source: cloud in its own frame, (N, 3), N ≥ 1, finite.
        target: cloud, (M, 3), M ≥ 1, finite, same dtype.
        target_normals: unit normals of ``target``, (M, 3).
        transform: T mapping source points into the target frame, (4, 4).
        gate: correspondence distance, > 0 (the clouds' units).
        thresholds: the acceptance test; ``QualityThresholds()`` by default.
        noise_floor: σ used for ``information`` is max(rms, noise_floor), ≥ 0.
        tree: a KD-tree of ``target`` built earlier (built here when None).

    Returns:
        :class:`AlignmentQuality`.
    """
    fn = "alignment_quality"
    source = _checks.as_points(fn, "source", source, min_points=1)
    target = _checks.as_points(fn, "target", target, like=source, min_points=1)
    target_normals = _checks.as_points(fn, "target_normals", target_normals, like=target)
    if target_normals.shape != target.shape:
        raise ValueError(
            f"{fn}: 'target_normals' must have the shape of 'target' {tuple(target.shape)}, "
            f"got {tuple(target_normals.shape)}"
        )
    _checks.check_tensor(fn, "transform", transform, (4, 4))
    if transform.dim() != 2:
        raise ValueError(f"{fn}: argument 'transform' must have shape (4, 4)")
    gate = _checks.check_real(fn, "gate", gate, low=0.0, low_open=True)
    noise_floor = _checks.check_real(fn, "noise_floor", noise_floor, low=0.0)
    thresholds = QualityThresholds() if thresholds is None else thresholds
    if not isinstance(thresholds, QualityThresholds):
        raise TypeError(
            f"{fn}: argument 'thresholds' must be a QualityThresholds or None, got "
            f"{_checks.describe(thresholds)}"
        )
    if tree is None:
        tree = _tree(fn, "target", target)
    return _measure(fn, source, target, target_normals, transform, gate, thresholds,
                    noise_floor, tree)  # fmt: skip


def _measure(
    fn: str,
    source: Tensor,
    target: Tensor,
    target_normals: Tensor,
    transform: Tensor,
    gate: float,
    thresholds: QualityThresholds,
    noise_floor: float,
    tree: KDTree,
    matcher: _Matcher | None = None,
) -> AlignmentQuality:
    """:func:`alignment_quality` on checked arguments. ``matcher``: a
    :class:`~torchslam.registration.neighbors._Matcher` of one run of ``source``'s size on
    ``tree`` (an ICP's, left near ``transform``): its certified answers replace most of the
    lookups, the same nearest neighbours as a fresh query (its class docstring)."""
    T = transform.detach().to(torch.float64).cpu().numpy()
    p = _host(fn, "source", source)
    moved = p @ T[:3, :3].T + T[:3, 3]
    if matcher is None:
        _, index = _query_host(tree, moved, gate)
    else:
        # the query's semantics: a neighbour counts when strictly within the gate
        distance, found = matcher(np.zeros(1, np.int64), torch.from_numpy(moved)[None],
                                  np.array([gate]), fn, "source")  # fmt: skip
        index = np.where(distance[0].numpy() < gate, found[0].numpy(), -1)
    hit = index >= 0
    inliers = int(hit.sum())
    fitness = inliers / len(p)
    eye = torch.eye(6, dtype=torch.float64)
    if inliers < 6:
        return AlignmentQuality(fitness, math.inf, 0.0, inliers, 0 * eye, "too few inliers")
    q = _host(fn, "target", target)[index[hit]]
    n_world = _host(fn, "target_normals", target_normals)[index[hit]]
    plane = np.einsum("ij,ij->i", moved[hit] - q, n_world)
    rms = float(np.sqrt(np.mean(plane * plane)))
    n_body = n_world @ T[:3, :3]  # Rᵀ n, row-wise
    arm = p[hit]
    J = np.concatenate((np.cross(arm, n_body), n_body), axis=1)  # (K, 6), about the origin
    H = J.T @ J
    centred = arm - arm.mean(0)
    length = max(float(np.sqrt(np.mean(np.einsum("ij,ij->i", centred, centred)))), 1e-12)
    Jn = np.concatenate((np.cross(centred, n_body) / length, n_body), axis=1)
    eigen = np.linalg.eigvalsh(Jn.T @ Jn)
    condition = float(max(eigen[0], 0.0) / eigen[-1]) if eigen[-1] > 0 else 0.0
    sigma = max(rms, noise_floor, 1e-12)
    information = torch.from_numpy(H / sigma**2)
    problem = None
    if fitness < thresholds.min_fitness:
        problem = f"overlap {fitness:.2f} < {thresholds.min_fitness:g}"
    elif thresholds.max_rms is not None and rms > thresholds.max_rms:
        problem = f"residual RMS {rms:.3g} > {thresholds.max_rms:g}"
    elif condition < thresholds.min_condition:
        problem = f"ill-conditioned (λ_min/λ_max {condition:.2g} < {thresholds.min_condition:g})"
    return AlignmentQuality(fitness, rms, condition, inliers, information, problem)
