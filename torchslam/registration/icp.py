"""ICP front end: pairwise ICP (point-to-point, point-to-plane), multistart, pose chaining.

The pairwise alignment of the seed's section 0: for successive frames, ICP estimates the
relative pose T̂ that maps the source cloud into the target frame (p' = R p + t), and chaining
the relative poses gives the initial T̂_0i = T̂_01 T̂_12 ⋯ T̂_(i−1,i) of seed eq. (0.1).

Point-to-point ICP alternates nearest-neighbour correspondences (a KD-tree, never an O(N·M)
distance matrix) with the closed-form weighted Kabsch solution
(:func:`torchslam.alignment.weighted_kabsch`). Outliers and non-overlapping parts are handled
by a distance gate that shrinks with the inlier RMS error and by trimming (keeping only the
best fraction of the gated correspondences, as in trimmed ICP). Point-to-plane ICP minimizes
Σ (n_q · (R p + t − q))² with target normals from PCA over k nearest neighbours.

Several initial guesses are run together as one batch (one KD-tree query and one batched
Kabsch per iteration for all of them); :func:`icp_multistart` keeps the one with the best
fitness. The ICP loop runs on the host (a KD-tree); it is not meant for jacrev or vmap.
Near convergence most points skip the KD-tree: a point that moved less than half the gap
between its nearest and second-nearest target point keeps its nearest one, which is then
certain (``neighbors._Matcher``); the correspondences are those of a full query.

Voxel grids, nearest neighbours and normals live in :mod:`torchslam.registration.neighbors`;
:func:`voxel_downsample`, :func:`nearest_neighbors` and :func:`estimate_normals` are also
importable from here.
"""

from __future__ import annotations

import contextlib
import enum
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from torchslam import _checks, _inference
from torchslam.alignment import weighted_kabsch
from torchslam.lie import _series, convert, se3, so3
from torchslam.losses import CauchyLoss, HuberLoss, TukeyLoss
from torchslam.registration.kdtree import KDTree
from torchslam.registration.neighbors import (
    _WORKERS,
    _downsample,
    _host,
    _Matcher,
    _normals,
    _query,
    _tree,
    estimate_normals,
    nearest_neighbors,
    query_workers,
    voxel_downsample,
)

__all__ = [
    "ICPConfig",
    "ICPResult",
    "ICPStatus",
    "Stage",
    "chain_poses",
    "estimate_normals",
    "icp",
    "icp_batch",
    "icp_multistart",
    "initial_guesses",
    "nearest_neighbors",
    "query_workers",
    "register_coarse_to_fine",
    "rotations_about_axis",
    "rotations_uniform",
    "voxel_downsample",
]


# ----------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class ICPConfig:
    """Options of :func:`icp`. Distances are in the units of the clouds (metres for the bunny).

    The gate of iteration k is g_k = clamp(gate_scale · rms_(k−1), min_distance, g_(k−1)),
    starting from g_0 = max_distance: it never grows, and it shrinks with the inlier RMS error.
    Of the gated correspondences, the ``trim_fraction`` with the smallest distances are kept.
    """

    # "point_to_point" (closed-form weighted Kabsch) or "point_to_plane" (needs target normals)
    method: Literal["point_to_point", "point_to_plane"] = "point_to_point"
    # upper bound on the number of pose updates
    max_iterations: int = 50
    # converged when rms_(k−1) − rms_k ≤ relative_tolerance · rms_(k−1) (no real decrease)
    relative_tolerance: float = 1e-6
    # initial correspondence gate g_0; None means no gate
    max_distance: float | None = None
    # floor of the gate, so that it cannot shrink below the noise level
    min_distance: float = 0.0
    # the gate follows gate_scale × inlier RMS; None keeps g_0 fixed
    gate_scale: float | None = 3.0
    # fraction (0, 1] of the gated correspondences kept, those with the smallest distances
    trim_fraction: float = 1.0
    # fewer inlier correspondences than this stops the iteration with a failure status
    min_correspondences: int = 6
    # also converged when an update turns by less than this (degrees) and moves the source
    # centroid by less than translation_tolerance; None: only the RMS test. Saves the pass
    # that would confirm the RMS no longer falls (the statistics are those before the step).
    rotation_tolerance_deg: float | None = None
    translation_tolerance: float | None = None
    # robust kernel on the kept correspondences (iteratively reweighted least squares, besides
    # the trimming): "none", "huber", "cauchy" or "tukey" (:mod:`torchslam.losses`), on the
    # point-to-plane distance (point_to_plane) or the point distance (point_to_point)
    kernel: Literal["none", "huber", "cauchy", "tukey"] = "none"
    # its scale, in the clouds' units; None: the inlier RMS of the iteration (scale-free)
    kernel_scale: float | None = None
    # point_to_plane only: turn the source about its own origin (the sensor, placed by T)
    # and keep T's translation: a coarse stage that a wide gate cannot make slide along the
    # target's weakly constrained directions (odometry's wide stage, rotation mispredicted)
    rotation_only: bool = False
    # point_to_plane only: directions of the update that the correspondences barely constrain
    # stay where T put them (degeneracy-aware ICP; a camera facing a bare wall, a corridor):
    # the eigen-directions of the step's normal equations, rotation scaled by the RMS lever
    # arm (:func:`~torchslam.registration.quality.alignment_quality`'s λ_min/λ_max), whose
    # eigenvalue is below ``degenerate_condition`` × the largest get no update. None: every
    # direction is solved (noise then slides a frame along the weak ones)
    degenerate_condition: float | None = None

    def __post_init__(self) -> None:
        fn = "ICPConfig"
        if not isinstance(self.method, str) or self.method not in (
            "point_to_point",
            "point_to_plane",
        ):
            raise ValueError(
                f"{fn}: unknown method {self.method!r}: argument 'method' must be "
                "'point_to_point' or 'point_to_plane'"
            )
        _checks.check_int(fn, "max_iterations", self.max_iterations, minimum=0)
        _checks.check_real(fn, "relative_tolerance", self.relative_tolerance, low=0.0)
        if self.max_distance is not None:
            _checks.check_real(fn, "max_distance", self.max_distance, low=0.0, low_open=True)
        _checks.check_real(fn, "min_distance", self.min_distance, low=0.0)
        if self.max_distance is not None and self.min_distance > self.max_distance:
            raise ValueError(
                f"{fn}: argument 'min_distance' (the floor of the gate) must be <= "
                f"'max_distance' = {self.max_distance:g}, got {self.min_distance:g}"
            )
        if self.gate_scale is not None:
            _checks.check_real(fn, "gate_scale", self.gate_scale, low=0.0, low_open=True)
        _checks.check_real(
            fn, "trim_fraction", self.trim_fraction, low=0.0, low_open=True, high=1.0
        )
        _checks.check_int(fn, "min_correspondences", self.min_correspondences, minimum=3)
        for name in ("rotation_tolerance_deg", "translation_tolerance"):
            if getattr(self, name) is not None:
                _checks.check_real(fn, name, getattr(self, name), low=0.0)
        if (self.rotation_tolerance_deg is None) != (self.translation_tolerance is None):
            raise ValueError(
                f"{fn}: give both 'rotation_tolerance_deg' and 'translation_tolerance' or neither"
            )
        if not isinstance(self.kernel, str) or self.kernel not in _KERNELS:
            raise ValueError(
                f"{fn}: argument 'kernel' must be one of {', '.join(map(repr, _KERNELS))}, "
                f"got {_checks.describe(self.kernel)}"
            )
        if self.kernel_scale is not None:
            _checks.check_real(fn, "kernel_scale", self.kernel_scale, low=0.0, low_open=True)
        _checks.check_bool(fn, "rotation_only", self.rotation_only)
        if self.degenerate_condition is not None:
            _checks.check_real(
                fn, "degenerate_condition", self.degenerate_condition, low=0.0, high=1.0
            )
            if self.method != "point_to_plane":
                raise ValueError(
                    f"{fn}: argument 'degenerate_condition' needs method='point_to_plane', got "
                    f"method={self.method!r}"
                )
        if self.rotation_only and self.method != "point_to_plane":
            raise ValueError(
                f"{fn}: argument 'rotation_only' needs method='point_to_plane', got "
                f"method={self.method!r}"
            )


