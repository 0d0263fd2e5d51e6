"""Multiview registration of range scans: pairwise ICP along a chain, then joint ICP-SLAM.

The pipeline of the seed's sections 0 and 1, for m scans given in a *chain order* (successive
scans must overlap):

1. **Downsample** every scan on a voxel grid (:func:`torchslam.registration.icp.voxel_downsample`).
2. **Pairwise ICP** between successive scans, T̂_(k,k+1) (scan k+1 → scan k), from
   ``hypotheses`` initial rotations spread over SO(3), refined coarse to fine with
   point-to-plane ICP (:func:`default_stages`). No prior pose is needed.
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

Pose file (:func:`write_poses` / :func:`read_poses`): one line per scan, in input order::

    name tx ty tz qw qx qy qz

T_0i = [[R(q), t], [0, 1]] maps the scan's coordinates into the frame of the reference scan
(the first scan unless chosen otherwise): p_ref = R(q) p_scan + t; q is a unit Hamilton
quaternion written scalar first; t in the scans' units. Lines starting with ``#`` are comments.
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from torchslam import _checks
from torchslam.cli import plots as _plotting
from torchslam.io import _text
from torchslam.io.ply import read_ply_points, write_ply
from torchslam.io.stanford import pose_errors, read_conf, relative_to_first, scan_name, stack
from torchslam.lie import convert, se3
from torchslam.losses import CauchyLoss, HuberLoss
from torchslam.problem import PointMapProblem
from torchslam.registration import icp
from torchslam.registration.tracks import Tracks, build_tracks
from torchslam.solver import SolverConfig, Status, solve

__all__ = [
    "ChainResult",
    "RefineResult",
    "RegisterConfig",
    "Registration",
    "RoundInfo",
    "add_arguments",
    "alignment_residual",
    "boundary_mask",
    "default_stages",
    "error_table",
    "information_matrices",
    "joint_cost",
    "load_scans",
    "main",
    "merged_cloud",
    "overlapping_pairs",
    "plane_distances",
    "plot_registration",
    "read_poses",
    "refine",
    "register",
    "register_chain",
    "run",
    "scan_colors",
    "write_poses",
]

Progress = Callable[[str], None]


# ----------------------------------------------------------------------------- configuration


def default_stages(voxel_size: float = 0.002) -> tuple[icp.Stage, ...]:
    """Coarse-to-fine pairwise schedule: 5×, 2.5× and 1× ``voxel_size`` (10, 5, 2 mm).

    Point-to-plane at every level: from starts 30–60° off it converges in a few iterations,
    where point-to-point creeps along the surface. Level 1 runs all hypotheses for 8
    iterations and passes the best 8 on; level 2 the best one; level 3 refines it.

    Raises:
        TypeError, ValueError: ``voxel_size`` is not a finite number > 0.
    """
    v = _checks.check_real("default_stages", "voxel_size", voxel_size, low=0, low_open=True)
    return (
        icp.Stage(
            5 * v,
            icp.ICPConfig(
                method="point_to_plane",
                max_iterations=8,
                max_distance=25 * v,
                min_distance=5 * v,
                trim_fraction=0.9,
                relative_tolerance=1e-3,
            ),
            keep=8,
        ),
        icp.Stage(
            2.5 * v,
            icp.ICPConfig(
                method="point_to_plane",
                max_iterations=20,
                max_distance=10 * v,
                min_distance=2.5 * v,
                trim_fraction=0.9,
                relative_tolerance=1e-4,
            ),
            keep=1,
        ),
        icp.Stage(
            v,
            icp.ICPConfig(
                method="point_to_plane",
                max_iterations=40,
                max_distance=5 * v,
                min_distance=v,
                trim_fraction=0.9,
                relative_tolerance=1e-5,
            ),
        ),
    )


@dataclass(frozen=True)
class RegisterConfig:
    """Options of :func:`register`. Lengths are in the scans' units (metres for the bunny)."""

    # finest voxel pitch: pairwise ICP's last level and the clouds the tracks are built on
    voxel_size: float = 0.002
    # initial rotations per chain pair (super-Fibonacci over SO(3), centroids aligned)
    hypotheses: int = 128
    # pairwise levels; None means default_stages(voxel_size)
    stages: tuple[icp.Stage, ...] | None = None
    # a pair is matched when each scan has ≥ this fraction of points within a voxel of the other
    min_overlap: float = 0.1
    # mutual-nearest-neighbour radius of the tracks, in units of voxel_size
    track_radius: float = 1.5
    # neighbours of the PCA normals of the track clouds (and of the boundary test)
    normal_neighbors: int = 12
    # points whose neighbour centroid is off by more than this × their mean neighbour
    # distance lie on a scan's boundary and make no tracks (None keeps them)
    boundary_threshold: float | None = 0.3
    # τ of Ω = n nᵀ + τ (I − n nᵀ): weight of residuals along the surface (1 = isotropic)
    tangent_weight: float = 0.01
    # robust kernel of the joint solve, on s = rᵀ Ω r
    loss: Literal["huber", "cauchy", "none"] = "huber"
    # its scale, in units of voxel_size
    loss_scale: float = 0.5
    # association + joint-solve rounds at most (0: chaining only)
    rounds: int = 4
    # stop the rounds when no pose moves more than this (degrees) ...
    rotation_tolerance_deg: float = 0.005
    # ... and this (in units of voxel_size) between two rounds
    translation_tolerance: float = 0.005
    # Levenberg–Marquardt iterations per round at most
    max_iterations: int = 30

    def __post_init__(self) -> None:
        fn, kind = "RegisterConfig", "field"
        for name in ("voxel_size", "track_radius", "loss_scale"):
            _checks.check_real(fn, name, getattr(self, name), low=0, low_open=True, kind=kind)
        _checks.check_real(
            fn, "tangent_weight", self.tangent_weight, low=0, high=1, low_open=True, kind=kind
        )
        _checks.check_real(fn, "min_overlap", self.min_overlap, low=0, high=1, kind=kind)
        for name in ("rotation_tolerance_deg", "translation_tolerance"):
            _checks.check_real(fn, name, getattr(self, name), low=0, kind=kind)
        if self.boundary_threshold is not None:
            _checks.check_real(
                fn, "boundary_threshold", self.boundary_threshold, low=0, low_open=True, kind=kind
            )
        _checks.check_int(fn, "hypotheses", self.hypotheses, minimum=1, kind=kind)
        _checks.check_int(fn, "normal_neighbors", self.normal_neighbors, minimum=3, kind=kind)
        _checks.check_int(fn, "rounds", self.rounds, minimum=0, kind=kind)
        _checks.check_int(fn, "max_iterations", self.max_iterations, minimum=0, kind=kind)
        if not isinstance(self.loss, str) or self.loss not in ("huber", "cauchy", "none"):
            raise ValueError(
                f"{fn}: field 'loss' must be 'huber', 'cauchy' or 'none', "
                f"got {_checks.describe(self.loss)}"
            )
        if self.stages is not None:
            stages = self.stages
            if isinstance(stages, (str, bytes)) or not isinstance(stages, Sequence):
                raise TypeError(
                    f"{fn}: field 'stages' must be None or a non-empty tuple of icp.Stage, "
                    f"got {_checks.describe(stages)}"
                )
            for k, stage in enumerate(stages):
                if not isinstance(stage, icp.Stage):
                    raise TypeError(
                        f"{fn}: field 'stages' must hold icp.Stage objects, got "
                        f"{_checks.describe(stage)} at index {k}"
                    )
            if not stages:
                raise ValueError(
                    f"{fn}: field 'stages' must be None or a non-empty tuple of icp.Stage, got ()"
                )
            object.__setattr__(self, "stages", tuple(stages))

    def pairwise_stages(self) -> tuple[icp.Stage, ...]:
        """The pairwise ICP levels in force."""
        return default_stages(self.voxel_size) if self.stages is None else self.stages

    def robust_loss(self) -> object | None:
        """The robust kernel object of the joint solve (None for plain least squares)."""
        scale = self.loss_scale * self.voxel_size
        if self.loss == "huber":
            return HuberLoss(scale)
        if self.loss == "cauchy":
            return CauchyLoss(scale)
        return None


