"""Which way do these poses map? Detect a pose set that is the inverse of what an API expects.

torchslam uses two directions of one pose (the module docstrings say which, and so do the
pose files of :mod:`torchslam.io.trajectories`):

- T_0i, frame i → world (reference scan): :func:`torchslam.registration.register` and
  :func:`~torchslam.registration.refine`, pose files, TUM/KITTI trajectories;
- T_i0 = T_0i⁻¹, world → frame i: :class:`torchslam.PointMapProblem` (r = X_ij − T_i0 X_0j).

(Pose graphs store the vertices T_i, body → world, like T_0i.) Handing one where the other is
expected does not fail: the solver converges from it, to a wrong answer, and the errors look
like 90–180° rotations. The checks below evaluate the data at the poses as given and at their
inverses — the residuals of the first linearization — and warn (:class:`InvertedPosesWarning`)
when the inverses explain the data clearly better.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from torchslam import _checks
from torchslam.lie import se3
from torchslam.registration.config import check_clouds, check_poses
from torchslam.registration.kdtree import KDTree
from torchslam.registration.neighbors import query_workers

__all__ = ["InvertedPosesWarning", "PoseDirectionCheck", "check_problem_poses", "check_scan_poses"]

# The inverses must explain the data this much better (cost ratio) before a warning: a pose
# set near the identity fits about equally both ways and is never flagged.
RATIO = 0.25


class InvertedPosesWarning(UserWarning):
    """The poses given look like the inverses of the ones the API expects."""


@dataclass(frozen=True)
class PoseDirectionCheck:
    """The data's misfit at the poses as given and at their inverses (lower is better)."""

    # misfit as given, and with every pose inverted (same measure, e.g. cost or 1 − overlap)
    as_given: float
    inverted: float
    # True when the inverses fit clearly better (inverted < RATIO × as_given)
    looks_inverted: bool
    # what the API expects, e.g. "T_0i (frame i → world)"
    expected: str

    def __str__(self) -> str:
        verdict = "looks INVERTED" if self.looks_inverted else "direction plausible"
        return (
            f"poses {verdict}: misfit {self.as_given:.4g} as given vs {self.inverted:.4g} "
            f"inverted (expected {self.expected})"
        )


def _verdict(
    fn: str, as_given: float, inverted: float, expected: str, warn: bool, stacklevel: int = 3
) -> PoseDirectionCheck:
    flagged = bool(math.isfinite(inverted) and inverted < RATIO * as_given and as_given > 0)
    result = PoseDirectionCheck(as_given, inverted, flagged, expected)
    if flagged and warn:
        warnings.warn(
            f"{fn}: the poses look inverted: the data fit {as_given / max(inverted, 1e-300):.3g}× "
            f"better with every pose inverted. Expected {expected}; pass "
            "torchslam.se3.inverse(poses) if yours map the other way",
            InvertedPosesWarning,
            stacklevel=stacklevel,
        )
    return result


def check_scan_poses(
    clouds: Sequence[Tensor],
    poses: Tensor,
    distance: float,
    *,
    warn: bool = True,
) -> PoseDirectionCheck:
    """Check that ``poses`` are T_0i (scan i → world), as :func:`~torchslam.registration.refine`
    and the pose files expect, not their inverses.

    The misfit is 1 − (mean over scan pairs of the larger of the two fractions of points
    within ``distance`` of the other scan, world frame): overlapping scans placed right
    overlap; placed by the inverse poses they scatter.

    Args:
        clouds: m ≥ 2 scans in their own frames, (N_i, 3) tensors or numpy arrays.
        poses: candidate T_0i, shape (m, 4, 4).
        distance: neighbourhood distance (> 0), e.g. a couple of voxels.
        warn: emit an :class:`InvertedPosesWarning` when the poses look inverted.

    Returns:
        :class:`PoseDirectionCheck` (misfits in [0, 1]).
    """
    fn = "check_scan_poses"
    clouds = check_clouds(fn, clouds, minimum=2)
    m = len(clouds)
    check_poses(fn, poses, m)
    distance = _checks.check_real(fn, "distance", distance, low=0, low_open=True)
    poses = poses.detach().to(clouds[0].dtype)

    def misfit(T: Tensor) -> float:
        world = [se3.act(T[i], clouds[i]).cpu().numpy() for i in range(m)]
        trees = [KDTree(w) for w in world]
        best = []
        for i in range(m):
            for k in range(i + 1, m):
                a, _ = trees[k].query(
                    world[i], distance_upper_bound=distance, workers=query_workers()
                )
                b, _ = trees[i].query(
                    world[k], distance_upper_bound=distance, workers=query_workers()
                )
                best.append(max(float(np.isfinite(a).mean()), float(np.isfinite(b).mean())))
        return 1.0 - float(np.mean(best))

    return _verdict(fn, misfit(poses), misfit(se3.inverse(poses)), "T_0i (scan i → world)", warn)


def check_problem_poses(problem: object, *, warn: bool = True) -> list[PoseDirectionCheck]:
    """Check that a :class:`torchslam.PointMapProblem` holds T_i0 (world → frame i) poses.

    Compares the cost ½ Σ ρ(rᵀΩr) of the first linearization point with the cost at the
    inverted poses (points as given), per problem of the batch.

    Returns:
        One :class:`PoseDirectionCheck` per problem (B of them).
    """
    fn = "check_problem_poses"
    from torchslam.objective.data import cost_from_poses
    from torchslam.problem import PointMapProblem

    if not isinstance(problem, PointMapProblem):
        raise TypeError(
            f"{fn}: argument 'problem' must be a PointMapProblem, got {_checks.describe(problem)}"
        )
    with torch.no_grad():
        T = problem.poses
        points = problem.points
        given = cost_from_poses(T, points, problem.data)
        flipped = cost_from_poses(se3.inverse(T), points, problem.data)
    return [
        _verdict(fn, float(a), float(b), "T_i0 (world → frame i)", warn)
        for a, b in zip(given.tolist(), flipped.tolist(), strict=True)
    ]