_KERNELS = ("none", "huber", "cauchy", "tukey")


# One instance of each kernel: _kernel_weights calls its ρ' on an aligned scale directly.
_KERNEL_TYPES = {"huber": HuberLoss, "cauchy": CauchyLoss, "tukey": TukeyLoss}
_KERNEL_INSTANCES = {name: kind(1.0) for name, kind in _KERNEL_TYPES.items()}


def _kernel_weights(kernel: str, residual: Tensor, scale: Tensor) -> Tensor:
    """IRLS weights ρ'(r²) of a robust kernel, residual (B, N), scale (B,) > 0: the kernel's
    ``weight(r², scale)`` bit for bit (the same ρ' on the same clamped scale), without its
    argument checks (both come from the loop, finite by construction), which cost as much as
    the weights on one frame."""
    info = torch.finfo(residual.dtype)
    aligned = scale.clamp(info.tiny, info.max)[:, None]
    return _KERNEL_INSTANCES[kernel]._weight_scaled(residual * residual, aligned)


class ICPStatus(enum.IntEnum):
    """Why an ICP run stopped."""

    RUNNING = 0
    CONVERGED = 1
    MAX_ITERATIONS = 2
    TOO_FEW_CORRESPONDENCES = 3


_REASONS = {
    ICPStatus.RUNNING: "not finished",
    ICPStatus.CONVERGED: "relative decrease of the RMS error below tolerance",
    ICPStatus.MAX_ITERATIONS: "maximum number of iterations reached",
    ICPStatus.TOO_FEW_CORRESPONDENCES: "too few correspondences within the gate",
}


@dataclass
class ICPResult:
    """Result of ICP for one or a batch of initial guesses (batch shape ``(...)``).

    For a single run (``icp``) the batch shape is ``()`` and :attr:`reason` is one string.
    """

    # T mapping source points into the target frame, target ≈ R source + t, shape (..., 4, 4)
    transform: Tensor
    # RMS distance over the inlier correspondences at the final transform, shape (...)
    rms: Tensor
    # fraction of source points that are inliers (gated and kept) at the final transform
    fitness: Tensor
    # correspondence gate in force at the end, shape (...) (inf when ungated)
    gate: Tensor
    # number of pose updates performed, int64, shape (...)
    iterations: Tensor
    # ICPStatus values, int64, shape (...)
    status: Tensor
    # inlier RMS before each update, one row per iteration, shape (iterations + 1, ...)
    history: Tensor = field(repr=False)

    @property
    def converged(self) -> Tensor:
        """True where the relative decrease of the RMS error fell below tolerance, shape (...)."""
        return self.status == ICPStatus.CONVERGED

    @property
    def reason(self) -> str | list[str]:
        """Why each run stopped: a string for a single run, a flat list for a batch."""
        codes = [ICPStatus(int(c)) for c in self.status.reshape(-1)]
        if self.status.dim() == 0:
            return _REASONS[codes[0]]
        return [_REASONS[c] for c in codes]

    @property
    def status_name(self) -> str | list[str]:
        """:class:`ICPStatus` names, e.g. ``"CONVERGED"``: a string for a single run, a flat
        list for a batch."""
        names = [ICPStatus(int(c)).name for c in self.status.reshape(-1)]
        return names[0] if self.status.dim() == 0 else names

    def __repr__(self) -> str:
        if self.status.dim() == 0:
            return (
                f"ICPResult(status={self.status_name}, iterations={int(self.iterations)}, "
                f"rms={float(self.rms):.6g}, fitness={float(self.fitness):.4g}, "
                f"gate={float(self.gate):.6g}, transform={self.transform!r})"
            )
        counts: dict[str, int] = {}
        for name in self.status_name:
            counts[name] = counts.get(name, 0) + 1
        return (
            f"ICPResult(batch_shape={tuple(self.status.shape)}, status={counts}, "
            f"iterations≤{int(self.iterations.max()) if self.iterations.numel() else 0}, "
            f"best rms={float(self.rms.min()) if self.rms.numel() else math.nan:.6g})"
        )

    def __getitem__(self, index: int) -> ICPResult:
        """The result of one batch entry (batch shape (B,) → ())."""
        return ICPResult(
            self.transform[index],
            self.rms[index],
            self.fitness[index],
            self.gate[index],
            self.iterations[index],
            self.status[index],
            self.history[:, index],
        )


