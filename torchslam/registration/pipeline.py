"""Multiview registration of range scans: pairwise ICP along a chain, then joint ICP-SLAM.

The pipeline of the seed's sections 0 and 1, for m scans given in a *chain order* (successive
scans must overlap):

1. **Downsample** every scan on a voxel grid
   (:func:`torchslam.registration.neighbors.voxel_downsample`).
2. **Pairwise ICP** between successive scans, T̂_(k,k+1) (scan k+1 → scan k), from
   ``hypotheses`` initial rotations spread over SO(3), refined coarse to fine with
   point-to-plane ICP (:func:`~torchslam.registration.config.default_stages`). No prior pose
   is needed.
3. **Chaining** T̂_0i = T̂_01 T̂_12 ⋯ T̂_(i−1,i) (seed eq. 0.1): the initial poses.
4. **Overlapping pairs**: at the chained poses, every pair of scans of which each has at least
   ``min_overlap`` of its points within one voxel of the other is matched (this adds the loop
   closures that chaining ignores).
5. **Point tracks**: mutual nearest neighbours within ``track_radius`` over those pairs,
   joined into tracks (:func:`torchslam.registration.tracks.build_tracks`); the world point
   X_0j starts at the mean of its observations (seed eq. 0.2). Points on a scan's boundary
   (:func:`boundary_mask`) make no tracks: range data are least reliable there.
6. **Joint ICP-SLAM solve** over all poses and points (:class:`torchslam.PointMapProblem`,
   residual r_ij = X_ij − T_i0 X_0j of seed eq. 1.1, T_i0 = T_0i⁻¹; robust loss; the first
   scan's pose fixed as the gauge), with :func:`torchslam.solve`.
7. **Re-association**: steps 5–6 again from the updated poses, ``rounds`` times at most.

Voxel centroids of two scans never sample the same surface point: matched observations are
offset along the surface by up to a voxel, which would pull the poses towards the current
association (the slow tangential creep of point-to-point ICP). The joint problem therefore
weights each residual by an information matrix Ω_ij = n nᵀ + τ (I − n nᵀ), with n the unit
surface normal of scan i at X_ij (PCA over its neighbours) and τ = ``tangent_weight`` ≪ 1:
the cost is still ½ Σ ρ(r_ijᵀ Ω_ij r_ij) of the seed's point-map problem, but offsets across
the surface count fully and offsets along it little (a point-to-plane metric inside the
point-map model; τ > 0 keeps every point determined). On synthetic scans with known poses
τ = 0.01 gave about 30 % smaller pose errors than τ = 0.05; τ = 1 (isotropic) the largest.

All distances scale with one length, ``voxel_size`` (the finest pitch, 2 mm by default, for
scans in metres about 0.15 m across, like the Stanford bunny).

Options: :mod:`torchslam.registration.config`; consistency checks and error tables:
:mod:`torchslam.registration.report`; pose files: :mod:`torchslam.io.trajectories`; the command
``torchslam register`` and its figure: :mod:`torchslam.cli.register`, :mod:`torchslam.cli.plots`.
"""

from __future__ import annotations

import itertools
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from torchslam import _checks
from torchslam.io.ply import read_ply_points
from torchslam.io.stanford import relative_to_first, scan_name
from torchslam.lie import se3
from torchslam.problem import PointMapProblem
from torchslam.registration import icp
from torchslam.registration.config import RegisterConfig, check_clouds, check_config, check_poses
from torchslam.registration.report import alignment_residual
from torchslam.registration.tracks import Tracks, build_tracks
from torchslam.solver import SolverConfig, Status, solve

__all__ = [
    "ChainResult",
    "Progress",
    "RefineResult",
    "Registration",
    "RoundInfo",
    "boundary_mask",
    "information_matrices",
    "joint_cost",
    "load_scans",
    "overlapping_pairs",
    "refine",
    "register",
    "register_chain",
]

Progress = Callable[[str], None]


# ----------------------------------------------------------------------------- input