# ----------------------------------------------------------------------------- input / output


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


def write_poses(
    path: str | os.PathLike, names: Sequence[str], poses: Tensor, *, frame: str | None = None
) -> None:
    """Write poses T_0i in the documented text format (module docstring).

    Args:
        path: output file.
        names: scan names, m of them (no white space).
        poses: T_0i mapping each scan into the reference frame, shape (m, 4, 4).
        frame: name of the reference scan, for the header comment.

    Raises:
        TypeError: a wrong type (``names`` must be a sequence of str, ``poses`` a float tensor
            or numpy array).
        ValueError: names that are empty, hold white space, start with ``#`` (a comment line
            on reading) or repeat; ``poses`` of the wrong shape, non-finite or not rigid.
    """
    fn = "write_poses"
    path = _checks.check_path(fn, path)
    names = _checks.check_names(fn, names)
    if not names:
        raise ValueError(f"{fn}: argument 'names' must hold at least one name, got none")
    if isinstance(poses, np.ndarray):
        poses = torch.from_numpy(poses)
    _checks.check_batched(
        fn, "poses", poses, ("m",), (4, 4), sizes=(len(names),), against="'names'"
    )
    _checks.check_pose_matrix(fn, "poses", poses)
    if frame is not None and (
        not isinstance(frame, str) or not frame or "\n" in frame or "\r" in frame
    ):
        raise ValueError(
            f"write_poses: argument 'frame' must be None or a one-line name, "
            f"got {_checks.describe(frame)}"
        )
    q = convert.matrix_to_quaternion(poses[:, :3, :3].detach().to(torch.float64))
    q = torch.where(q[:, :1] < 0, -q, q)  # qw ≥ 0
    t = poses[:, :3, 3].detach().to(torch.float64)
    lines = [
        "# torchslam register poses: name tx ty tz qw qx qy qz",
        f"# T_0i maps scan coordinates into the frame of {frame or (names[0] if names else '-')}: "
        "p = R(q) p_scan + t (Hamilton quaternion, scalar first)",
    ]
    for name, ti, qi in zip(names, t.tolist(), q.tolist(), strict=True):
        lines.append(" ".join([name, *(repr(float(x)) for x in (*ti, *qi))]))
    Path(path).write_text("\n".join(lines) + "\n")