# ----------------------------------------------------------------------------- ICP


def _clouds(
    fn: str, source: object, target: object, *, min_points: int = 3, finite: bool | None = True
) -> tuple[Tensor, Tensor]:
    """``source`` and ``target`` as (N, 3) tensors of one dtype and device (numpy accepted)."""
    like = _checks.first_tensor(source, target)
    source = _checks.as_points(
        fn, "source", source, like=like, min_points=min_points, finite=finite
    )
    target = _checks.as_points(
        fn, "target", target, like=like, min_points=min_points, finite=finite
    )
    _checks.check_same_kind(fn, source=source, target=target)
    return source, target


def _check_config(fn: str, config: object) -> ICPConfig:
    if config is None:
        return ICPConfig()
    if not isinstance(config, ICPConfig):
        raise TypeError(
            f"{fn}: argument 'config' must be an ICPConfig or None, got {_checks.describe(config)}"
        )
    return config


def _check_initial(fn: str, initial: object, like: Tensor, *, allow_empty: bool) -> Tensor:
    """Initial guesses, shape (B, 4, 4), rigid and finite (always: the loop runs on the host)."""
    _checks.check_tensor(fn, "initial", initial, (4, 4))
    assert isinstance(initial, Tensor)
    if initial.dim() != 3 or (initial.shape[0] == 0 and not allow_empty):
        at_least = "" if allow_empty else " with B ≥ 1"
        raise ValueError(
            f"{fn}: argument 'initial' must have shape (B, 4, 4){at_least}, got "
            f"{tuple(initial.shape)}"
        )
    _checks.check_same_kind(fn, source=like, initial=initial)
    if not bool(torch.isfinite(initial.detach()).all()):
        raise ValueError(f"{fn}: argument 'initial' contains non-finite values (NaN or Inf)")
    _checks.check_pose_matrix(fn, "initial", initial)
    return initial


def _check_normals(fn: str, normals: object, target: Tensor, method: str) -> Tensor | None:
    if normals is None:
        if method == "point_to_plane":
            raise ValueError(
                f"{fn}: method 'point_to_plane' needs 'target_normals' (see estimate_normals)"
            )
        return None
    normals = _checks.as_points(
        fn, "target_normals", normals, like=target, cloud=False, finite=True
    )
    if normals.shape != target.shape:
        raise ValueError(
            f"{fn}: 'target_normals' must have the shape of 'target' {tuple(target.shape)}, "
            f"got {tuple(normals.shape)}"
        )
    _checks.check_same_kind(fn, target=target, target_normals=normals)
    return normals


def _prepare(
    fn: str,
    source: object,
    target: object,
    initial: object,
    config: object,
    target_normals: object,
    *,
    allow_empty: bool = False,
) -> tuple[Tensor, Tensor, Tensor, ICPConfig, Tensor | None]:
    """The checked arguments of the ICP entry points (errors name ``fn``)."""
    config = _check_config(fn, config)
    source, target = _clouds(fn, source, target)
    if initial is None:
        initial = se3.identity(dtype=source.dtype, device=source.device)[None]
    initial = _check_initial(fn, initial, source, allow_empty=allow_empty)
    normals = _check_normals(fn, target_normals, target, config.method)
    return source, target, initial, config, normals


def _move(T: Tensor, points: Tensor) -> Tensor:
    """R p + t for every pose and point: T (B, 4, 4), points (N, 3) → (B, N, 3)."""
    return points @ T[:, :3, :3].transpose(-1, -2) + T[:, None, :3, 3]


def _inlier_mask(distance: Tensor, gate: Tensor, trim_fraction: float) -> Tensor:
    """Gated (distance ≤ gate) and trimmed (smallest fraction) correspondences, (B, N)."""
    gated = distance <= gate[:, None]
    if trim_fraction >= 1.0:
        return gated
    masked = torch.where(gated, distance, torch.full_like(distance, math.inf))
    keep = torch.ceil(gated.sum(-1).to(distance.dtype) * trim_fraction).to(torch.int64)
    position = (keep - 1).clamp_min(0)
    if distance.shape[0] == 1:  # one run: a selection, O(N), instead of a sort
        threshold = torch.kthvalue(masked, int(position[0]) + 1, dim=-1, keepdim=True).values
    else:
        ordered, _ = masked.sort(dim=-1)
        threshold = ordered.gather(-1, position[:, None])
    return gated & (distance <= threshold) & (keep[:, None] > 0)