def load_scans(
    paths: Sequence[str | os.PathLike], *, dtype: torch.dtype = torch.float64
) -> tuple[list[str], list[Tensor]]:
    """Read PLY scans (vertex coordinates only).

    Args:
        paths: the files, ≥ 2, with distinct base names.
        dtype: dtype of the clouds.

    Returns:
        ``(names, clouds)``: scan names (base names without extension) and clouds (N_i, 3).

    Raises:
        OSError: a file is missing or unreadable.
        TypeError: ``paths`` is a single path (wrap it in a list) or holds a non-path;
            ``dtype`` is not float32/float64.
        ValueError: fewer than 2 files, a repeated name, a directory, a malformed PLY or too
            few points.
    """
    fn = "load_scans"
    if isinstance(paths, (str, bytes, os.PathLike)):
        raise TypeError(
            f"{fn}: argument 'paths' must be a list of paths, got a single "
            f"{type(paths).__name__} {os.fsdecode(os.fspath(paths))!r}; wrap it in a list"
        )
    if not isinstance(paths, Sequence):
        raise TypeError(
            f"{fn}: argument 'paths' must be a list of paths, got {_checks.describe(paths)}"
        )
    paths = [_checks.check_path(fn, p, f"paths[{k}]") for k, p in enumerate(paths)]
    _checks.check_float_dtype(fn, dtype)
    if len(paths) < 2:
        raise ValueError(f"{fn}: argument 'paths' must hold at least 2 scans, got {len(paths)}")
    names = [scan_name(p) for p in paths]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ValueError(
            f"{fn}: argument 'paths' must give distinct scan names (base names without "
            f"extension), repeated: {', '.join(repeated)}"
        )
    clouds = []
    for path in paths:
        if os.path.isdir(path):
            raise ValueError(f"{fn}: argument 'paths' holds a directory, not a scan: {path}")
        if not os.path.isfile(path):
            raise FileNotFoundError(f"{fn}: no such scan file: {path}")
        cloud = read_ply_points(path, dtype=dtype)
        if cloud.shape[0] < 10:
            raise ValueError(f"{fn}: {path}: only {cloud.shape[0]} points, need ≥ 10")
        if not bool(torch.isfinite(cloud).all()):
            raise ValueError(f"{fn}: {path}: non-finite vertex coordinates")
        clouds.append(cloud)
    return names, clouds


# ----------------------------------------------------------------------------- pairwise chain


@dataclass
class ChainResult:
    """Pairwise ICP between successive scans and the chained poses."""

    # T̂_(k,k+1) mapping scan k+1 into scan k, shape (m − 1, 4, 4)
    relative: Tensor
    # T̂_0i = T̂_01 ⋯ T̂_(i−1,i) mapping scan i into scan 0, shape (m, 4, 4)
    poses: Tensor
    # per pair: the ICP result of the last level (fitness/rms at its yardstick distance)
    pair_results: list[icp.ICPResult]
    # per pair: wall seconds
    pair_seconds: list[float]


def register_chain(
    clouds: Sequence[Tensor],
    config: RegisterConfig | None = None,
    progress: Progress | None = None,
    names: Sequence[str] | None = None,
) -> ChainResult:
    """Pairwise ICP between successive scans (coarse to fine, many starts), then chaining.

    Args:
        clouds: m ≥ 2 scans in chain order, shapes (N_i, 3), in their own frames.
        config: options (``hypotheses``, ``stages``).
        progress: called with one line per pair.
        names: scan names for the progress lines.

    Returns:
        :class:`ChainResult`; poses in the frame of scan 0.
    """
    fn = "register_chain"
    clouds = check_clouds(fn, clouds, minimum=2, min_points=3)
    config = check_config(fn, config)
    if names is not None:
        names = _checks.check_names(fn, names, count=len(clouds), words=False)
    if progress is not None and not callable(progress):
        raise TypeError(f"{fn}: argument 'progress' must be callable or None")
    stages = config.pairwise_stages()
    rotations = icp.rotations_uniform(config.hypotheses, dtype=clouds[0].dtype)
    relative, results, seconds = [], [], []
    for k, (target, source) in enumerate(itertools.pairwise(clouds)):
        tic = time.perf_counter()
        initial = icp.initial_guesses(source, target, rotations)
        best, _ = icp.register_coarse_to_fine(source, target, initial, stages)
        relative.append(best.transform)
        results.append(best)
        seconds.append(time.perf_counter() - tic)
        if progress is not None:
            label = f"{names[k]} ← {names[k + 1]}" if names is not None else "pair"
            fitness = float(best.fitness)
            # Successive scans that share less than a fifth of their points rarely register.
            warning = " (low: do these scans overlap?)" if fitness < 0.2 else ""
            progress(
                f"{label} ({k + 1}/{len(clouds) - 1}): {best.status_name.lower()}, fitness "
                f"{fitness:.3f}{warning}, rms {float(best.rms):.3g}, {seconds[-1]:.1f} s"
            )
    relative_t = torch.stack(relative)
    return ChainResult(relative_t, icp.chain_poses(relative_t), results, seconds)


