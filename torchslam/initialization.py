"""Initialization of ICP-SLAM problems as the seed does it (section 0).

1. Relative poses between successive frames, T̂_{i+1,i} (maps frame-i coordinates to frame
   i+1), either from a weighted Kabsch alignment of the points both frames observe
   (:func:`relative_poses_kabsch`: X_{i+1,j} ≈ T̂_{i+1,i} X_ij) or from noisy odometry
   (:func:`odometry_relative_poses`, ground truth perturbed by a known amount).
2. Chaining from the origin (gauge T̂_00 = I): T̂_{i0} = T̂_{i,i-1} ⋯ T̂_{1,0}, equivalently
   T̂_0i = T̂_01 T̂_12 ⋯ T̂_{i-1,i} (:func:`chain_relative_poses`).
3. Points by averaging their views mapped to frame 0 (seed eq. 0.2):
   X̂_j = Σ_i w_ij T̂_i0⁻¹ X_ij / Σ_i w_ij over the frames i seeing j (:func:`average_points`).

Observations come as padded edge lists, as in :class:`torchslam.data.SyntheticScene`:
``pose_index``/``point_index`` (B, E) int64, ``observations`` (B, E, 3) with X_ij in frame i,
an optional ``valid`` (B, E) bool mask (False = padding, ignored entirely: its indices,
observations and weights may be anything, out of range or NaN) and optional non-negative
``weights`` (B, E). Each (pose, point) pair is assumed to be observed at most once.

Everything is vectorized over the batch, the observations and the shared-point sets (segment
sums with ``index_add``); only the chaining loops over the m frames. The functions are
differentiable w.r.t. the observations, but the fallback decisions and warnings need a host
sync, so use them eagerly (not under ``vmap``/``jacrev``).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import torch
from torch import Tensor

from torchslam import _checks
from torchslam.alignment import _degenerate_spectrum, _rigid_from_covariance
from torchslam.lie import se3, so3

if TYPE_CHECKING:
    from torchslam.data.synthetic import SyntheticScene

__all__ = [
    "Initialization",
    "average_points",
    "chain_relative_poses",
    "initialize",
    "initialize_scene",
    "odometry_relative_poses",
    "relative_poses_kabsch",
]

# Successive frames need this many shared points for a pairwise alignment.
_MIN_SHARED = 3
# At most this many offending (problem, frame) pairs are listed in one warning.
_MAX_LISTED = 10


@dataclass(frozen=True, eq=False)
class Initialization:
    """An initial estimate of B ICP-SLAM problems (m poses, n points)."""

    # Initial poses T̂_i0 (world → frame i), T̂_00 = I, shape (B, m, 4, 4).
    poses: Tensor
    # Initial world points X̂_j (seed eq. 0.2), shape (B, n, 3).
    points: Tensor
    # Relative poses T̂_{i+1,i} that were chained, shape (B, m-1, 4, 4).
    relative_poses: Tensor
    # True where a pair of successive frames fell back to the identity, shape (B, m-1).
    fallback: Tensor


def relative_poses_kabsch(
    pose_index: Tensor,
    point_index: Tensor,
    observations: Tensor,
    num_poses: int,
    *,
    valid: Tensor | None = None,
    weights: Tensor | None = None,
) -> Tensor:
    """Relative poses T̂_{i+1,i} of successive frames by weighted Kabsch on their shared points.

    For each i the points j observed in both frames i and i+1 give the correspondences
    X_ij ↔ X_{i+1,j}; T̂_{i+1,i} minimizes Σ_j w_j ‖X_{i+1,j} − T X_ij‖² (closed form of
    :mod:`torchslam.alignment`), with the pair weight w_j = w_ij w_{i+1,j} / (w_ij + w_{i+1,j})
    (the inverse of the summed variances when weights are inverse variances).

    Fallback: where two successive frames share fewer than 3 points with positive weight, or
    their shared points are collinear (the rotation is not unique), T̂_{i+1,i} = I and one
    ``UserWarning`` lists the problems and frames concerned. The chained poses after such a
    pair are then only as good as that guess; the solver has to recover them.

    Args:
        pose_index: frame i of each observation, int64, shape (B, E).
        point_index: point j of each observation, int64, shape (B, E).
        observations: X_ij in frame i, shape (B, E, 3).
        num_poses: m ≥ 2, the number of frames (frame 0 included).
        valid: bool mask, shape (B, E); False entries are padding. ``None``: all valid.
        weights: non-negative weights, shape (B, E). ``None``: all 1.

    Returns:
        T̂_{i+1,i} for i = 0 … m−2, shape (B, m−1, 4, 4), dtype/device of ``observations``.
    """
    fn = "relative_poses_kabsch"
    valid, weights = _check_edges(
        fn, pose_index, point_index, observations, valid, weights, num_poses, None
    )
    relative, fallback = _relative_poses_kabsch(
        pose_index, point_index, observations, valid, weights, num_poses
    )
    _warn_fallback(fallback)
    return relative


def odometry_relative_poses(
    poses_gt: Tensor,
    *,
    rotation_noise_deg: float,
    translation_noise: float,
    seed: int = 0,
) -> Tensor:
    """Noisy odometry: ground-truth relative poses, each off by an exact, known amount.

    An odometer reports the motion from frame i to frame i+1, T_{i,i+1} = T_i0 T_{i+1,0}⁻¹
    (the pose of frame i+1 in frame i); here it is perturbed on the right,
    T̂_{i,i+1} = T_{i,i+1} · E_i with E_i = [[Exp(θ a_i), τ b_i], [0, 1]], θ =
    ``rotation_noise_deg`` (in radians), τ = ``translation_noise`` and a_i, b_i independent
    uniformly random unit vectors; the function returns T̂_{i+1,i} = T̂_{i,i+1}⁻¹ =
    E_i⁻¹ T_{i+1,i}. So the relative pose error of every step
    (:func:`torchslam.metrics.relative_pose_error`, Sturm et al. 2012) is exactly θ in rotation
    and τ in translation. Chained, the rotation error of frame k performs a random walk on
    SO(3): about θ√k after k steps, never more than kθ (the angle is a bi-invariant metric).
    E.g. θ = 5° over 50 frames typically gives a few tens of degrees of accumulated drift.

    Args:
        poses_gt: ground-truth T_i0, shape (..., m, 4, 4), m ≥ 2.
        rotation_noise_deg: rotation error per step in degrees, ≥ 0.
        translation_noise: translation error per step (scene units, metres), ≥ 0.
        seed: seed of the CPU generator the directions are drawn from (float64, then cast),
            so a seed gives the same perturbations on every device and dtype.

    Returns:
        T̂_{i+1,i} for i = 0 … m−2, shape (..., m−1, 4, 4), dtype/device of ``poses_gt``.
    """
    fn = "odometry_relative_poses"
    _checks.check_tensor(fn, "poses_gt", poses_gt, (4, 4))
    if poses_gt.dim() < 3 or poses_gt.shape[-3] < 2:
        raise ValueError(
            f"{fn}: argument 'poses_gt' must have shape (..., m, 4, 4) with m >= 2, got "
            f"{tuple(poses_gt.shape)}"
        )
    _checks.check_pose_matrix(fn, "poses_gt", poses_gt)
    _check_noise(fn, rotation_noise_deg, translation_noise, seed)
    # T_{i,i+1} = T_i0 T_{i+1,0}⁻¹, the motion from frame i to frame i+1.
    motion = poses_gt[..., :-1, :, :] @ se3.inverse(poses_gt[..., 1:, :, :])
    shape = motion.shape[:-2]
    gen = torch.Generator().manual_seed(seed)
    directions = torch.randn(*shape, 2, 3, generator=gen, dtype=torch.float64)
    directions = directions / directions.norm(dim=-1, keepdim=True)
    omega = math.radians(rotation_noise_deg) * directions[..., 0, :]
    t = translation_noise * directions[..., 1, :]
    error = se3.from_rotation_translation(so3.exp(omega), t)
    noisy_motion = motion @ error.to(dtype=poses_gt.dtype, device=poses_gt.device)
    return se3.inverse(noisy_motion)


def chain_relative_poses(relative_poses: Tensor) -> Tensor:
    """Chain relative poses from the origin: T̂_00 = I, T̂_{i+1,0} = T̂_{i+1,i} T̂_{i0}.

    Equivalently T̂_0i = T̂_01 T̂_12 ⋯ T̂_{i-1,i} (the seed's chaining, inverted).

    Args:
        relative_poses: T̂_{i+1,i} for i = 0 … m−2, shape (..., m−1, 4, 4).

    Returns:
        T̂_i0 for i = 0 … m−1, shape (..., m, 4, 4), with an exact identity at i = 0.
    """
    fn = "chain_relative_poses"
    _checks.check_tensor(fn, "relative_poses", relative_poses, (4, 4))
    if relative_poses.dim() < 3:
        raise ValueError(
            f"{fn}: argument 'relative_poses' must have shape (..., m-1, 4, 4), got "
            f"{tuple(relative_poses.shape)}"
        )
    _checks.check_pose_matrix(fn, "relative_poses", relative_poses)
    identity = torch.eye(4, dtype=relative_poses.dtype, device=relative_poses.device)
    chained = [identity.expand(*relative_poses.shape[:-3], 4, 4)]
    for i in range(relative_poses.shape[-3]):
        chained.append(relative_poses[..., i, :, :] @ chained[-1])
    return torch.stack(chained, dim=-3)


def average_points(
    poses: Tensor,
    pose_index: Tensor,
    point_index: Tensor,
    observations: Tensor,
    num_points: int,
    *,
    valid: Tensor | None = None,
    weights: Tensor | None = None,
) -> Tensor:
    """World points as the weighted mean of their views mapped to frame 0 (seed eq. 0.2).

    X̂_j = Σ_i w_ij T̂_i0⁻¹ X_ij / Σ_i w_ij over the observations of j (the seed's plain mean
    when ``weights`` is None).

    A point with no valid observation of positive weight is set to 0 and reported in one
    ``UserWarning`` (problem and point indices); nothing is dropped silently.

    Args:
        poses: T̂_i0, shape (B, m, 4, 4).
        pose_index: frame i of each observation, int64, shape (B, E).
        point_index: point j of each observation, int64, shape (B, E).
        observations: X_ij in frame i, shape (B, E, 3).
        num_points: n ≥ 1, the number of points.
        valid: bool mask, shape (B, E); False entries are padding. ``None``: all valid.
        weights: non-negative weights, shape (B, E). ``None``: all 1.

    Returns:
        X̂_j, shape (B, n, 3), dtype/device of ``observations``.
    """
    fn = "average_points"
    _checks.check_tensor(fn, "poses", poses, (4, 4))
    if poses.dim() != 4 or poses.shape[0] != pose_index.shape[0]:
        raise ValueError(
            f"{fn}: argument 'poses' must have shape (B, m, 4, 4) with B = "
            f"{pose_index.shape[0] if pose_index.dim() > 0 else '?'} (from 'pose_index'), "
            f"got {tuple(poses.shape)}"
        )
    _checks.check_same_kind(fn, observations=observations, poses=poses)
    valid, weights = _check_edges(
        fn, pose_index, point_index, observations, valid, weights, poses.shape[1], num_points
    )
    _checks.check_pose_matrix(fn, "poses", poses)
    if _checks.value_checks_active():
        # Extra poses no observation refers to mean 'poses' does not belong to these edges.
        used = torch.zeros(poses.shape[1], dtype=torch.bool, device=pose_index.device)
        used[pose_index[valid]] = True
        if not bool(used.all()):
            unused = (~used).nonzero().flatten().tolist()
            raise ValueError(
                f"{fn}: argument 'poses' has m = {poses.shape[1]} frames but no valid "
                f"observation refers to frame(s) {unused[:_MAX_LISTED]}: it does not match "
                "'pose_index' (pass the poses of the observed frames)"
            )
    points, count = _average_points(
        poses, pose_index, point_index, observations, valid, weights, num_points
    )
    _warn_unobserved(count)
    return points


def initialize(
    pose_index: Tensor,
    point_index: Tensor,
    observations: Tensor,
    num_poses: int,
    num_points: int,
    *,
    valid: Tensor | None = None,
    weights: Tensor | None = None,
    relative_poses: Tensor | None = None,
) -> Initialization:
    """Initial poses and points of B problems, the seed's section 0 end to end.

    Relative poses T̂_{i+1,i} from ``relative_poses`` (e.g. odometry) or, when None, from
    :func:`relative_poses_kabsch` (with its identity fallback and warning); chained by
    :func:`chain_relative_poses`; points by :func:`average_points` (seed eq. 0.2).

    Args:
        pose_index: frame i of each observation, int64, shape (B, E).
        point_index: point j of each observation, int64, shape (B, E).
        observations: X_ij in frame i, shape (B, E, 3).
        num_poses: m ≥ 2.
        num_points: n ≥ 1.
        valid: bool mask, shape (B, E); False entries are padding. ``None``: all valid.
        weights: non-negative weights, shape (B, E). ``None``: all 1.
        relative_poses: given T̂_{i+1,i}, shape (B, m−1, 4, 4); ``None`` to align.

    Returns:
        The :class:`Initialization`.
    """
    fn = "initialize"
    valid, weights = _check_edges(
        fn, pose_index, point_index, observations, valid, weights, num_poses, num_points
    )
    B = pose_index.shape[0]
    if relative_poses is None:
        relative, fallback = _relative_poses_kabsch(
            pose_index, point_index, observations, valid, weights, num_poses
        )
        _warn_fallback(fallback)
    else:
        _checks.check_tensor(fn, "relative_poses", relative_poses, (4, 4))
        _checks.check_same_kind(fn, observations=observations, relative_poses=relative_poses)
        if tuple(relative_poses.shape) != (B, num_poses - 1, 4, 4):
            raise ValueError(
                f"{fn}: argument 'relative_poses' must have shape (B, m-1, 4, 4) = "
                f"{(B, num_poses - 1, 4, 4)}, got {tuple(relative_poses.shape)}"
            )
        _checks.check_pose_matrix(fn, "relative_poses", relative_poses)
        relative = relative_poses
        fallback = torch.zeros(B, num_poses - 1, dtype=torch.bool, device=observations.device)
    poses = chain_relative_poses(relative)
    points, count = _average_points(
        poses, pose_index, point_index, observations, valid, weights, num_points
    )
    _warn_unobserved(count)
    return Initialization(poses=poses, points=points, relative_poses=relative, fallback=fallback)


def initialize_scene(
    scene: SyntheticScene,
    *,
    method: Literal["kabsch", "odometry"] = "kabsch",
    rotation_noise_deg: float = 5.0,
    translation_noise: float = 0.05,
    seed: int = 0,
) -> Initialization:
    """Initialize a synthetic scene: Kabsch chaining, or drifted odometry from its ground truth.

    ``method="odometry"`` chains :func:`odometry_relative_poses` of ``scene.poses_gt`` (each
    step off by exactly ``rotation_noise_deg`` and ``translation_noise``; ``seed`` picks the
    directions) — the drifted start of the solver tests; ``"kabsch"`` ignores the three noise
    arguments. Points always come from seed eq. 0.2 with the chained poses.

    Args:
        scene: a :class:`torchslam.data.SyntheticScene`.
        method: ``"kabsch"`` or ``"odometry"``.
        rotation_noise_deg: odometry rotation error per step (degrees).
        translation_noise: odometry translation error per step (metres).
        seed: odometry seed.

    Returns:
        The :class:`Initialization`.
    """
    from torchslam.data.synthetic import SyntheticScene

    fn = "initialize_scene"
    if not isinstance(scene, SyntheticScene):
        hint = "; pass its .scene" if hasattr(scene, "scene") else ""
        raise TypeError(
            f"{fn}: argument 'scene' must be a torchslam.data.SyntheticScene, "
            f"got {_checks.describe(scene)}{hint}"
        )
    if method not in ("kabsch", "odometry"):
        raise ValueError(f"{fn}: argument 'method' must be 'kabsch' or 'odometry', got {method!r}")
    _check_noise(fn, rotation_noise_deg, translation_noise, seed)
    if method == "kabsch":
        relative = None
    elif method == "odometry":
        relative = odometry_relative_poses(
            scene.poses_gt,
            rotation_noise_deg=rotation_noise_deg,
            translation_noise=translation_noise,
            seed=seed,
        )
    else:
        raise ValueError(
            f"initialize_scene: argument 'method' must be 'kabsch' or 'odometry', got {method!r}"
        )
    return initialize(
        scene.pose_index,
        scene.point_index,
        scene.observations,
        scene.num_poses,
        scene.num_points,
        valid=scene.valid,
        relative_poses=relative,
    )


def _check_noise(fn: str, rotation_noise_deg: float, translation_noise: float, seed: int) -> None:
    """The odometry noise amounts (finite, ≥ 0) and seed of ``fn``."""
    for name, value in (
        ("rotation_noise_deg", rotation_noise_deg),
        ("translation_noise", translation_noise),
    ):
        try:  # TypeError for a non-number; ValueError (reworded here) for NaN, Inf, < 0
            _checks.check_real(fn, name, value, low=0)
        except ValueError:
            raise ValueError(
                f"{fn}: argument '{name}' must be finite and >= 0, got {value!r}"
            ) from None
    _checks.check_seed(fn, seed)


def _check_edges(
    fn: str,
    pose_index: Tensor,
    point_index: Tensor,
    observations: Tensor,
    valid: Tensor | None,
    weights: Tensor | None,
    num_poses: int,
    num_points: int | None,
) -> tuple[Tensor, Tensor]:
    """Check the padded edge lists; return (valid, weights) with the defaults filled in."""
    for name, x in (("pose_index", pose_index), ("point_index", point_index)):
        _checks.check_tensor(fn, name, x, (), floating=False)
        if x.dtype != torch.long:
            raise TypeError(f"{fn}: argument '{name}' must be int64 (torch.long), got {x.dtype}")
        if x.dim() != 2:
            raise ValueError(
                f"{fn}: argument '{name}' must have shape (B, E), got {tuple(x.shape)}"
            )
    if pose_index.shape != point_index.shape:
        raise ValueError(
            f"{fn}: 'pose_index' and 'point_index' must have the same shape (B, E), got "
            f"{tuple(pose_index.shape)} and {tuple(point_index.shape)}"
        )
    B, E = pose_index.shape
    _checks.check_tensor(fn, "observations", observations, (3,))
    if tuple(observations.shape) != (B, E, 3):
        raise ValueError(
            f"{fn}: argument 'observations' must have shape (B, E, 3) = {(B, E, 3)} (from "
            f"'pose_index'), got {tuple(observations.shape)}"
        )
    if valid is None:
        valid = torch.ones(B, E, dtype=torch.bool, device=observations.device)
    else:
        _checks.check_tensor(fn, "valid", valid, (), floating=False)
        if valid.dtype != torch.bool:
            raise TypeError(f"{fn}: argument 'valid' must be a bool tensor, got {valid.dtype}")
        if tuple(valid.shape) != (B, E):
            raise ValueError(
                f"{fn}: argument 'valid' must have shape (B, E) = {(B, E)}, got "
                f"{tuple(valid.shape)}"
            )
    if weights is None:
        weights = observations.new_ones(B, E)
    else:
        _checks.check_tensor(fn, "weights", weights, ())
        _checks.check_same_kind(fn, observations=observations, weights=weights)
        if tuple(weights.shape) != (B, E):
            raise ValueError(
                f"{fn}: argument 'weights' must have shape (B, E) = {(B, E)}, got "
                f"{tuple(weights.shape)}"
            )
    for name, value, minimum in (("num_poses", num_poses, 2), ("num_points", num_points, 1)):
        if value is not None:
            _checks.check_int(fn, name, value, minimum=minimum)
    if _checks.value_checks_active():
        for name, x, bound in (
            ("pose_index", pose_index, num_poses),
            ("point_index", point_index, num_points),
        ):
            bad = valid & ((x < 0) | (x >= bound if bound is not None else False))
            if bool(bad.any()):
                b, e = (int(i) for i in bad.nonzero()[0])
                raise ValueError(
                    f"{fn}: {name}[{b}, {e}] = {int(x[b, e])} is out of range "
                    f"[0, {bound}) (problem {b}, observation {e})"
                )
        zero = torch.zeros_like(observations)
        _checks.check_finite(fn, "observations", torch.where(valid[..., None], observations, zero))
        _checks.check_finite(fn, "weights", torch.where(valid, weights, torch.zeros_like(weights)))
        negative = valid & (weights < 0)
        if bool(negative.any()):
            b, e = (int(i) for i in negative.nonzero()[0])
            raise ValueError(
                f"{fn}: argument 'weights' must be >= 0, got {float(weights[b, e])} at [{b}, {e}]"
            )
    return valid, weights


def _relative_poses_kabsch(
    pose_index: Tensor,
    point_index: Tensor,
    observations: Tensor,
    valid: Tensor,
    weights: Tensor,
    num_poses: int,
) -> tuple[Tensor, Tensor]:
    """Unchecked core of :func:`relative_poses_kabsch`: (T̂_{i+1,i} (B, m-1, 4, 4), fallback)."""
    B, E = pose_index.shape
    m = num_poses
    num_segments = B * (m - 1)
    dtype, device = observations.dtype, observations.device
    # Sort each problem's edges by (point, pose): the two views of a point in frames i and
    # i+1 become neighbours. Padding sorts last.
    key = (point_index * m + pose_index).masked_fill(~valid, torch.iinfo(torch.long).max)
    order = key.argsort(dim=-1)
    point = point_index.gather(-1, order)
    pose = pose_index.gather(-1, order)
    keep = valid.gather(-1, order)
    w = torch.where(keep, weights.gather(-1, order), torch.zeros_like(weights))
    X = observations.gather(1, order[..., None].expand(B, E, 3))
    X = torch.where(keep[..., None], X, torch.zeros_like(X))

    # Pairs of neighbours (k, k+1): same point, frames i and i+1. Static shapes (B, E-1).
    pair = keep[:, :-1] & keep[:, 1:] & (point[:, 1:] == point[:, :-1])
    pair &= pose[:, 1:] == pose[:, :-1] + 1
    w_a, w_b = w[:, :-1], w[:, 1:]
    w_sum = w_a + w_b
    w_pair = torch.where(
        pair & (w_sum > 0), w_a * w_b / torch.where(w_sum > 0, w_sum, torch.ones_like(w_sum)), 0
    )
    frame = torch.where(pair, pose[:, :-1], torch.zeros_like(pose[:, :-1]))
    batch = torch.arange(B, device=device)[:, None]
    segment = (batch * (m - 1) + frame.clamp(max=m - 2)).reshape(-1)
    w_pair = w_pair.reshape(-1)
    source = X[:, :-1].reshape(-1, 3)
    target = X[:, 1:].reshape(-1, 3)

    # Segment sums: weighted centroids, then the centred cross-covariance (two passes).
    total = observations.new_zeros(num_segments).index_add_(0, segment, w_pair)
    count = observations.new_zeros(num_segments).index_add_(0, segment, (w_pair > 0).to(dtype))
    total_safe = torch.where(total > 0, total, torch.ones_like(total))[:, None]
    mu_s = observations.new_zeros(num_segments, 3).index_add_(0, segment, w_pair[:, None] * source)
    mu_t = observations.new_zeros(num_segments, 3).index_add_(0, segment, w_pair[:, None] * target)
    mu_s, mu_t = mu_s / total_safe, mu_t / total_safe
    s_c = source - mu_s[segment]
    t_c = target - mu_t[segment]
    outer = (w_pair[:, None, None] * s_c[:, :, None]) * t_c[:, None, :]
    H = observations.new_zeros(num_segments, 3, 3).index_add_(0, segment, outer)

    too_few = count < _MIN_SHARED
    # Keep the SVD (and its backward) away from the zero covariance of an empty pair.
    H_safe = torch.diag(torch.tensor([3.0, 2.0, 1.0], dtype=dtype, device=device))
    H = torch.where(too_few[:, None, None], H_safe, H)
    T, singular_values = _rigid_from_covariance(H, mu_s, mu_t)
    fallback = too_few | _degenerate_spectrum(singular_values.detach())
    identity = torch.eye(4, dtype=dtype, device=device)
    T = torch.where(fallback[:, None, None], identity, T)
    return T.reshape(B, m - 1, 4, 4), fallback.reshape(B, m - 1)


def _average_points(
    poses: Tensor,
    pose_index: Tensor,
    point_index: Tensor,
    observations: Tensor,
    valid: Tensor,
    weights: Tensor,
    num_points: int,
) -> tuple[Tensor, Tensor]:
    """Unchecked core of :func:`average_points`: (X̂ (B, n, 3), total weight (B, n))."""
    B, E = pose_index.shape
    # Padding may hold any index: point it at 0 (its weight is 0).
    pose_index = torch.where(valid, pose_index, torch.zeros_like(pose_index))
    point_index = torch.where(valid, point_index, torch.zeros_like(point_index))
    world_from_frame = se3.inverse(poses)  # T̂_0i
    index = pose_index[..., None, None].expand(B, E, 4, 4)
    T = world_from_frame.gather(1, index)
    X = torch.where(valid[..., None], observations, torch.zeros_like(observations))
    w = torch.where(valid, weights, torch.zeros_like(weights))
    in_world = (T[..., :3, :3] @ X[..., None]).squeeze(-1) + T[..., :3, 3]
    sums = observations.new_zeros(B, num_points, 3).scatter_add_(
        1, point_index[..., None].expand(B, E, 3), w[..., None] * in_world
    )
    total = observations.new_zeros(B, num_points).scatter_add_(1, point_index, w)
    points = sums / torch.where(total > 0, total, torch.ones_like(total))[..., None]
    return points, total


def _format_pairs(pairs: Tensor) -> str:
    listed = ", ".join(f"({int(b)}, {int(i)})" for b, i in pairs[:_MAX_LISTED].tolist())
    more = pairs.shape[0] - _MAX_LISTED
    return listed + (f" and {more} more" if more > 0 else "")


def _warn_fallback(fallback: Tensor) -> None:
    if not bool(fallback.any()):
        return
    pairs = fallback.nonzero()
    details = "; ".join(
        f"problem {b}: frames {i} and {i + 1}" for b, i in pairs[:_MAX_LISTED].tolist()
    )
    more = pairs.shape[0] - _MAX_LISTED
    warnings.warn(
        f"relative_poses_kabsch: {pairs.shape[0]} pair(s) of successive frames share fewer "
        f"than {_MIN_SHARED} points with positive weight or only collinear ones, so their "
        f"relative pose T̂_(i+1,i) is set to the identity: {details}"
        + (f"; and {more} more" if more > 0 else ""),
        UserWarning,
        stacklevel=3,
    )


def _warn_unobserved(total: Tensor) -> None:
    unobserved = total <= 0
    if not bool(unobserved.any()):
        return
    pairs = unobserved.nonzero()
    warnings.warn(
        f"average_points: {pairs.shape[0]} point(s) have no valid observation with positive "
        "weight, so their initial position is set to 0; (problem, point): " + _format_pairs(pairs),
        UserWarning,
        stacklevel=3,
    )