def _point_to_plane_step(
    moved: Tensor,
    matched: Tensor,
    normals: Tensor,
    mask: Tensor,
    weights: Tensor | None = None,
    residual: Tensor | None = None,
    pivot: Tensor | None = None,
    degenerate: float | None = None,
) -> Tensor:
    """Increment ΔT minimizing Σ (n · (ΔT p − q))² to first order over the kept pairs, (B, 4, 4).

    ΔT = exp(δ) about the centroid c of the kept points (for conditioning), δ = (ω, v): with
    p' ≈ p + ω × (p − c) + v, r = n·(p − q) + ((p − c) × n)·ω + n·v, so J = [(p − c) × n, n]
    and δ solves the Gauss–Newton normal equations JᵀJ δ = −Jᵀ r. ``residual``: the
    distances n·(p − q), (B, N), when the caller has them (:func:`_plane_distances`).
    ``pivot`` (B, 3): turn about this point only (v = 0, J = [(p − pivot) × n]).
    ``degenerate``: ICPConfig.degenerate_condition (:func:`_weak_directions_kept`).
    """
    w = mask.to(moved.dtype)  # (B, N)
    if pivot is None:
        count = w.sum(-1, keepdim=True).clamp_min(1.0)  # (B, 1)
        centroid = (w[:, None, :] @ moved).squeeze(-2) / count  # (B, 3)
    else:
        centroid = pivot
    if weights is not None:
        w = torch.where(mask, weights, torch.zeros_like(weights))
    arm = moved - centroid[:, None]
    if residual is None:
        residual = _plane_distances(moved, matched, normals)
    # [J | r], (B, N, 7) (rotation only: (B, N, 4)): one product gives JᵀWJ and JᵀWr.
    cross = torch.linalg.cross(arm, normals)
    columns = (cross, normals) if pivot is None else (cross,)
    augmented = torch.cat((*columns, residual[..., None]), -1)
    products = (augmented * w[..., None]).transpose(-1, -2) @ augmented  # (B, 7, 7)
    d = augmented.shape[-1] - 1
    H, g = products[:, :d, :d], products[:, :d, d:]
    # A tiny ridge keeps H invertible for degenerate overlaps (a plane leaves 3 directions
    # free; there g vanishes and they stay put). Rows without data get H = I, g = 0.
    eye = _series.constant(f"icp eye {d}", torch.eye(d).tolist, H.dtype, H.device)
    scale = H.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None]
    empty = scale <= 0
    H = torch.where(empty, eye, H + 1e-12 * scale * eye)
    g = torch.where(empty, torch.zeros_like(g), g)
    delta = -torch.linalg.solve(H, g).squeeze(-1)
    if degenerate is not None:
        delta = _weak_directions_kept(delta, H, g, arm, w, degenerate)
    if pivot is not None:
        delta = torch.cat((delta, torch.zeros_like(delta)), -1)  # (ω, v = 0)
    # The θ-power form is the robust one bit for bit within these bounds (se3's docstring) and
    # skips its branches; a Gauss-Newton increment leaves them only on degenerate data.
    fast = float(delta.abs().max()) <= 2.0**20 if delta.numel() else True
    step = se3._exp(delta) if fast else se3._exp_robust(delta)
    # Rotate about the centroid: Trans(c) exp(δ) Trans(−c) (step is exp's fresh tensor).
    step[:, :3, 3] = step[:, :3, 3] + centroid - (step[:, :3, :3] @ centroid[..., None]).squeeze(-1)
    return step


def _weak_directions_kept(
    delta: Tensor, H: Tensor, g: Tensor, arm: Tensor, w: Tensor, condition: float
) -> Tensor:
    """The Gauss–Newton increment ``delta`` (B, d) of H δ = −g (H (B, d, d), g (B, d, 1);
    d = 6, or 3 turning only) with no component along the weak directions of H: in units
    where a rotation moves the points by the weighted RMS lever arm ℓ of ``arm`` (B, N, 3)
    (weights ``w`` (B, N)), H̃ = S H S with S = diag(1/ℓ, 1/ℓ, 1/ℓ, 1, 1, 1); its
    eigen-directions with eigenvalue below ``condition`` × the largest get a zero step
    (solution remapping, Zhang et al. 2016), the others their Gauss–Newton one. Rows
    without a weak direction keep ``delta`` exactly."""
    total = w.sum(-1).clamp_min(torch.finfo(w.dtype).tiny)
    lever = torch.sqrt((w * (arm * arm).sum(-1)).sum(-1) / total).clamp_min(1e-12)  # (B,)
    scale = torch.ones(H.shape[:-1], dtype=H.dtype, device=H.device)  # (B, d)
    scale[:, :3] = 1.0 / lever[:, None]
    Hs = H * scale[:, :, None] * scale[:, None, :]
    values, vectors = torch.linalg.eigh(Hs)
    weak = values < condition * values[:, -1:]  # (B, d), ascending
    if not bool(weak.any()):
        return delta
    inverse = torch.where(weak, torch.zeros_like(values), 1.0 / torch.where(weak, 1.0, values))
    gs = (g.squeeze(-1) * scale)[..., None]  # S g
    remapped = -(vectors @ (inverse[..., None] * (vectors.transpose(-1, -2) @ gs))).squeeze(-1)
    remapped = remapped * scale  # δ = S δ̃
    return torch.where(weak.any(-1, keepdim=True), remapped, delta)


def _plane_distances(moved: Tensor, matched: Tensor, normals: Tensor) -> Tensor:
    """Signed point-to-plane distances n·(p − q), (B, N) from (B, N, 3) each."""
    offset = moved - matched
    return (
        offset[..., 0] * normals[..., 0]
        + offset[..., 1] * normals[..., 1]
        + offset[..., 2] * normals[..., 2]
    )


def icp_batch(
    source: Tensor,
    target: Tensor,
    initial: Tensor,
    config: ICPConfig | None = None,
    target_normals: Tensor | None = None,
) -> ICPResult:
    """ICP from several initial guesses at once (one KD-tree query per iteration for all).

    Each run stops on its own (convergence, max iterations, too few correspondences); the
    loop ends when all have stopped. Runs are independent: the result of one entry equals
    :func:`icp` from that initial guess.

    Args:
        source: cloud to move, shape (N, 3), N ≥ 3, finite; a torch tensor or a numpy array
            (float32/float64; numpy arrays are moved to the device of the tensor arguments).
        target: fixed cloud, shape (M, 3), M ≥ 3, finite, same dtype (no silent promotion:
            mixed float32/float64 is a TypeError) and device.
        initial: initial guesses of T (source → target frame), shape (B, 4, 4), B ≥ 0.
        config: options; ``ICPConfig()`` by default.
        target_normals: unit normals of ``target``, shape (M, 3); required for
            ``method="point_to_plane"`` (see :func:`estimate_normals`).

    Returns:
        :class:`ICPResult` with batch shape (B,) (empty for B = 0).
    """
    fn = "icp_batch"
    source, target, initial, config, normals = _prepare(
        fn, source, target, initial, config, target_normals, allow_empty=True
    )
    return _run(fn, source, target, initial, config, normals)