# ----------------------------------------------------------------------------- joint solve


def overlapping_pairs(
    clouds: Sequence[Tensor], poses: Tensor, distance: float, min_overlap: float
) -> tuple[list[tuple[int, int]], Tensor]:
    """Pairs of scans that overlap at the given poses.

    The overlap of scan i with scan k is the fraction of i's points that have a point of k
    within ``distance`` (world frame). A pair (i, k), i < k, is kept when both overlaps
    (i with k and k with i) are at least ``min_overlap``.

    Args:
        clouds: m clouds in their scan frames, shapes (N_i, 3).
        poses: T_0i, shape (m, 4, 4).
        distance: neighbourhood distance, > 0.
        min_overlap: smallest overlap fraction, in [0, 1].

    Returns:
        ``(pairs, overlap)``: the kept pairs (i < k) and the overlap matrix (m, m) (row i:
        fraction of scan i's points near scan k; diagonal 1).
    """
    fn = "overlapping_pairs"
    clouds = check_clouds(fn, clouds)
    m = len(clouds)
    check_poses(fn, poses, m)
    distance = _checks.check_real(fn, "distance", distance, low=0, low_open=True)
    _checks.check_real(fn, "min_overlap", min_overlap, low=0, high=1)
    world = [se3.act(poses[i], clouds[i]).detach().cpu().numpy() for i in range(m)]
    trees = [cKDTree(w) for w in world]
    overlap = np.eye(m)
    for i, k in itertools.permutations(range(m), 2):
        d, _ = trees[k].query(world[i], distance_upper_bound=distance)
        overlap[i, k] = float(np.isfinite(d).mean())
    pairs = [
        (i, k)
        for i, k in itertools.combinations(range(m), 2)
        if min(overlap[i, k], overlap[k, i]) >= min_overlap
    ]
    return pairs, torch.from_numpy(overlap)


def boundary_mask(points: Tensor, neighbors: int = 12, threshold: float = 0.3) -> Tensor:
    """Points on the boundary of a scan (its silhouette or a hole's rim).

    Inside a sampled surface the k nearest neighbours of a point surround it and their
    centroid lies close to it; on a boundary they all lie on one side. A point is a boundary
    point when the component of centroid − p along the surface (normal removed, PCA of the
    same neighbourhood) exceeds ``threshold`` × (mean distance to its neighbours). Range
    scans are least reliable there (grazing angles, edge curl, partial voxels), and ICP
    variants reject correspondences on boundaries for that reason (Turk & Levoy 1994).

    Args:
        points: cloud, shape (N, 3), N ≥ 2, finite (a tensor or a numpy array).
        neighbors: k ≥ 3, including the point itself, clipped to N.
        threshold: offset ratio, > 0.

    Returns:
        Mask, bool, shape (N,), on ``points``' device (CPU for a numpy array).
    """
    fn = "boundary_mask"
    if isinstance(points, np.ndarray):
        if not np.issubdtype(points.dtype, np.floating):
            raise TypeError(f"{fn}: argument 'points' must be floating point, got {points.dtype}")
        points = torch.from_numpy(np.asarray(points, dtype=np.float64))
    _checks.check_batched(fn, "points", points, ("N",), (3,))
    if points.shape[0] < 2:
        raise ValueError(
            f"{fn}: argument 'points' must have ≥ 2 points, got shape {tuple(points.shape)}"
        )
    neighbors = _checks.check_int(fn, "neighbors", neighbors, minimum=3)
    threshold = _checks.check_real(fn, "threshold", threshold, low=0, low_open=True)
    x = points.detach().cpu().numpy().astype(np.float64, copy=False)
    if not np.isfinite(x).all():
        bad = int(np.flatnonzero(~np.isfinite(x).all(-1))[0])
        raise ValueError(
            f"{fn}: argument 'points' contains non-finite values (NaN or Inf), first at point {bad}"
        )
    k = min(neighbors, points.shape[0])
    distance, index = cKDTree(x).query(x, k=k)
    local = x[index]  # (N, k, 3)
    centroid = local.mean(1)
    # Only the offset along the surface counts: on a curved surface the centroid also lies
    # off the point along the normal (the smallest principal axis of the neighbourhood).
    centred = local - centroid[:, None]
    _, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
    normal = vectors[..., 0]
    offset = centroid - x
    offset -= (offset * normal).sum(-1, keepdims=True) * normal
    spacing = distance[:, 1:].mean(1)
    return torch.from_numpy(np.linalg.norm(offset, axis=-1) > threshold * spacing).to(points.device)