def read_poses(
    path: str | os.PathLike, *, dtype: torch.dtype = torch.float64
) -> tuple[list[str], Tensor]:
    """Read a pose file of :func:`write_poses`: ``(names, T_0i of shape (m, 4, 4))``.

    Raises:
        ValueError: a malformed line (field count, a number that is not a finite decimal, a
            zero quaternion), a repeated name, no poses, bytes that are not UTF-8 text; the
            message names the file and the line.
        TypeError: ``path`` is not a str / os.PathLike or ``dtype`` not float32/float64.
        OSError: the file cannot be read.
    """
    fn = "read_poses"
    where = _checks.check_path(fn, path, is_file=True)
    _checks.check_float_dtype(fn, dtype)
    largest = torch.finfo(dtype).max
    with open(where, "rb") as f:
        lines = _text.decode_lines(f.read(), path, fn, "text pose file")
    names: list[str] = []
    rows: list[list[float]] = []
    for number, raw in enumerate(lines, start=1):
        words = raw.split()
        if not words or words[0].startswith("#"):
            continue
        if len(words) != 8:
            raise ValueError(
                f"{fn}: {where}: line {number}: expected 'name tx ty tz qw qx qy qz', got "
                f"{len(words)} fields"
            )
        try:
            values = [_text.parse_finite_float(v) for v in words[1:]]
            q = _text.unit_quaternion(values[3:], "quaternion (qw, qx, qy, qz)")
        except _text.TokenError as error:
            raise ValueError(f"{fn}: {where}: line {number}: {error}") from None
        too_large = [v for v in values[:3] if abs(v) > largest]
        if too_large:
            raise ValueError(
                f"{fn}: {where}: line {number}: translation {too_large[0]!r} overflows {dtype} "
                f"(largest {largest:.4g}); read with dtype=torch.float64"
            )
        if words[0] in names:
            raise ValueError(f"{fn}: {where}: line {number}: scan {words[0]!r} listed twice")
        names.append(words[0])
        rows.append([*values[:3], *q])
    if not rows:
        raise ValueError(f"{fn}: {where}: no poses")
    values_t = torch.tensor(rows, dtype=dtype)
    R = convert.quaternion_to_matrix(values_t[:, 3:])
    return names, se3.from_rotation_translation(R, values_t[:, :3])


# ----------------------------------------------------------------------------- argument checks