def _run(
    fn: str,
    source: Tensor,
    target: Tensor,
    initial: Tensor,
    config: ICPConfig,
    target_normals: Tensor | None,
    tree: KDTree | None = None,
    matcher: _Matcher | None = None,
) -> ICPResult:
    """The ICP loop on checked arguments; an empty batch gives an empty result. ``tree``: a
    KD-tree of ``target`` built earlier (a local map registered against frame after frame);
    built here when None. ``matcher``: a fresh :class:`_Matcher` of ``tree`` for this batch
    and source size, made by the caller so that it can reuse the lookups of the last pass
    afterwards (alignment_quality's); made here when None."""
    if initial.shape[0] == 0:
        empty = source.new_zeros(0)
        none = torch.zeros(0, dtype=torch.int64)
        return ICPResult(initial.clone(), empty, empty, empty, none, none, source.new_zeros(1, 0))
    # No input asks for a gradient: the loop runs in inference mode (bit-identical results,
    # ~8 % less time a pass: no autograd bookkeeping on its ~hundreds of small operations a
    # pass), and its tensors leave as normal ones (torchslam._inference.plain).
    tracked = _inference.tracked(source, target, initial, target_normals)
    with _checks.validation(False), _host_threads(), torch.inference_mode(not tracked):
        result = _icp_loop(fn, source, target, initial, config, target_normals, tree, matcher)
    return _inference.plain(result)


@contextlib.contextmanager
def _host_threads() -> Iterator[None]:
    """The KD-tree queries get the caller's torch threads (:func:`query_workers`), the small
    per-iteration tensor algebra one thread: spread over threads that other processes keep
    busy, its OpenMP regions cost far more than they compute (ICP went 4× slower with 2
    threads than with 1 on a shared 2-core machine). The thread count is restored on exit."""
    threads = torch.get_num_threads()
    if threads == 1:
        yield
        return
    _WORKERS.append(threads)
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
        _WORKERS.pop()


def _icp_loop(
    fn: str,
    source: Tensor,
    target: Tensor,
    initial: Tensor,
    config: ICPConfig,
    target_normals: Tensor | None,
    tree: KDTree | None = None,
    matcher: _Matcher | None = None,
) -> ICPResult:
    """One pass per iteration: nearest neighbours (KD-tree lookups on :func:`query_workers`
    threads for the points not certain to keep theirs, :class:`_Matcher`) for the runs still
    going, their inlier statistics, the stop tests and the update. A run that
    stops keeps the correspondences of its last pass (its final statistics need no extra
    query). The per-run bookkeeping (rows still going, statuses, iteration counts, the stop
    tests) is on the host, in numpy: a few numbers per run, which the matcher's host
    lookups synchronize every pass anyway; each would cost a tensor operation or several."""
    batch = initial.shape[0]
    n = source.shape[0]
    if tree is None:
        tree = _tree(fn, "target", target)
    if matcher is None:
        matcher = _Matcher(tree, _host(fn, "target", target), batch, n)
    T = initial.clone()
    infinite = math.inf if config.max_distance is None else config.max_distance
    gate = source.new_full((batch,), infinite)
    running, converged = int(ICPStatus.RUNNING), int(ICPStatus.CONVERGED)
    status = np.full(batch, running, dtype=np.int64)
    iterations = np.zeros(batch, dtype=np.int64)
    # in the source's dtype, so that the relative test below rounds as the RMS does
    previous_rms = source.new_full((batch,), math.inf).cpu().numpy()
    rms_all = source.new_zeros(batch)
    count_all = torch.zeros(batch, dtype=torch.int64, device=source.device)
    history: list[Tensor] = []
    zero = source.new_zeros(())
    rows = np.arange(batch)  # the runs still going, increasing
    picked = torch.arange(batch, device=source.device)  # rows, as an index of the tensors
    centroid = source.mean(0)  # the step tolerances' lever

    while True:
        # Correspondences of the runs still going (rows), at their current transforms.
        whole = len(rows) == batch
        T_rows, gate_rows = (T, gate) if whole else (T[picked], gate[picked])
        moved = _move(T_rows, source)
        distance, index = matcher(rows, moved, gate_rows.cpu().numpy(), fn, "source")
        mask = _inlier_mask(distance, gate_rows, config.trim_fraction)
        count = mask.sum(-1)
        squared = torch.where(mask, distance, zero) ** 2
        rms = torch.sqrt(squared.sum(-1) / count.clamp_min(1).to(source.dtype))
        if whole:
            rms_all.copy_(rms)
            count_all.copy_(count)
        else:
            rms_all[picked] = rms
            count_all[picked] = count
        history.append(rms_all.clone())
        # Stop tests (every row here is running).
        rms_host, count_host = rms.cpu().numpy(), count.cpu().numpy()
        few = count_host < config.min_correspondences
        # Signed: an RMS that went up (noise floor, a flip of the trimmed set) also stops.
        previous = previous_rms[rows]
        settled = np.isfinite(previous) & (
            previous - rms_host <= previous.dtype.type(config.relative_tolerance) * previous
        )
        # An exact fit (rms = 0) needs no update.
        settled = ~few & (settled | (rms_host == 0))
        capped = ~few & ~settled & (iterations[rows] >= config.max_iterations)
        code = np.select(
            (few, settled, capped),
            (int(ICPStatus.TOO_FEW_CORRESPONDENCES), converged, int(ICPStatus.MAX_ITERATIONS)),
            running,
        )
        status[rows] = code
        go = code == running
        if not go.any():
            break
        if not go.all():
            kept = torch.from_numpy(np.flatnonzero(go)).to(source.device)
            rows, rms_host, whole = rows[go], rms_host[go], False
            picked = picked[kept]
            T_rows, gate_rows = T_rows[kept], gate_rows[kept]
            moved, distance, index = moved[kept], distance[kept], index[kept]
            mask, rms = mask[kept], rms[kept]
        # (B, N, 3); unmatched rows are masked out (index_select: the same rows, a fraction of
        # advanced indexing's cost)
        safe_index = index.clamp_min(0).reshape(-1)
        matched = target.index_select(0, safe_index).view(moved.shape)
        weights = step = None
        if config.method == "point_to_point":
            if config.kernel != "none":
                weights = _kernel_weights(
                    config.kernel, distance.nan_to_num(posinf=0.0), _scale(config, rms)
                )
            # Absolute solve from the original source: no drift from composing increments.
            T_new = weighted_kabsch(
                source.expand(len(rows), n, 3), matched, weights=weights, mask=mask
            )
        else:
            assert target_normals is not None
            normals = target_normals.index_select(0, safe_index).view(moved.shape)
            plane = _plane_distances(moved, matched, normals)
            if config.kernel != "none":
                weights = _kernel_weights(config.kernel, plane, _scale(config, rms))
            pivot = T_rows[:, :3, 3] if config.rotation_only else None
            step = _point_to_plane_step(
                moved, matched, normals, mask, weights, plane, pivot, config.degenerate_condition
            )
            T_new = step @ T_rows
        if whole:
            T = T_new  # a fresh tensor; T_rows keeps the transforms before the update
        else:
            T[picked] = T_new
        iterations[rows] += 1
        previous_rms[rows] = rms_host
        if config.gate_scale is not None:
            shrunk = torch.clamp(config.gate_scale * rms, min=config.min_distance)
            gate_new = torch.minimum(gate_rows, shrunk)
            if whole:
                gate = gate_new
            else:
                gate[picked] = gate_new
        if config.rotation_tolerance_deg is not None:
            # The increment: the point-to-plane step, or T_new T⁻¹ of the absolute solve.
            delta = step if step is not None else T_new @ se3.inverse(T_rows)
            small = _small_steps(delta, T_rows, centroid, config).cpu().numpy()
            if small.any():
                status[rows[small]] = converged
                rows = rows[~small]
                picked = torch.from_numpy(rows).to(source.device)
                if len(rows) == 0:
                    break

    fitness = count_all.to(source.dtype) / n
    return ICPResult(
        T,
        rms_all,
        fitness,
        gate,
        torch.from_numpy(iterations),
        torch.from_numpy(status),
        torch.stack(history),
    )