def information_matrices(normals: Tensor, tangent_weight: float) -> Tensor:
    """Ω = n nᵀ + τ (I − n nᵀ) per observation (module docstring).

    Args:
        normals: unit normals in the observing scan's frame, shape (E, 3).
        tangent_weight: τ in (0, 1].

    Returns:
        Information matrices, shape (E, 3, 3), symmetric positive definite (eigenvalues 1, τ, τ).
    """
    fn = "information_matrices"
    _checks.check_batched(fn, "normals", normals, ("E",), (3,))
    _checks.check_finite(fn, "normals", normals)
    tangent_weight = _checks.check_real(
        fn, "tangent_weight", tangent_weight, low=0, high=1, low_open=True
    )
    outer = normals[:, :, None] * normals[:, None, :]
    eye = torch.eye(3, dtype=normals.dtype, device=normals.device)
    return outer + tangent_weight * (eye - outer)


@dataclass
class RoundInfo:
    """One round of association and joint solve."""

    # number of tracks n, observations E, and refused merges of the track builder
    num_points: int
    num_observations: int
    num_conflicts: int
    # joint cost ½ Σ ρ(rᵀΩr) before and after the solve
    initial_cost: float
    final_cost: float
    # LM iterations, stop status
    iterations: int
    status: Status
    # largest pose change of the round: degrees, and the scans' units
    rotation_change_deg: float
    translation_change: float
    # wall seconds of the round (tracks + solve)
    seconds: float


@dataclass
class RefineResult:
    """Output of :func:`refine`."""

    # T_0i after the last round, in the frame of scan 0, shape (m, 4, 4)
    poses: Tensor
    # one entry per round
    rounds: list[RoundInfo]
    # the tracks of the last round (built at the poses it started from)
    tracks: Tracks | None
    # the matched scan pairs (i < k)
    pairs: list[tuple[int, int]]
    # the clouds the tracks index (boundary points removed) and their unit normals
    track_clouds: list[Tensor]
    track_normals: list[Tensor]


def _normals_of(tracks: Tracks, normals: Sequence[Tensor]) -> Tensor:
    sizes = torch.tensor([0] + [len(n) for n in normals[:-1]], dtype=torch.int64)
    offsets = torch.cumsum(sizes, 0)
    return torch.cat(list(normals))[offsets[tracks.pose_index] + tracks.source_index]


def _problem(
    tracks: Tracks,
    poses: Tensor,
    normals: Sequence[Tensor],
    config: RegisterConfig,
    fixed_poses: Tensor | None = None,
    points: Tensor | None = None,
) -> PointMapProblem:
    information = None
    if config.tangent_weight < 1:
        information = information_matrices(_normals_of(tracks, normals), config.tangent_weight)[
            None
        ]
    return PointMapProblem(
        se3.inverse(poses)[None],  # T_i0 = T_0i⁻¹
        (tracks.points if points is None else points)[None],
        tracks.pose_index[None],
        tracks.point_index[None],
        tracks.observations[None],
        weights=information,
        fixed_poses=fixed_poses,
        loss=config.robust_loss(),
    )


