"""Accuracy metrics of an ICP-SLAM estimate against ground truth: poses, trajectory, points.

Poses are T_i0 (world → frame i) as everywhere in torchslam; the sensor position of frame i
is the translation c_i of T_0i = T_i0⁻¹, c_i = −R_i0ᵀ t_i0. Estimate and ground truth both
fix frame 0 at the identity (the gauge), so they are directly comparable and no alignment is
needed by default; ``align="se3"`` first moves the estimate by the rigid transform S that best
aligns its sensor positions to the ground truth (weighted Kabsch/Umeyama without scale), for
estimates with another gauge.

Definitions (all batched over leading dims):

- rotation error of pose i: the angle of R̂_i0 R_i0ᵀ, in degrees;
- translation error of pose i: ‖ĉ_i − c_i‖ (sensor position error);
- ATE: sqrt(mean_i ‖ĉ_i − c_i‖²), the RMSE of the sensor positions;
- RPE (Sturm et al. 2012) of step i: E_i = (P_i⁻¹ P_{i+1})⁻¹ (P̂_i⁻¹ P̂_{i+1}) with P_i = T_0i,
  i.e. E_i = T_{i,i+1}⁻¹ T̂_{i,i+1}; its rotation angle (degrees) and translation norm;
- point error of point j: ‖X̂_j − X_j‖, summarized by its RMS over the points.

Both the estimate and the ground truth must be finite rigid transforms (checked when
validation is on: a non-rigid estimate would yield wrong angles, a diverged one NaN errors),
and points must be finite. Every pose sequence needs at least one pose (m ≥ 1); ``align="se3"``
needs at least 3 non-collinear sensor positions per problem.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from torchslam import _checks
from torchslam.alignment import weighted_kabsch
from torchslam.lie import se3, so3

__all__ = [
    "TrajectoryErrors",
    "absolute_trajectory_error",
    "align_trajectories",
    "evaluate",
    "point_errors",
    "pose_errors",
    "relative_pose_error",
]


@dataclass(frozen=True, eq=False)
class TrajectoryErrors:
    """Errors of B estimates (m poses, n points) against ground truth; see the module docstring.

    Tensors have the leading batch dims of the inputs, written (B,) here; summary floats are
    means over all problems (and poses, steps or points).
    """

    # Rotation error of each pose in degrees, shape (B, m); 0 at frame 0 when both fix it.
    rotation_error_deg: Tensor
    # Sensor position error ‖ĉ_i − c_i‖ of each pose, shape (B, m).
    translation_error: Tensor
    # ATE, the RMSE of the sensor positions, shape (B,).
    ate: Tensor
    # RPE rotation angle of each step i → i+1 in degrees, shape (B, m-1).
    rpe_rotation_deg: Tensor
    # RPE translation norm of each step, shape (B, m-1).
    rpe_translation: Tensor
    # ‖X̂_j − X_j‖ of each point, shape (B, n); None when no points were given.
    point_error: Tensor | None
    # RMS of the point errors, shape (B,); None when no points were given.
    point_rmse: Tensor | None
    # The transform S applied to the estimate (T̂_0i ← S T̂_0i, X̂ ← S X̂), shape (B, 4, 4);
    # None when align="none".
    alignment: Tensor | None
    # Mean and max of rotation_error_deg over all problems and poses.
    mean_rotation_error_deg: float
    max_rotation_error_deg: float
    # Mean of translation_error over all problems and poses.
    mean_translation_error: float
    # Mean of ate over the problems.
    mean_ate: float
    # Means of the RPE over all problems and steps (0.0 when m = 1).
    mean_rpe_rotation_deg: float
    mean_rpe_translation: float
    # Mean of point_rmse over the problems; None when no points were given.
    mean_point_rmse: float | None

    def summary(self) -> str:
        """One line with the summary figures."""
        text = (
            f"rotation error mean {self.mean_rotation_error_deg:.4g}° "
            f"max {self.max_rotation_error_deg:.4g}°, ATE {self.mean_ate:.4g}, "
            f"RPE {self.mean_rpe_rotation_deg:.4g}° / {self.mean_rpe_translation:.4g}"
        )
        if self.mean_point_rmse is not None:
            text += f", point RMSE {self.mean_point_rmse:.4g}"
        return text


def _check_pose_pair(fn: str, poses: Tensor, poses_gt: Tensor, *, min_poses: int = 0) -> None:
    _checks.check_tensor(fn, "poses", poses, (4, 4))
    _checks.check_tensor(fn, "poses_gt", poses_gt, (4, 4))
    _checks.check_same_kind(fn, poses=poses, poses_gt=poses_gt)
    if poses.dim() < 3:
        raise ValueError(
            f"{fn}: argument 'poses' must have shape (..., m, 4, 4), got {tuple(poses.shape)}"
        )
    if poses.shape != poses_gt.shape:
        raise ValueError(
            f"{fn}: 'poses' and 'poses_gt' must have the same shape (..., m, 4, 4), got "
            f"{tuple(poses.shape)} and {tuple(poses_gt.shape)}"
        )
    if poses.shape[-3] < min_poses:
        raise ValueError(
            f"{fn}: arguments 'poses' and 'poses_gt' must hold at least {min_poses} pose(s) "
            f"(m ≥ {min_poses}), got shape {tuple(poses.shape)}"
        )
    _checks.check_pose_matrix(fn, "poses", poses)
    _checks.check_pose_matrix(fn, "poses_gt", poses_gt)


def _check_point_pair(fn: str, points: Tensor, points_gt: Tensor) -> None:
    _checks.check_tensor(fn, "points", points, (3,))
    _checks.check_tensor(fn, "points_gt", points_gt, (3,))
    _checks.check_same_kind(fn, points=points, points_gt=points_gt)
    if points.shape != points_gt.shape:
        raise ValueError(
            f"{fn}: 'points' and 'points_gt' must have the same shape (..., n, 3), got "
            f"{tuple(points.shape)} and {tuple(points_gt.shape)}"
        )
    _checks.check_finite(fn, "points", points)
    _checks.check_finite(fn, "points_gt", points_gt)


def _alignment(fn: str, poses: Tensor, poses_gt: Tensor) -> Tensor:
    """weighted_kabsch of the sensor positions, its errors rephrased for ``fn``."""
    if poses.shape[-3] < 3:
        raise ValueError(
            f"{fn}: the SE(3) alignment needs at least 3 non-collinear sensor positions per "
            f"problem; 'poses' and 'poses_gt' hold m = {poses.shape[-3]} pose(s), shape "
            f"{tuple(poses.shape)}"
        )
    try:
        return weighted_kabsch(_positions(poses), _positions(poses_gt))
    except ValueError as error:  # the positions are finite here: only a degenerate layout
        raise ValueError(
            f"{fn}: the SE(3) alignment needs at least 3 non-collinear sensor positions per "
            f"problem; those of 'poses' and 'poses_gt' are collinear or coincident ({error})"
        ) from None


def _rotation_angle_deg(R: Tensor) -> Tensor:
    """Rotation angle of R (..., 3, 3) in degrees, exact near 0 (from Log, not acos)."""
    with _checks.validation(False):  # products of checked poses: rigid up to round-off
        return torch.rad2deg(torch.linalg.vector_norm(so3.log(R), dim=-1))


def _positions(poses: Tensor) -> Tensor:
    """Sensor positions c_i = −R_i0ᵀ t_i0, the translation of T_0i, shape (..., m, 3)."""
    R, t = poses[..., :3, :3], poses[..., :3, 3:]
    return -(R.transpose(-1, -2) @ t).squeeze(-1)


def pose_errors(poses: Tensor, poses_gt: Tensor) -> tuple[Tensor, Tensor]:
    """Per-pose rotation error (degrees) and sensor position error, no alignment.

    Args:
        poses: estimated T̂_i0, shape (..., m, 4, 4).
        poses_gt: ground-truth T_i0, same shape.

    Returns:
        (rotation_error_deg, translation_error), each of shape (..., m): the angle of
        R̂_i0 R_i0ᵀ in degrees and ‖ĉ_i − c_i‖ with c_i the translation of T_0i.
    """
    _check_pose_pair("pose_errors", poses, poses_gt)
    return _pose_errors(poses, poses_gt)


def _pose_errors(poses: Tensor, poses_gt: Tensor) -> tuple[Tensor, Tensor]:
    R_hat, R = poses[..., :3, :3], poses_gt[..., :3, :3]
    rotation = _rotation_angle_deg(R_hat @ R.transpose(-1, -2))
    translation = torch.linalg.vector_norm(_positions(poses) - _positions(poses_gt), dim=-1)
    return rotation, translation


def absolute_trajectory_error(poses: Tensor, poses_gt: Tensor) -> Tensor:
    """ATE: RMSE of the sensor positions, sqrt(mean_i ‖ĉ_i − c_i‖²), no alignment.

    Args:
        poses: estimated T̂_i0, shape (..., m, 4, 4), m ≥ 1.
        poses_gt: ground-truth T_i0, same shape.

    Returns:
        ATE, shape (...,).
    """
    _check_pose_pair("absolute_trajectory_error", poses, poses_gt, min_poses=1)
    return _ate(_pose_errors(poses, poses_gt)[1])


def _ate(translation_error: Tensor) -> Tensor:
    return translation_error.square().mean(-1).sqrt()


def relative_pose_error(poses: Tensor, poses_gt: Tensor) -> tuple[Tensor, Tensor]:
    """RPE of successive frames (Sturm et al. 2012), independent of any global alignment.

    E_i = T_{i,i+1}⁻¹ T̂_{i,i+1} with T_{i,i+1} = T_i0 T_{i+1,0}⁻¹ (the motion from frame i to
    frame i+1, P_i⁻¹ P_{i+1} with P_i = T_0i).

    Args:
        poses: estimated T̂_i0, shape (..., m, 4, 4).
        poses_gt: ground-truth T_i0, same shape.

    Returns:
        (rotation_deg, translation), each of shape (..., m−1): the angle of E_i in degrees and
        the norm of its translation.
    """
    _check_pose_pair("relative_pose_error", poses, poses_gt)
    return _rpe(poses, poses_gt)


def _rpe(poses: Tensor, poses_gt: Tensor) -> tuple[Tensor, Tensor]:
    def motion(T: Tensor) -> Tensor:
        return T[..., :-1, :, :] @ se3.inverse(T[..., 1:, :, :])

    with _checks.validation(False):  # checked poses and their products
        E = se3.inverse(motion(poses_gt)) @ motion(poses)
    rotation = _rotation_angle_deg(E[..., :3, :3])
    translation = torch.linalg.vector_norm(E[..., :3, 3], dim=-1)
    return rotation, translation


def point_errors(points: Tensor, points_gt: Tensor) -> Tensor:
    """Per-point error ‖X̂_j − X_j‖, no alignment.

    Args:
        points: estimated world points, shape (..., n, 3).
        points_gt: ground-truth world points, same shape.

    Returns:
        Errors, shape (..., n).
    """
    _check_point_pair("point_errors", points, points_gt)
    return torch.linalg.vector_norm(points - points_gt, dim=-1)


def align_trajectories(poses: Tensor, poses_gt: Tensor) -> Tensor:
    """Rigid S minimizing Σ_i ‖c_i − S ĉ_i‖² over the sensor positions (Umeyama, no scale).

    Apply it as T̂_0i ← S T̂_0i, i.e. T̂_i0 ← T̂_i0 S⁻¹, and X̂ ← S X̂. Needs at least 3
    non-collinear sensor positions (a ValueError otherwise; collinearity is checked when
    validation is on).

    Args:
        poses: estimated T̂_i0, shape (..., m, 4, 4).
        poses_gt: ground-truth T_i0, same shape.

    Returns:
        S, shape (..., 4, 4).
    """
    fn = "align_trajectories"
    _check_pose_pair(fn, poses, poses_gt)
    return _alignment(fn, poses, poses_gt)


def evaluate(
    poses: Tensor,
    poses_gt: Tensor,
    points: Tensor | None = None,
    points_gt: Tensor | None = None,
    *,
    align: Literal["none", "se3"] = "none",
) -> TrajectoryErrors:
    """All the metrics of the module docstring in one :class:`TrajectoryErrors`.

    Args:
        poses: estimated T̂_i0, shape (..., m, 4, 4), m ≥ 1 (m ≥ 3 for ``align="se3"``).
        poses_gt: ground-truth T_i0, same shape.
        points: estimated world points, shape (..., n, 3), or None.
        points_gt: ground-truth world points, same shape, or None (both or neither).
        align: ``"none"`` (default: both fix frame 0 at the identity) or ``"se3"`` (first apply
            :func:`align_trajectories` to the estimate, poses and points). The RPE does not
            depend on the alignment.

    Returns:
        The :class:`TrajectoryErrors`.
    """
    fn = "evaluate"
    _check_pose_pair(fn, poses, poses_gt, min_poses=1)
    if (points is None) != (points_gt is None):
        raise ValueError(f"{fn}: pass both 'points' and 'points_gt' or neither")
    if points is not None and points_gt is not None:
        _check_point_pair(fn, points, points_gt)
        _checks.check_same_kind(fn, poses=poses, points=points)
        if points.shape[:-2] != poses.shape[:-3]:
            raise ValueError(
                f"{fn}: 'points' must have the batch dims of 'poses' {tuple(poses.shape[:-3])} "
                f"in front of (n, 3), got {tuple(points.shape)}"
            )
    if not isinstance(align, str) or align not in ("none", "se3"):
        raise ValueError(
            f"{fn}: argument 'align' must be 'none' or 'se3', got {_checks.describe(align)}"
        )
    if align == "se3":
        alignment = _alignment(fn, poses, poses_gt)
        with _checks.validation(False):  # a rigid alignment of checked inputs
            poses = poses @ se3.inverse(alignment)[..., None, :, :]
            if points is not None:
                points = se3.act(alignment[..., None, :, :], points)
    else:
        alignment = None

    rotation, translation = _pose_errors(poses, poses_gt)
    ate = _ate(translation)
    rpe_rotation, rpe_translation = _rpe(poses, poses_gt)
    point_error = point_rmse = None
    if points is not None and points_gt is not None:
        point_error = torch.linalg.vector_norm(points - points_gt, dim=-1)
        point_rmse = point_error.square().mean(-1).sqrt()

    def mean(x: Tensor) -> float:
        return float(x.detach().mean()) if x.numel() > 0 else 0.0

    return TrajectoryErrors(
        rotation_error_deg=rotation,
        translation_error=translation,
        ate=ate,
        rpe_rotation_deg=rpe_rotation,
        rpe_translation=rpe_translation,
        point_error=point_error,
        point_rmse=point_rmse,
        alignment=alignment,
        mean_rotation_error_deg=mean(rotation),
        max_rotation_error_deg=float(rotation.detach().max()) if rotation.numel() else 0.0,
        mean_translation_error=mean(translation),
        mean_ate=mean(ate),
        mean_rpe_rotation_deg=mean(rpe_rotation),
        mean_rpe_translation=mean(rpe_translation),
        mean_point_rmse=None if point_rmse is None else mean(point_rmse),
    )