def _small_steps(delta: Tensor, before: Tensor, centroid: Tensor, config: ICPConfig) -> Tensor:
    """Updates ``delta`` (B, 4, 4; the new transform is delta · before) below the step
    tolerances: rotation angle and motion of the source centroid (3,) placed by ``before``."""
    cos = ((delta[:, 0, 0] + delta[:, 1, 1] + delta[:, 2, 2] - 1) / 2).clamp(-1.0, 1.0)
    angle = torch.rad2deg(torch.acos(cos))
    moved = before[:, :3, :3] @ centroid + before[:, :3, 3]
    shift = torch.linalg.vector_norm(
        (delta[:, :3, :3] @ moved[..., None]).squeeze(-1) + delta[:, :3, 3] - moved, dim=-1
    )
    assert config.rotation_tolerance_deg is not None and config.translation_tolerance is not None
    return (angle <= config.rotation_tolerance_deg) & (shift <= config.translation_tolerance)


def _scale(config: ICPConfig, rms: Tensor) -> Tensor:
    """The kernel scale per run: ``config.kernel_scale`` or the inlier RMS (kept > 0)."""
    if config.kernel_scale is not None:
        return torch.full_like(rms, config.kernel_scale)
    tiny = torch.finfo(rms.dtype).tiny ** 0.5
    return rms.clamp_min(tiny)


def icp(
    source: Tensor,
    target: Tensor,
    initial: Tensor | None = None,
    config: ICPConfig | None = None,
    target_normals: Tensor | None = None,
) -> ICPResult:
    """Register ``source`` to ``target``: find T with target ≈ R source + t.

    Iteration k: move the source by T_k, find each point's nearest target point (KD-tree),
    keep the gated and trimmed correspondences (:class:`ICPConfig`), stop if the inlier RMS
    decreased by at most ``relative_tolerance`` relative to the previous iteration (or went
    up), else solve
    for T_(k+1) in closed form (weighted Kabsch over the kept pairs) or, for point-to-plane,
    by one Gauss–Newton step on the linearized plane distances (left update exp(δ) T_k).

    Args:
        source: cloud to move, shape (N, 3), N ≥ 3, finite; a torch tensor or a numpy array
            (float32/float64).
        target: fixed cloud, shape (M, 3), M ≥ 3, finite, same dtype and device.
        initial: initial T, shape (4, 4); identity by default.
        config: options; ``ICPConfig()`` by default.
        target_normals: unit normals of ``target``, shape (M, 3), for point-to-plane.

    Returns:
        :class:`ICPResult` with batch shape (): ``transform`` (4, 4), scalar ``rms``,
        ``fitness``, ``iterations``, ``converged`` and a ``reason`` string.
        Non-convergence is reported in ``status``, not raised. When an input requires a
        gradient, ``transform`` carries the graph of the unrolled passes with their
        correspondences held fixed (the matching itself is discrete); for gradients of a
        registration, differentiate the joint solve (:mod:`torchslam.solver.differentiable`).
    """
    fn = "icp"
    if initial is not None:
        _checks.check_tensor(fn, "initial", initial, (4, 4))
        if initial.dim() != 2:
            raise ValueError(
                f"{fn}: argument 'initial' must have shape (4, 4), got {tuple(initial.shape)}"
            )
        initial = initial[None]
    prepared = _prepare(fn, source, target, initial, config, target_normals)
    return _run(fn, *prepared)[0]