def _pose_change(before: Tensor, after: Tensor) -> tuple[float, float]:
    delta = se3.compose(se3.inverse(before), after)
    angle = torch.rad2deg(torch.linalg.vector_norm(se3.log(delta)[:, :3], dim=-1))
    shift = torch.linalg.vector_norm(after[:, :3, 3] - before[:, :3, 3], dim=-1)
    return float(angle.max()), float(shift.max())


def refine(
    clouds: Sequence[Tensor],
    poses: Tensor,
    config: RegisterConfig | None = None,
    *,
    pairs: Sequence[tuple[int, int]] | None = None,
    progress: Progress | None = None,
) -> RefineResult:
    """Joint ICP-SLAM refinement: rounds of point tracks + the point-map least-squares solve.

    Args:
        clouds: m downsampled clouds (track level, ``config.voxel_size``) in their scan frames.
        poses: initial T_0i (e.g. chained), shape (m, 4, 4).
        config: options.
        pairs: scan pairs to match; by default those of :func:`overlapping_pairs` at
            ``poses`` with ``config.min_overlap``.
        progress: called with one line per round.

    Returns:
        :class:`RefineResult`, poses in the frame of scan 0 (its pose is the gauge).
    """
    fn = "refine"
    clouds = check_clouds(fn, clouds, minimum=2, min_points=2)
    check_poses(fn, poses, len(clouds))
    config = check_config(fn, config)
    if progress is not None and not callable(progress):
        raise TypeError(f"{fn}: argument 'progress' must be callable or None")
    if pairs is not None:
        pairs = _checks.check_index_pairs(fn, pairs, len(clouds))
    poses = relative_to_first(poses.detach().clone().to(clouds[0].dtype), 0)
    if pairs is None:
        pairs, _ = overlapping_pairs(clouds, poses, config.voxel_size, config.min_overlap)
    pairs = list(pairs)
    normals = [icp.estimate_normals(c, min(config.normal_neighbors, len(c))) for c in clouds]
    if config.boundary_threshold is not None:
        # Tracks only on interior points; Tracks.source_index then indexes these subsets.
        interior = [
            ~boundary_mask(c, config.normal_neighbors, config.boundary_threshold) for c in clouds
        ]
        clouds = [c[keep] for c, keep in zip(clouds, interior, strict=True)]
        normals = [n[keep] for n, keep in zip(normals, interior, strict=True)]
    solver = SolverConfig(max_iterations=config.max_iterations, function_tolerance=1e-8)
    radius = config.track_radius * config.voxel_size
    rounds: list[RoundInfo] = []
    tracks = None
    for index in range(config.rounds if pairs else 0):
        tic = time.perf_counter()
        tracks = build_tracks(clouds, poses, radius, pairs=pairs)
        if tracks.num_points == 0:
            break
        problem = _problem(tracks, poses, normals, config)
        result = solve(problem, solver)
        updated = se3.inverse(result.poses[0].detach())
        rotation_change, translation_change = _pose_change(poses, updated)
        poses = relative_to_first(updated, 0)
        info = RoundInfo(
            tracks.num_points,
            tracks.num_edges,
            tracks.num_conflicts,
            float(result.initial_cost[0]),
            float(result.final_cost[0]),
            int(result.iterations[0]),
            result.status[0],
            rotation_change,
            translation_change,
            time.perf_counter() - tic,
        )
        rounds.append(info)
        if progress is not None:
            progress(
                f"round {index + 1}: {info.num_points} tracks, {info.num_observations} "
                f"observations, cost {info.initial_cost:.4g} → {info.final_cost:.4g} in "
                f"{info.iterations} LM iterations ({info.status.name.lower()}), pose change "
                f"≤ {rotation_change:.3f}° / {translation_change:.3g}, {info.seconds:.1f} s"
            )
        if (
            rotation_change <= config.rotation_tolerance_deg
            and translation_change <= config.translation_tolerance * config.voxel_size
        ):
            break
    return RefineResult(poses, rounds, tracks, pairs, clouds, normals)