def _check_clouds(
    fn: str, clouds: object, *, minimum: int = 1, min_points: int = 1, name: str = "clouds"
) -> list[Tensor]:
    """A list of ≥ ``minimum`` float clouds (N_i, 3), N_i ≥ ``min_points``, of one dtype and
    device, finite when value checks are active."""
    if isinstance(clouds, Tensor) or not isinstance(clouds, Sequence) or isinstance(clouds, str):
        raise TypeError(
            f"{fn}: argument '{name}' must be a list of tensors of shape (N_i, 3), "
            f"got {_checks.describe(clouds)}"
        )
    out = list(clouds)
    if len(out) < minimum:
        raise ValueError(f"{fn}: argument '{name}' must hold ≥ {minimum} clouds, got {len(out)}")
    for k, cloud in enumerate(out):
        if isinstance(cloud, np.ndarray):
            raise TypeError(
                f"{fn}: argument '{name}' must hold torch tensors, got a numpy array at index "
                f"{k}; convert with torch.from_numpy"
            )
        _checks.check_batched(fn, f"{name}[{k}]", cloud, ("N",), (3,))
        if cloud.shape[0] < min_points:
            raise ValueError(
                f"{fn}: argument '{name}[{k}]' must have ≥ {min_points} points, "
                f"got shape {tuple(cloud.shape)}"
            )
        if k:
            _checks.check_same_kind(fn, **{f"{name}[0]": out[0], f"{name}[{k}]": cloud})
        _checks.check_finite(fn, f"{name}[{k}]", cloud)
    return out


def _check_poses(fn: str, poses: object, m: int, against: str = "'clouds'") -> Tensor:
    """T_0i of shape (m, 4, 4), rigid when value checks are active."""
    _checks.check_batched(fn, "poses", poses, ("m",), (4, 4), sizes=(m,), against=against)
    assert isinstance(poses, Tensor)
    _checks.check_pose_matrix(fn, "poses", poses)
    return poses


def _check_config(fn: str, config: object) -> RegisterConfig:
    if config is None:
        return RegisterConfig()
    if not isinstance(config, RegisterConfig):
        raise TypeError(
            f"{fn}: argument 'config' must be a RegisterConfig or None, "
            f"got {_checks.describe(config)}; build one with RegisterConfig(**options)"
        )
    return config


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
    clouds = _check_clouds(fn, clouds, minimum=2, min_points=3)
    config = _check_config(fn, config)
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
    clouds = _check_clouds(fn, clouds)
    m = len(clouds)
    _check_poses(fn, poses, m)
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
    clouds = _check_clouds(fn, clouds, minimum=2, min_points=2)
    _check_poses(fn, poses, len(clouds))
    config = _check_config(fn, config)
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
    config = _check_config(fn, config)
    m = len(refinement.track_clouds)
    _check_poses(fn, poses, m, against="the refinement's scans")
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


def plane_distances(
    clouds: Sequence[Tensor],
    poses: Tensor,
    pairs: Sequence[tuple[int, int]],
    distance: float,
    normal_neighbors: int = 12,
) -> np.ndarray:
    """Signed point-to-plane distances between overlapping scans (see :func:`alignment_residual`).

    Returns:
        One distance per corresponding point, float64 array (K,), in the clouds' units.
    """
    return _plane_distances("plane_distances", clouds, poses, pairs, distance, normal_neighbors)


def _plane_distances(
    fn: str,
    clouds: Sequence[Tensor],
    poses: Tensor,
    pairs: Sequence[tuple[int, int]],
    distance: float,
    normal_neighbors: int,
) -> np.ndarray:
    clouds = _check_clouds(fn, clouds, min_points=3)
    m = len(clouds)
    _check_poses(fn, poses, m)
    poses = poses.to(clouds[0].dtype)
    pairs = _checks.check_index_pairs(fn, pairs, m)
    distance = _checks.check_real(fn, "distance", distance, low=0, low_open=True)
    normal_neighbors = _checks.check_int(fn, "normal_neighbors", normal_neighbors, minimum=3)
    normals = [icp.estimate_normals(c, min(normal_neighbors, len(c))) for c in clouds]
    world = [se3.act(poses[i], clouds[i]).detach().cpu().numpy() for i in range(m)]
    world_normals = [(normals[i] @ poses[i, :3, :3].T).detach().cpu().numpy() for i in range(m)]
    trees = [cKDTree(w) for w in world]
    out = [np.zeros(0)]
    for a, b in pairs:
        for i, k in ((a, b), (b, a)):
            d, j = trees[k].query(world[i], distance_upper_bound=distance)
            inside = np.isfinite(d)
            offset = world[i][inside] - world[k][j[inside]]
            out.append((offset * world_normals[k][j[inside]]).sum(-1))
    return np.concatenate(out)