def rotations_about_axis(
    count: int, axis: Tensor | None = None, *, dtype: torch.dtype = torch.float64
) -> Tensor:
    """``count`` rotations by 2πk/count, k = 0 … count−1, about a fixed axis.

    Args:
        count: number of rotations, an int ≥ 1.
        axis: rotation axis, shape (3,), finite and non-zero (any length); the y axis (the
            turntable axis of the Stanford scans) by default.
        dtype: dtype of the result when ``axis`` is None (float32 or float64); otherwise
            the result has ``axis``'s dtype and device.

    Returns:
        Rotation matrices, shape (count, 3, 3); the first is the identity.
    """
    fn = "rotations_about_axis"
    count = _checks.check_int(fn, "count", count, minimum=1)
    if axis is None:
        _checks.check_dtype_device(fn, dtype, None)
        axis = torch.tensor([0.0, 1.0, 0.0], dtype=dtype)
    _checks.check_tensor(fn, "axis", axis, (3,))
    if axis.dim() != 1:
        raise ValueError(f"{fn}: argument 'axis' must have shape (3,), got {tuple(axis.shape)}")
    _checks.check_finite(fn, "axis", axis)
    norm = torch.linalg.vector_norm(axis)
    if _checks.value_checks_active() and not bool(norm > 0):
        raise ValueError(f"{fn}: argument 'axis' must be a non-zero vector, got {axis.tolist()}")
    unit = axis / norm
    angles = torch.arange(count, dtype=axis.dtype, device=axis.device) * (2 * math.pi / count)
    return so3.exp(angles[:, None] * unit)


def rotations_uniform(
    count: int, *, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
) -> Tensor:
    """``count`` nearly uniformly spread rotations (deterministic super-Fibonacci spiral).

    Alexa, "Super-Fibonacci Spirals: Fast, Low-Discrepancy Sampling of SO(3)", CVPR 2022.
    The spacing between neighbours is about (3π / (4·count))^(1/3) · 2 radians (≈ 30° for
    count = 128, ≈ 24° for 256).

    Args:
        count: number of rotations, an int ≥ 1.
        dtype: float32 or float64.
        device: device of the result.

    Returns:
        Rotation matrices, shape (count, 3, 3).
    """
    fn = "rotations_uniform"
    count = _checks.check_int(fn, "count", count, minimum=1)
    _checks.check_dtype_device(fn, dtype, device)
    phi = math.sqrt(2.0)
    psi = 1.533751168755204288118041
    s = torch.arange(count, dtype=torch.float64) + 0.5
    r = torch.sqrt(s / count)
    big_r = torch.sqrt(1.0 - s / count)
    alpha = 2 * math.pi * s / phi
    beta = 2 * math.pi * s / psi
    # (x, y, z, w) of the paper, reordered to Hamilton (w, x, y, z).
    q = torch.stack(
        (
            big_r * torch.cos(beta),
            r * torch.sin(alpha),
            r * torch.cos(alpha),
            big_r * torch.sin(beta),
        ),
        dim=-1,
    )
    R = convert.quaternion_to_matrix(q)
    return R.to(dtype=dtype, device=device)


def initial_guesses(source: Tensor, target: Tensor, rotations: Tensor) -> Tensor:
    """Initial transforms T = [[R, c_t − R c_s], [0, 1]] that map the source centroid c_s
    onto the target centroid c_t after each rotation R.

    Args:
        source: cloud, shape (N, 3), N ≥ 1, finite; a torch tensor or a numpy array.
        target: cloud, shape (M, 3), M ≥ 1, finite, same dtype and device.
        rotations: rotation matrices, shape (B, 3, 3), same dtype and device.

    Returns:
        Transforms, shape (B, 4, 4).
    """
    fn = "initial_guesses"
    source, target = _clouds(fn, source, target, min_points=1, finite=None)
    _checks.check_tensor(fn, "rotations", rotations, (3, 3))
    _checks.check_same_kind(fn, source=source, rotations=rotations)
    _checks.check_rotation(fn, "rotations", rotations)
    c_s = source.mean(0)
    c_t = target.mean(0)
    t = c_t - rotations @ c_s
    return se3.from_rotation_translation(rotations, t)


def icp_multistart(
    source: Tensor,
    target: Tensor,
    initial: Tensor,
    config: ICPConfig | None = None,
    fitness_distance: float | None = None,
    target_normals: Tensor | None = None,
) -> tuple[ICPResult, ICPResult]:
    """Run ICP from every initial guess and keep the best.

    Runs are compared on one fixed yardstick (their own gates differ): the fraction of
    source points whose nearest target point lies within ``fitness_distance`` at the final
    transform; ties go to the lower RMS over those points.

    Args:
        source: cloud to move, shape (N, 3).
        target: fixed cloud, shape (M, 3).
        initial: initial guesses, shape (B, 4, 4), B ≥ 1 (e.g. :func:`initial_guesses`).
        config: ICP options.
        fitness_distance: yardstick distance, a finite number > 0; ``config.min_distance``
            if None (then that must be > 0).
        target_normals: for point-to-plane.

    Returns:
        ``(best, all_runs)``: the best run (batch shape ()) and every run (batch shape (B,)).
        ``best.fitness`` and ``best.rms`` are measured at ``fitness_distance``.
    """
    fn = "icp_multistart"
    source, target, initial, config, normals = _prepare(
        fn, source, target, initial, config, target_normals
    )
    if fitness_distance is not None:
        distance = _checks.check_real(
            fn, "fitness_distance", fitness_distance, low=0.0, low_open=True
        )
    elif config.min_distance > 0:
        distance = config.min_distance
    else:
        raise ValueError(
            f"{fn}: argument 'fitness_distance' is None and config.min_distance is 0; give a "
            "fitness_distance > 0 (or a config with min_distance > 0)"
        )
    runs = _run(fn, source, target, initial, config, normals)
    best, _ = _select(runs, source, target, distance, fn)
    return best, runs


def _select(
    runs: ICPResult, source: Tensor, target: Tensor, distance: float, fn: str = "icp"
) -> tuple[ICPResult, Tensor]:
    """The best run by fitness at ``distance`` (then RMS), and the ranking of all runs."""
    fitness, rms = _fitness(runs.transform, source, target, distance, fn)
    # Stable lexicographic order: sort by RMS first, then stably by descending fitness.
    by_rms = torch.argsort(rms, stable=True)
    order = by_rms[torch.argsort(-fitness[by_rms], stable=True)]
    best = int(order[0])
    chosen = runs[best]
    chosen.fitness = fitness[best]
    chosen.rms = rms[best]
    chosen.gate = source.new_tensor(distance)
    return chosen, order