def joint_cost(
    refinement: RefineResult,
    poses: Tensor,
    config: RegisterConfig | None = None,
) -> float:
    """The joint cost of fixed poses on the final tracks of a refinement, best points for them.

    All poses are held fixed and only the world points X_0j are solved for, so this is
    min over X of ½ Σ ρ(r_ijᵀ Ω_ij r_ij) on one data association: it compares pose sets
    (e.g. the estimate and a reference alignment) on the same tracks.

    Args:
        refinement: a :func:`refine` result (its last tracks, clouds and normals).
        poses: T_0i, shape (m, 4, 4), any common frame.
        config: the options that define Ω and ρ (those of the refinement).

    Returns:
        The cost (nan when the refinement has no tracks).
    """
    fn = "joint_cost"
    if not isinstance(refinement, RefineResult):
        raise TypeError(
            f"{fn}: argument 'refinement' must be a RefineResult, "
            f"got {_checks.describe(refinement)}"
        )
    config = check_config(fn, config)
    m = len(refinement.track_clouds)
    check_poses(fn, poses, m, against="the refinement's scans")
    tracks = refinement.tracks
    if tracks is None:
        return math.nan
    poses = poses.to(tracks.observations.dtype)
    points = _track_points(tracks, poses)
    fixed = torch.ones(1, m, dtype=torch.bool)
    problem = _problem(tracks, poses, refinement.track_normals, config, fixed, points)
    result = solve(problem, SolverConfig(max_iterations=config.max_iterations))
    return float(result.final_cost[0])


def _track_points(tracks: Tracks, poses: Tensor) -> Tensor:
    """Initial X_0j for ``poses``: the mean of T_0i X_ij over each track (seed eq. 0.2)."""
    moved = se3.act(poses[tracks.pose_index], tracks.observations)
    sums = moved.new_zeros(tracks.num_points, 3).index_add_(0, tracks.point_index, moved)
    counts = torch.bincount(tracks.point_index, minlength=tracks.num_points)
    return sums / counts.clamp_min(1).to(moved.dtype)[:, None]


# ----------------------------------------------------------------------------- pipeline


@dataclass
class Registration:
    """Result of :func:`register`. Poses map each scan into the frame of scan ``frame``."""

    # scan names, input (chain) order
    names: list[str]
    # index of the reference scan whose frame the poses are in
    frame: int
    # chained pairwise-ICP poses T_0i, shape (m, 4, 4)
    chained: Tensor
    # jointly optimized poses T_0i, shape (m, 4, 4) (the chained ones if rounds = 0)
    poses: Tensor
    # the pairwise chain
    chain: ChainResult
    # the joint refinement
    refinement: RefineResult
    # track-level clouds (voxel_size) in their scan frames
    clouds: list[Tensor]
    # overlap matrix at the chained poses, (m, m)
    overlap: Tensor
    # RMS point-to-plane distance between matched scans: chained, joint
    residual_chained: float
    residual_joint: float
    # voxel pitch of ``clouds``
    voxel_size: float = 0.0
    # wall seconds per stage (downsample, chain, refine, total)
    seconds: dict[str, float] = field(default_factory=dict)