def alignment_residual(
    clouds: Sequence[Tensor],
    poses: Tensor,
    pairs: Sequence[tuple[int, int]],
    distance: float,
    normal_neighbors: int = 12,
) -> float:
    """RMS point-to-plane distance between overlapping scans: a consistency check of poses.

    For every ordered pair (i, k) of ``pairs`` (both directions), each point of scan i whose
    nearest point of scan k (world frame) lies within ``distance`` contributes its distance
    to the tangent plane of scan k there (PCA normal). Independent of any point tracks.

    Args:
        clouds: m clouds in their scan frames, shapes (N_i, 3).
        poses: T_0i, shape (m, 4, 4).
        pairs: scan pairs.
        distance: correspondence gate, > 0.
        normal_neighbors: k of the PCA normals.

    Returns:
        The RMS distance, in the clouds' units (nan when no point corresponds).
    """
    d = _plane_distances("alignment_residual", clouds, poses, pairs, distance, normal_neighbors)
    return float(np.sqrt(np.mean(d**2))) if len(d) else math.nan


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
    clouds = _check_clouds(fn, clouds, minimum=2, min_points=3)
    if len(names) != len(clouds):
        raise ValueError(
            f"{fn}: argument 'names' must hold one name per cloud, got {len(names)} names for "
            f"{len(clouds)} clouds"
        )
    config = _check_config(fn, config)
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


# ----------------------------------------------------------------------------- reporting


def error_table(
    names: Sequence[str],
    frame: int,
    reference: Tensor,
    columns: dict[str, Tensor],
    include: Sequence[int] | None = None,
) -> tuple[str, dict[str, dict[str, float]]]:
    """Per-scan rotation (degrees) and translation (mm, for scans in metres) error table.

    Args:
        names: scan names, m.
        frame: index of the scan whose frame both pose sets are compared in.
        reference: reference T_0i (any common frame), shape (m, 4, 4).
        columns: label → estimated T_0i (m, 4, 4).
        include: scans in the mean/max rows; all but ``frame`` by default.

    Returns:
        ``(text, summary)`` with summary[label] = {"rot_mean", "rot_max", "trans_mean",
        "trans_max"} (degrees, mm).
    """
    fn = "error_table"
    names = _checks.check_names(fn, names, words=False)
    m = len(names)
    if m == 0:
        raise ValueError(f"{fn}: argument 'names' must hold at least one name, got none")
    frame = _checks.check_int(fn, "frame", frame, minimum=0, maximum=m - 1)
    _check_poses(fn, reference, m, against="'names'")
    if not isinstance(columns, dict) or not columns:
        raise TypeError(
            f"{fn}: argument 'columns' must be a non-empty dict label → poses (m, 4, 4), "
            f"got {_checks.describe(columns)}"
        )
    for label, poses in columns.items():
        if not isinstance(label, str):
            raise TypeError(f"{fn}: argument 'columns' must have str labels, got {label!r}")
        _checks.check_batched(fn, f"columns[{label!r}]", poses, ("m",), (4, 4), sizes=(m,))
        _checks.check_pose_matrix(fn, f"columns[{label!r}]", poses)
    if include is None:
        include = [i for i in range(m) if i != frame]
    else:
        if isinstance(include, (str, Tensor)) or not isinstance(include, Sequence):
            raise TypeError(
                f"{fn}: argument 'include' must be None or a list of scan indices, "
                f"got {_checks.describe(include)}"
            )
        include = [
            _checks.check_int(fn, f"include[{k}]", i, minimum=0, maximum=m - 1)
            for k, i in enumerate(include)
        ]
    if not include:
        raise ValueError(f"{fn}: no scans to summarize ('include' is empty or only 'frame')")
    errors = {}
    for label, poses in columns.items():
        rotation, translation = pose_errors(poses.to(reference.dtype), reference, frame)
        errors[label] = (rotation, translation * 1000)
    head = f"{'scan':<10}" + "".join(
        f" {label + ' rot°':>14} {label + ' mm':>12}" for label in errors
    )
    lines = [head]
    for i, name in enumerate(names):
        mark = "" if i in include or i == frame else " *"
        row = f"{name + mark:<10}"
        for rotation, translation in errors.values():
            row += f" {float(rotation[i]):14.3f} {float(translation[i]):12.3f}"
        lines.append(row)
    summary: dict[str, dict[str, float]] = {}
    index = torch.tensor(include, dtype=torch.int64)
    for key in ("mean", "max"):
        row = f"{key:<10}"
        for label, (rotation, translation) in errors.items():
            r, t = rotation[index], translation[index]
            r_value = float(r.mean() if key == "mean" else r.max())
            t_value = float(t.mean() if key == "mean" else t.max())
            summary.setdefault(label, {})[f"rot_{key}"] = r_value
            summary[label][f"trans_{key}"] = t_value
            row += f" {r_value:14.3f} {t_value:12.3f}"
        lines.append(row)
    return "\n".join(lines), summary