@dataclass(frozen=True)
class Stage:
    """One level of :func:`register_coarse_to_fine`."""

    # downsampling pitch of both clouds at this level (voxel_downsample); 0 keeps them
    voxel_size: float
    # ICP options at this level
    config: ICPConfig = field(default_factory=ICPConfig)
    # number of hypotheses passed on to the next level: the best by fitness
    keep: int = 1
    # distance of the fitness yardstick used for ranking; voxel_size if None
    fitness_distance: float | None = None
    # k of the PCA normals of the target, used by point-to-plane levels
    normal_neighbors: int = 12

    def __post_init__(self) -> None:
        fn = "Stage"
        _checks.check_real(fn, "voxel_size", self.voxel_size, low=0.0)
        if not isinstance(self.config, ICPConfig):
            raise TypeError(
                f"{fn}: argument 'config' must be an ICPConfig, got {_checks.describe(self.config)}"
            )
        _checks.check_int(fn, "keep", self.keep, minimum=1)
        if self.fitness_distance is not None:
            _checks.check_real(
                fn, "fitness_distance", self.fitness_distance, low=0.0, low_open=True
            )
        elif self.voxel_size == 0:
            raise ValueError(f"{fn}: give 'fitness_distance' when 'voxel_size' is 0")
        _checks.check_int(fn, "normal_neighbors", self.normal_neighbors, minimum=3)


def register_coarse_to_fine(
    source: Tensor, target: Tensor, initial: Tensor, stages: tuple[Stage, ...] | list[Stage]
) -> tuple[ICPResult, list[ICPResult]]:
    """Multi-hypothesis, coarse-to-fine ICP.

    Level l downsamples both clouds to ``stages[l].voxel_size``, runs ICP from every
    surviving hypothesis (one batch), ranks the runs by fitness at the level's yardstick
    distance (as :func:`icp_multistart`) and passes the best ``keep`` transforms on. A wide
    set of initial rotations (:func:`rotations_uniform` with :func:`initial_guesses`) at a
    coarse level followed by a few finer levels handles initial misalignments far outside
    the basin of plain ICP at a fraction of the cost of running all hypotheses finely.

    Args:
        source: cloud to move, shape (N, 3), finite; a torch tensor or a numpy array.
        target: fixed cloud, shape (M, 3), finite, same dtype and device.
        initial: initial guesses of T (source → target frame), shape (B, 4, 4), B ≥ 1.
        stages: the levels (:class:`Stage`), coarse to fine; the last one's result is
            returned.

    Returns:
        ``(best, per_stage)``: the best run of the last level (batch shape (), with
        ``fitness``/``rms`` at that level's yardstick) and every level's batch of runs.
    """
    fn = "register_coarse_to_fine"
    source, target = _clouds(fn, source, target)
    initial = _check_initial(fn, initial, source, allow_empty=False)
    if not isinstance(stages, (tuple, list)):
        raise TypeError(
            f"{fn}: argument 'stages' must be a tuple or list of Stage, got "
            f"{_checks.describe(stages)}"
        )
    if len(stages) == 0:
        raise ValueError(f"{fn}: argument 'stages' must not be empty")
    for level, stage in enumerate(stages):
        if not isinstance(stage, Stage):
            raise TypeError(
                f"{fn}: argument 'stages' must hold Stage objects, got "
                f"{_checks.describe(stage)} at index {level}"
            )
    hypotheses = initial
    per_stage: list[ICPResult] = []
    best: ICPResult | None = None
    for level, stage in enumerate(stages):
        src = _downsample(fn, source, stage.voxel_size) if stage.voxel_size > 0 else source
        tgt = _downsample(fn, target, stage.voxel_size) if stage.voxel_size > 0 else target
        if min(src.shape[0], tgt.shape[0]) < 3:
            raise ValueError(
                f"{fn}: level {level} (voxel size {stage.voxel_size:g}) leaves "
                f"{src.shape[0]} source and {tgt.shape[0]} target points, need ≥ 3 each; use a "
                "smaller voxel size"
            )
        normals = None
        if stage.config.method == "point_to_plane":
            normals = _normals(fn, tgt, min(stage.normal_neighbors, tgt.shape[0]), None)
        distance = stage.voxel_size if stage.fitness_distance is None else stage.fitness_distance
        runs = _run(fn, src, tgt, hypotheses, stage.config, normals)
        best, order = _select(runs, src, tgt, distance, fn)
        per_stage.append(runs)
        hypotheses = runs.transform[order[: stage.keep]]
    assert best is not None
    return best, per_stage


def _fitness(
    T: Tensor, source: Tensor, target: Tensor, distance: float, fn: str = "icp"
) -> tuple[Tensor, Tensor]:
    """Fraction of source points within ``distance`` of the target and their RMS, (B,) each."""
    d, _ = _query(_tree(fn, "target", target), _move(T, source), distance, fn=fn)
    inside = torch.isfinite(d)
    fitness = inside.to(source.dtype).mean(-1)
    squared = torch.where(inside, d, torch.zeros_like(d)) ** 2
    rms = torch.sqrt(squared.sum(-1) / inside.sum(-1).clamp_min(1).to(source.dtype))
    return fitness, rms


def chain_poses(relative: Tensor) -> Tensor:
    """Chain successive relative poses into poses in the frame of the first scan.

    ``relative[k]`` maps scan k+1 into scan k (the ICP result with source = scan k+1 and
    target = scan k, T̂_(k,k+1)). Then T̂_0i = T̂_01 T̂_12 ⋯ T̂_(i−1,i) (seed eq. (0.1)) maps
    scan i into scan 0.

    Args:
        relative: shape (M − 1, 4, 4).

    Returns:
        Poses T̂_0i, shape (M, 4, 4), the first one the identity.
    """
    fn = "chain_poses"
    _checks.check_tensor(fn, "relative", relative, (4, 4), min_batch_dims=1, dims="N")
    if relative.dim() != 3:
        raise ValueError(
            f"{fn}: argument 'relative' must have shape (M-1, 4, 4), got {tuple(relative.shape)}"
        )
    _checks.check_pose_matrix(fn, "relative", relative)
    poses = [se3.identity(dtype=relative.dtype, device=relative.device)]
    for step in relative:
        poses.append(se3.compose(poses[-1], step))
    return torch.stack(poses)