def register(
    names: Sequence[str],
    clouds: Sequence[Tensor],
    config: RegisterConfig | None = None,
    *,
    frame: int | str = 0,
    progress: Progress | None = None,
) -> Registration:
    """The whole pipeline (module docstring) on scans given in chain order.

    Args:
        names: scan names, m ≥ 2.
        clouds: full-resolution scans in their own frames, shapes (N_i, 3), chain order.
        config: options.
        frame: index or name of the scan whose frame the poses are expressed in.
        progress: called with one line per stage (and per pair and round).

    Returns:
        :class:`Registration`.

    Raises:
        TypeError, ValueError: bad arguments (names must be distinct single words, as
            :func:`write_poses` writes them; clouds float tensors (N_i, 3) of one dtype and
            device, finite; ``frame`` an int index or a name among ``names``).
    """
    fn = "register"
    names = _checks.check_names(fn, names)
    clouds = check_clouds(fn, clouds, minimum=2, min_points=3)
    if len(names) != len(clouds):
        raise ValueError(
            f"{fn}: argument 'names' must hold one name per cloud, got {len(names)} names for "
            f"{len(clouds)} clouds"
        )
    config = check_config(fn, config)
    if progress is not None and not callable(progress):
        raise TypeError(f"{fn}: argument 'progress' must be callable or None")
    if isinstance(frame, str):
        if frame not in names:
            raise ValueError(
                f"{fn}: argument 'frame' must be an index or one of the names, got {frame!r}"
            )
        frame = names.index(frame)
    frame = _checks.check_int(fn, "frame", frame, minimum=0, maximum=len(names) - 1)
    _check_point_counts(names, clouds, config)
    say = progress or (lambda _line: None)
    seconds: dict[str, float] = {}
    start = time.perf_counter()

    say(f"pairwise ICP along the chain: {len(clouds) - 1} pairs …")
    tic = time.perf_counter()
    chain = register_chain(clouds, config, lambda line: say("  " + line), names)
    seconds["chain"] = time.perf_counter() - tic

    tic = time.perf_counter()
    small = [icp.voxel_downsample(c, config.voxel_size) for c in clouds]
    pairs, overlap = overlapping_pairs(small, chain.poses, config.voxel_size, config.min_overlap)
    chain_pairs = {(k, k + 1) for k in range(len(clouds) - 1)}
    pairs = sorted(set(pairs) | chain_pairs)
    extra = [p for p in pairs if p not in chain_pairs]
    seconds["overlap"] = time.perf_counter() - tic
    say(
        f"overlapping pairs at the chained poses: {len(pairs)}, {len(extra)} besides the chain "
        f"(overlap ≥ {config.min_overlap:g} within {config.voxel_size:g})"
    )
    for i, k in extra:
        say(f"  {names[i]} – {names[k]}: overlap {overlap[i, k]:.2f} / {overlap[k, i]:.2f}")

    say(
        f"joint ICP-SLAM on {sum(len(c) for c in small)} points ({config.voxel_size:g} voxels), "
        f"{config.rounds} rounds at most …"
    )
    tic = time.perf_counter()
    refinement = refine(
        small, chain.poses, config, pairs=pairs, progress=lambda line: say("  " + line)
    )
    seconds["refine"] = time.perf_counter() - tic

    # The consistency check uses the clouds the joint problem saw (boundary points removed).
    distance = config.voxel_size
    residual_chained = alignment_residual(refinement.track_clouds, chain.poses, pairs, distance)
    residual_joint = alignment_residual(refinement.track_clouds, refinement.poses, pairs, distance)
    seconds["total"] = time.perf_counter() - start
    return Registration(
        names,
        frame,
        relative_to_first(chain.poses, frame),
        relative_to_first(refinement.poses, frame),
        chain,
        refinement,
        small,
        overlap,
        residual_chained,
        residual_joint,
        config.voxel_size,
        seconds,
    )


def _check_point_counts(
    names: Sequence[str], clouds: Sequence[Tensor], config: RegisterConfig
) -> None:
    """Every scan keeps enough points at every voxel size of the pipeline (ValueError)."""
    sizes = sorted({s.voxel_size for s in config.pairwise_stages()} | {config.voxel_size})
    # ICP needs 3 points and stops at fewer than min_correspondences (6 by default) matches.
    need = max([3, *(s.config.min_correspondences for s in config.pairwise_stages())])
    for name, cloud in zip(names, clouds, strict=True):
        for size in sizes:
            count = len(icp.voxel_downsample(cloud, size)) if size > 0 else len(cloud)
            if count < need:
                raise ValueError(
                    f"register: scan {name!r} keeps {count} of {len(cloud)} points on a "
                    f"{size:g} voxel grid, need ≥ {need}; use a smaller voxel size "
                    "(--voxel-size)"
                )