_PALETTE = np.array(
    [
        [31, 119, 180],
        [255, 127, 14],
        [44, 160, 44],
        [214, 39, 40],
        [148, 103, 189],
        [140, 86, 75],
        [227, 119, 194],
        [127, 127, 127],
        [188, 189, 34],
        [23, 190, 207],
    ],
    dtype=np.uint8,
)


def scan_colors(count: int) -> np.ndarray:
    """One RGB colour (uint8) per scan, shape (count, 3) (matplotlib's tab10, repeating)."""
    count = _checks.check_int("scan_colors", "count", count, minimum=0)
    return _PALETTE[np.arange(count) % len(_PALETTE)]


def merged_cloud(clouds: Sequence[Tensor], poses: Tensor) -> tuple[np.ndarray, np.ndarray]:
    """All clouds moved into the common frame, with one colour per scan: (N, 3), (N, 3) uint8."""
    clouds = _check_clouds("merged_cloud", clouds)
    poses = _check_poses("merged_cloud", poses, len(clouds)).to(clouds[0].dtype)
    colors = scan_colors(len(clouds))
    points = [se3.act(poses[i], c).detach().cpu().numpy() for i, c in enumerate(clouds)]
    rgb = [np.repeat(colors[i][None], len(p), axis=0) for i, p in enumerate(points)]
    return np.concatenate(points), np.concatenate(rgb)


