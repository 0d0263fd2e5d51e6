"""Loop closure: candidates from revisits, each verified by ICP with a documented test.

**Candidates.** When keyframe k arrives, the earlier keyframes j with

- ‖p_k − p_j‖ ≤ ``loop_radius`` (positions of the odometry poses),
- k − j ≥ ``loop_min_gap`` keyframes and at least ``loop_min_path`` metres travelled from j to k

are candidates, nearest first (at most ``loop_candidates`` verified per keyframe, none within
``loop_cooldown`` keyframes after an accepted closure).

**Verification.** Keyframe k's cloud is registered by point-to-plane ICP (the library's loop,
Cauchy kernel) against the submap of keyframes j − w … j + w (``loop_window``) merged in the
world frame at their odometry poses, starting from k's odometry pose, with gates shrinking from
``loop_gate`` to the odometry's scale (``loop_gate``, ÷3, ÷9, then 2 voxels). The closure is
**accepted** when, on the correspondences within 3 voxels
(:func:`torchslam.registration.quality.alignment_quality`):

- the overlap (fitness) is at least ``loop_min_fitness``,
- the RMS point-to-plane distance is at most ``loop_max_rms_voxels`` · voxel,
- the normal equations are well conditioned (λ_min/λ_max ≥ ``min_condition``).

An accepted closure becomes a pose-graph edge j → k with measurement Z_jk = T_j⁻¹ T̂_k (T̂_k
the verified pose) and the alignment's information (scaled like the odometry edges', see
``effective_points``); in the graph it carries a Cauchy kernel and two χ² consistency
checks, against the odometry chain and against the other loops
(:mod:`torchslam.slam.backend`), so one wrong closure that passed cannot bend the map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from torchslam import _checks
from torchslam.lie import se3, so3
from torchslam.registration import icp as _icp
from torchslam.registration.kdtree import KDTree
from torchslam.registration.quality import AlignmentQuality, QualityThresholds, alignment_quality
from torchslam.slam.config import SLAMConfig
from torchslam.slam.odometry import JUDGE_VOXELS, Keyframe

__all__ = ["LoopClosure", "find_candidates", "verify_loop"]


@dataclass
class LoopClosure:
    """A verified (or rejected) loop candidate between keyframes ``first`` < ``second``."""

    first: int
    second: int
    # Z = T_first⁻¹ T̂_second, (4, 4)
    measurement: Tensor
    # information (6, 6), (ω, v), right perturbation of the second keyframe, scaled
    information: Tensor
    quality: AlignmentQuality
    accepted: bool
    # set by the back end: kept in the final graph (its χ² passed), and its χ² there
    kept: bool = False
    chi2: float = float("nan")
    # added by hand with its measurement (SLAM.add_loop(..., measurement=...)), not verified
    forced: bool = False
    # set by the back end: the χ² of this loop against the odometry chain alone (the
    # Mahalanobis distance of the measurement from the chain's prediction), and whether it
    # exceeded the bound (the loop was then dropped before the graph; chi2 holds it too)
    odometry_chi2: float = float("nan")
    contradicts_odometry: bool = False

    @property
    def reason(self) -> str:
        label = "forced" if self.forced else "accepted"
        if not (self.forced or self.accepted):
            return self.quality.problem or "rejected"
        if self.contradicts_odometry:
            return f"{label}, dropped by χ² against the odometry"
        if self.kept or self.chi2 != self.chi2:
            return label
        return f"{label}, dropped by χ² against the other loops"


def find_candidates(
    positions: np.ndarray, path: np.ndarray, k: int, config: SLAMConfig
) -> list[int]:
    """Earlier keyframes j near keyframe k (module docstring), nearest first.

    Args:
        positions: keyframe positions (K, 3) (odometry), K > k.
        path: cumulative distance travelled at each keyframe, (K,).
        k: the new keyframe.
        config: ``loop_radius``, ``loop_min_gap``, ``loop_min_path``.
    """
    last = k - config.loop_min_gap
    if last < 0:
        return []
    earlier = np.arange(last + 1)
    far_enough = path[k] - path[earlier] >= config.loop_min_path
    earlier = earlier[far_enough]
    if earlier.size == 0:
        return []
    distance = np.linalg.norm(positions[earlier] - positions[k], axis=1)
    near = distance <= config.loop_radius
    order = np.argsort(distance[near], kind="stable")
    return [int(j) for j in earlier[near][order]]


def _submap(keyframes: list[Keyframe], j: int, window: int) -> tuple[Tensor, Tensor]:
    lo, hi = max(0, j - window), min(len(keyframes), j + window + 1)
    points, normals = [], []
    for kf in keyframes[lo:hi]:
        R, t = kf.pose[:3, :3], kf.pose[:3, 3]
        points.append(kf.points @ R.T + t)
        normals.append(kf.normals @ R.T)
    return torch.cat(points), torch.cat(normals)


def verify_loop(
    keyframes: list[Keyframe], first: int, second: int, config: SLAMConfig
) -> LoopClosure:
    """Register keyframe ``second`` against the submap around ``first`` and judge it
    (module docstring)."""
    with _icp._host_threads():  # small tensors: one thread, the KD-tree queries the caller's
        return _verify_loop(keyframes, first, second, config)


def _verify_loop(
    keyframes: list[Keyframe], first: int, second: int, config: SLAMConfig
) -> LoopClosure:
    fn = "verify_loop"
    for name, value in (("first", first), ("second", second)):
        _checks.check_int(fn, name, value, minimum=0, maximum=len(keyframes) - 1)
    target, normals = _submap(keyframes, first, config.loop_window)
    source = keyframes[second].points
    tree = KDTree(target.numpy())
    T = keyframes[second].pose.clone()
    gates = [config.loop_gate, config.loop_gate / 3, config.loop_gate / 9, 2 * config.voxel]
    with _checks.validation(False):
        for gate in sorted({max(g, 2 * config.voxel) for g in gates}, reverse=True):
            icp_config = _icp.ICPConfig(
                method="point_to_plane",
                max_iterations=config.icp_iterations,
                max_distance=gate,
                gate_scale=None,
                kernel="cauchy",
                kernel_scale=gate / 3,
                rotation_tolerance_deg=0.01,
                translation_tolerance=0.01 * config.voxel,
            )
            T = _icp._run(fn, source, target, T[None], icp_config, normals, tree)[0].transform
    T = se3.from_rotation_translation(so3.project(T[:3, :3]), T[:3, 3])
    thresholds = QualityThresholds(
        config.loop_min_fitness, config.loop_max_rms_voxels * config.voxel, config.min_condition
    )
    quality = alignment_quality(
        source, target, normals, T, JUDGE_VOXELS * config.voxel, thresholds,
        noise_floor=0.1 * config.voxel, tree=tree,
    )  # fmt: skip
    measurement = se3.compose(se3.inverse(keyframes[first].pose), T)
    information = quality.information * (config.effective_points / max(quality.inliers, 1))
    return LoopClosure(first, second, measurement, information, quality, quality.trusted)