def plot_registration(registration: Registration, path: str | os.PathLike) -> None:
    """Figure of a registration: chained pairwise ICP (row 1) vs joint ICP-SLAM (row 2).

    Columns: top view (x, z) and side view (x, y) of the merged downsampled cloud, coloured by
    scan, in the axes of the reference scan (mm for scans in metres); a section, the slab
    |z − z_mid| < one voxel through the middle of the cloud, where misregistration shows as
    doubled contours; and two diagnostics: the histogram of point-to-plane distances between
    overlapping scans (chained and joint, row 1) and the change of every pose from chained to
    joint (row 2: rotation in degrees, translation in mm).

    Raises:
        torchslam.cli.plots.MatplotlibMissingError: matplotlib is not installed.
    """
    plt = _plotting.require_pyplot()

    reg = registration
    colors = scan_colors(len(reg.names)) / 255.0
    scale = 1000.0  # metres → mm
    voxel = reg.voxel_size * scale
    rows = (
        ("chained pairwise ICP", reg.chained, reg.residual_chained),
        ("joint ICP-SLAM", reg.poses, reg.residual_joint),
    )
    worlds = [
        [se3.act(poses[i], c).detach().cpu().numpy() * scale for i, c in enumerate(reg.clouds)]
        for _, poses, _ in rows
    ]
    z_mid = float(np.median(np.concatenate(worlds[1])[:, 2]))
    fig, axes = plt.subplots(2, 4, figsize=(20, 9.5), gridspec_kw={"width_ratios": [1, 1, 1, 0.9]})
    for row, ((title, _, residual), world) in enumerate(zip(rows, worlds, strict=True)):
        inside = [np.abs(p[:, 2] - z_mid) < voxel for p in world]
        panels = (
            ("top view", [(p[:, 0], p[:, 2]) for p in world], ("x", "z"), 0.25),
            ("side view", [(p[:, 0], p[:, 1]) for p in world], ("x", "y"), 0.25),
            (
                f"section |z − {z_mid:.0f}| < {voxel:g} mm",
                [(p[k, 0], p[k, 1]) for p, k in zip(world, inside, strict=True)],
                ("x", "y"),
                2.5,
            ),
        )
        for col, (name, series, (u, v), size) in enumerate(panels):
            ax = axes[row, col]
            for i, (x, y) in enumerate(series):
                ax.scatter(x, y, s=size, color=colors[i], linewidths=0, alpha=0.8)
            ax.set_aspect("equal")
            ax.set_xlabel(f"{u} (mm)")
            ax.set_ylabel(f"{v} (mm)")
            ax.set_title(f"{title}: {name}", fontsize=11)
        axes[row, 0].annotate(
            f"point-to-plane RMS between overlapping scans {residual * scale:.3f} mm",
            xy=(0.02, 0.02),
            xycoords="axes fraction",
            fontsize=9,
        )

    ax = axes[0, 3]
    pairs = reg.refinement.pairs
    bins = np.linspace(-3 * voxel / 4, 3 * voxel / 4, 61)
    for (title, poses, residual), color in zip(rows, ("tab:gray", "tab:blue"), strict=True):
        d = plane_distances(reg.refinement.track_clouds, poses, pairs, reg.voxel_size) * scale
        ax.hist(
            d,
            bins=bins,
            histtype="step",
            linewidth=1.5,
            color=color,
            label=f"{title} (RMS {residual * scale:.3f} mm)",
        )
    ax.set_xlabel("point-to-plane distance (mm)")
    ax.set_ylabel("points")
    ax.set_title("consistency of the overlaps", fontsize=11)
    ax.legend(fontsize=8, loc="upper left")

    ax = axes[1, 3]
    change = se3.compose(se3.inverse(reg.chained), reg.poses)
    rotation = torch.rad2deg(torch.linalg.vector_norm(se3.log(change)[:, :3], dim=-1))
    translation = torch.linalg.vector_norm(reg.poses[:, :3, 3] - reg.chained[:, :3, 3], dim=-1)
    x = np.arange(len(reg.names))
    ax.bar(x - 0.2, rotation.numpy(), 0.4, color="tab:blue", label="rotation (°)")
    ax.bar(x + 0.2, translation.numpy() * scale, 0.4, color="tab:orange", label="translation (mm)")
    ax.set_xticks(x, reg.names, rotation=60, fontsize=8)
    ax.set_title(f"pose change chained → joint (frame {reg.names[reg.frame]})", fontsize=11)
    ax.legend(fontsize=8)

    handles = [
        plt.Line2D([], [], marker="o", linestyle="", color=colors[i], label=n)
        for i, n in enumerate(reg.names)
    ]
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 10), frameon=False)
    fig.suptitle(
        f"{len(reg.names)} scans ({voxel:g} mm voxels) in the frame of "
        f"{reg.names[reg.frame]}: chained pairwise ICP (top) vs joint ICP-SLAM (bottom)"
    )
    fig.tight_layout(rect=(0, 0.04, 1, 0.97))
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ----------------------------------------------------------------------------- command line


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``torchslam register``."""
    from torchslam.cli import float_range, int_range

    parser.add_argument("scans", nargs="+", type=Path, help="PLY scans in chain order (≥ 2)")
    parser.add_argument(
        "--reference", type=Path, default=None, help="Stanford .conf alignment to compare with"
    )
    parser.add_argument("--out", type=Path, default=Path("out"), help="output folder (out)")
    parser.add_argument(
        "--frame", default=None, help="scan whose frame the poses are in (default: the first)"
    )
    parser.add_argument(
        "--voxel-size",
        type=float_range(0.0, 1e6, low_open=True),
        default=0.002,
        help="finest voxel pitch, scan units (0, 1e6] (0.002)",
    )
    parser.add_argument(
        "--hypotheses", type=int_range(1, 10_000), default=128, help="starts per pair (128)"
    )
    parser.add_argument(
        "--rounds", type=int_range(0, 100), default=4, help="joint rounds at most [0, 100] (4)"
    )
    parser.add_argument(
        "--threads", type=int_range(1, 1024), default=1, help="torch threads [1, 1024] (1)"
    )


def _stderr(line: str) -> None:
    print(line, file=sys.stderr)


def run(
    args: argparse.Namespace,
    echo: Callable[[str], None] = print,
    warn: Callable[[str], None] = _stderr,
) -> int:
    """Run ``torchslam register``: progress lines, poses, merged PLY, PNG, optional table.

    Returns the exit status: 0, or 1 when a joint solve ended ``NON_FINITE`` or
    ``LINEAR_SOLVE_FAILED`` (outputs are still written; :mod:`torchslam.cli`). Without
    matplotlib the figure is skipped with one ``figure skipped: …`` line through ``warn``.

    Raises:
        ValueError: bad option values or input files. OSError: unreadable or unwritable files.
    """
    if args.threads < 1:
        raise ValueError(f"--threads must be ≥ 1, got {args.threads}")
    if not (args.voxel_size > 0 and math.isfinite(args.voxel_size)):
        raise ValueError(f"--voxel-size must be > 0, got {args.voxel_size}")
    if args.hypotheses < 1:
        raise ValueError(f"--hypotheses must be ≥ 1, got {args.hypotheses}")
    if args.rounds < 0:
        raise ValueError(f"--rounds must be ≥ 0, got {args.rounds}")
    if len(args.scans) < 2:
        raise ValueError(f"need at least 2 scans, got {len(args.scans)}")
    expected = [scan_name(p) for p in args.scans]
    frame = expected[0] if args.frame is None else args.frame
    if frame not in expected:
        raise ValueError(f"--frame {frame!r} is not among the scans ({', '.join(expected)})")
    if args.out.exists() and not args.out.is_dir():
        raise ValueError(f"--out {args.out} exists and is not a directory")
    config = RegisterConfig(
        voxel_size=args.voxel_size, hypotheses=args.hypotheses, rounds=args.rounds
    )
    threads = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    try:
        return _run(args, config, expected, frame, echo, warn)
    finally:
        torch.set_num_threads(threads)


def _run(
    args: argparse.Namespace,
    config: RegisterConfig,
    expected: list[str],
    frame: str,
    echo: Callable[[str], None],
    warn: Callable[[str], None],
) -> int:
    start = time.perf_counter()
    reference = None
    if args.reference is not None:
        if not args.reference.is_file():
            raise FileNotFoundError(f"no such reference file: {args.reference}")
        reference = read_conf(args.reference)
        missing = [n for n in expected if n not in reference]
        if missing:
            raise ValueError(f"{args.reference}: no pose for scan(s) {', '.join(missing)}")
    echo(f"[1/5] reading {len(args.scans)} scans …")
    names, clouds = load_scans(args.scans)
    echo(f"      {', '.join(f'{n} ({len(c)})' for n, c in zip(names, clouds, strict=True))}")
    stage = iter(("[2/5]", "[3/5]", "[4/5]"))

    def progress(line: str) -> None:
        prefix = "     " if line.startswith(" ") else next(stage, "     ")
        echo(f"{prefix} {line}")

    registration = register(names, clouds, config, frame=frame, progress=progress)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    echo(f"[5/5] writing {out} …")
    write_poses(out / "poses.txt", names, registration.poses, frame=frame)
    write_poses(out / "poses_chained.txt", names, registration.chained, frame=frame)
    points, colors = merged_cloud(registration.clouds, registration.poses)
    legend = [
        f"scan {n} rgb {' '.join(map(str, c))}"
        for n, c in zip(names, scan_colors(len(names)), strict=True)
    ]
    write_ply(out / "merged.ply", points, colors, coordinate_type="float", comments=legend)
    written = ["poses.txt", "poses_chained.txt", f"merged.ply ({len(points)} points)"]
    try:
        plot_registration(registration, out / "registration.png")
    except _plotting.MatplotlibMissingError as error:
        warn(f"figure skipped: {error}")
    else:
        written.append("registration.png")
    echo(f"      {', '.join(written)}")
    echo(
        f"point-to-plane RMS between overlapping scans: chained "
        f"{registration.residual_chained:.4g} → joint {registration.residual_joint:.4g}"
    )
    if reference is not None:
        reference_poses = stack(reference, names)
        text, _ = error_table(
            names,
            registration.frame,
            reference_poses,
            {"chain": registration.chained, "joint": registration.poses},
        )
        echo(f"errors vs {args.reference} in the frame of {frame} (mm assumes metres):")
        echo(text)
    echo(f"total {time.perf_counter() - start:.1f} s")
    for pair, result in zip(
        itertools.pairwise(names), registration.chain.pair_results, strict=True
    ):
        if int(result.status) == icp.ICPStatus.TOO_FEW_CORRESPONDENCES:
            warn(f"warning: pairwise ICP {pair[0]} ← {pair[1]}: {result.reason}")
    from torchslam.cli import solve_exit_status

    statuses = [info.status for info in registration.refinement.rounds]
    return solve_exit_status(statuses, warn, "a joint solve")


def main(argv: list[str] | None = None) -> int:
    """``python -m torchslam.registration.pipeline``: the same as ``torchslam register``."""
    from torchslam import cli

    return cli.main(["register", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    raise SystemExit(main())
