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
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from torch import Tensor

from torchslam import _checks
from torchslam.io.ply import read_ply_points
from torchslam.io.stanford import relative_to_first, scan_name
from torchslam.lie import se3
from torchslam.problem import PointMapProblem
from torchslam.registration import icp
from torchslam.registration.config import (
    RegisterConfig,
    ScanScale,
    auto_voxel_size,
    check_clouds,
    check_config,
    check_poses,
    scan_scale,
)
from torchslam.registration.kdtree import KDTree
from torchslam.registration.neighbors import _boundary_from_neighbours
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
    "register_tree",
]

Progress = Callable[[str], None]


# ----------------------------------------------------------------------------- input


def load_scans(
    paths: Sequence[str | os.PathLike],
    *,
    dtype: torch.dtype = torch.float64,
    nonfinite: str = "drop",
    return_dropped: bool = False,
) -> tuple[list[str], list[Tensor]] | tuple[list[str], list[Tensor], list[int]]:
    """Read scans: PLY (vertex coordinates, the strict reader :func:`read_ply_points`), PCD,
    XYZ/TXT/PTS, NPY and KITTI ``.bin`` (:func:`torchslam.io.frames.read_points`, which drops
    non-finite points: missed returns).

    Args:
        paths: the files, ≥ 2, with distinct base names.
        nonfinite: ``"drop"`` (default) removes points with a NaN/±Inf coordinate (sensor
            clouds mark missed returns so), in PLY files too; ``"raise"`` refuses such a file.
        return_dropped: also return the number of points dropped from each scan.
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
    if nonfinite not in ("drop", "raise"):
        raise ValueError(
            f"{fn}: argument 'nonfinite' must be 'drop' or 'raise', got "
            f"{_checks.describe(nonfinite)}"
        )
    clouds: list[Tensor] = []
    dropped: list[int] = []
    for path in paths:
        if os.path.isdir(path):
            raise ValueError(f"{fn}: argument 'paths' holds a directory, not a scan: {path}")
        if not os.path.isfile(path):
            raise FileNotFoundError(f"{fn}: no such scan file: {path}")
        from torchslam.io.frames import read_points

        dropped_here = 0
        if path.lower().endswith(".ply"):
            try:
                cloud = read_ply_points(path, dtype=dtype)
            except ValueError as error:
                # The strict reader refuses NaN/Inf; sensor clouds hold them for missed returns.
                if nonfinite == "raise" or "finite" not in str(error):
                    raise
                cloud, dropped_here = read_points(
                    path, dtype=dtype, nonfinite="drop", return_dropped=True
                )
        else:
            cloud, dropped_here = read_points(
                path, dtype=dtype, nonfinite=nonfinite, return_dropped=True
            )
        dropped.append(dropped_here)
        if cloud.shape[0] < 10:
            raise ValueError(f"{fn}: {path}: only {cloud.shape[0]} points, need ≥ 10")
        if not bool(torch.isfinite(cloud).all()):
            raise ValueError(f"{fn}: {path}: non-finite vertex coordinates")
        clouds.append(cloud)
    return (names, clouds, dropped) if return_dropped else (names, clouds)


# ----------------------------------------------------------------------------- pairwise chain


@dataclass
class ChainResult:
    """Pairwise ICP along a chain or a spanning tree of the scans, and the chained poses.

    For a chain (``register_chain``) edge k is (k, k + 1); for scans in any order
    (:func:`register_tree`) the edges of the maximum spanning tree, parent first.
    """

    # T̂_(p,c) mapping scan c into scan p for each edge (p, c), shape (m − 1, 4, 4)
    relative: Tensor
    # T̂_0i: the relative poses composed from scan 0 to scan i, mapping scan i into scan 0,
    # shape (m, 4, 4)
    poses: Tensor
    # per edge: the ICP result of the last level (fitness/rms at its yardstick distance)
    pair_results: list[icp.ICPResult]
    # per edge: wall seconds
    pair_seconds: list[float]
    # the edges (parent, child); None means the chain (k, k + 1)
    edges: list[tuple[int, int]] | None = None
    # order "any": symmetric overlap score of every pair after the coarse level, (m, m), and
    # after the fine levels for the candidate pairs (nan where not registered finely)
    coarse_score: Tensor | None = None
    fine_score: Tensor | None = None

    @property
    def tree_edges(self) -> list[tuple[int, int]]:
        """The edges (parent, child): the chain's (k, k + 1) or the spanning tree's."""
        if self.edges is not None:
            return list(self.edges)
        return [(k, k + 1) for k in range(self.relative.shape[0])]


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
    config = check_config(fn, config).resolved(clouds, fn)
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


def _bar(items: list, description: str, enabled: bool):
    """``items``, under a tqdm progress bar on stderr when ``enabled``."""
    if not enabled or not items:
        return items
    import sys

    from tqdm import tqdm

    return tqdm(items, desc=description, unit="pair", leave=False, file=sys.stderr)


def register_tree(
    clouds: Sequence[Tensor],
    config: RegisterConfig | None = None,
    progress: Progress | None = None,
    names: Sequence[str] | None = None,
    *,
    progress_bar: bool = False,
) -> ChainResult:
    """Initial poses of scans in any order: coarse alignment of every pair, an overlap graph
    and its maximum spanning tree.

    1. **Coarse level, all pairs.** Every pair (i, k), i < k, runs the first pairwise level
       (``hypotheses`` rotations spread over SO(3), centroids aligned, point-to-plane ICP on
       the coarsest voxels) and is scored by its *symmetric overlap*: the smaller of the two
       fractions of points within the level's yardstick of the other scan.
    2. **Fine levels, candidate pairs.** Each scan's ``candidates`` best partners by that
       score are refined through the remaining levels from the coarse level's best
       hypotheses and scored again at the finest yardstick (one voxel).
    3. **Maximum spanning tree** of the fine scores (Kruskal): the most reliable pairs that
       connect all scans; the initial poses compose the tree's relative poses from scan 0.

    Wrong pairwise alignments (a partial view matched to the wrong side of an object) overlap
    less than right ones, so the tree avoids them while right ones exist; the joint
    refinement then uses every pair that overlaps at these poses, not only the tree's.

    Args:
        clouds: m ≥ 2 scans in any order, shapes (N_i, 3), in their own frames; tensors or
            numpy arrays.
        config: options (``voxel_size`` None: derived from the scans; ``hypotheses``,
            ``stages``, ``candidates``).
        progress: called with one line per step.
        names: scan names for the progress lines.
        progress_bar: a tqdm bar on stderr over the pairs of the coarse and fine stages.

    A pair joining two groups of scans is left out when most other registered pairs between
    those groups (weighted by their scores) contradict it — unless no other pair joins them.
    Pairwise scores cannot tell the views of a near-symmetric object apart when most of its
    pairs match the mirror side; give such scans in chain order (``order="chain"``).

    Returns:
        :class:`ChainResult` with the tree's edges, poses in the frame of scan 0.

    Raises:
        ValueError: bad arguments; scans that no pair connects (no overlap found).
    """
    fn = "register_tree"
    clouds = check_clouds(fn, clouds, minimum=2, min_points=3)
    config = check_config(fn, config).resolved(clouds, fn)
    m = len(clouds)
    if names is not None:
        names = _checks.check_names(fn, names, count=m, words=False)
    if progress is not None and not callable(progress):
        raise TypeError(f"{fn}: argument 'progress' must be callable or None")
    label = list(names) if names is not None else [str(k) for k in range(m)]
    say = progress or (lambda _line: None)
    stages = config.pairwise_stages()
    rotations = icp.rotations_uniform(config.hypotheses, dtype=clouds[0].dtype)
    levels = [_level(fn, clouds, stage) for stage in stages]
    tic = time.perf_counter()
    coarse = torch.full((m, m), math.nan, dtype=torch.float64)
    kept: dict[tuple[int, int], Tensor] = {}
    first = stages[0]
    all_pairs = list(itertools.combinations(range(m), 2))
    for i, k in _bar(all_pairs, "coarse alignment of all pairs", progress_bar):
        (src, tgt), normals = (levels[0][0][k], levels[0][0][i]), levels[0][1][i]
        initial = icp.initial_guesses(clouds[k], clouds[i], rotations)
        runs = icp._run(fn, src, tgt, initial, first.config, normals)
        best, order = icp._select(runs, src, tgt, _yardstick(first), fn)
        coarse[i, k] = coarse[k, i] = _symmetric_overlap(
            fn, best.transform, src, tgt, _yardstick(first)
        )
        kept[(i, k)] = runs.transform[order[: first.keep]]
    say(
        f"coarse alignment of all {len(kept)} pairs ({config.hypotheses} starts each, "
        f"{first.voxel_size:g} voxels): {time.perf_counter() - tic:.1f} s"
    )
    candidates: set[tuple[int, int]] = set()
    for i in range(m):
        others = [k for k in range(m) if k != i]
        others.sort(key=lambda k: (-float(coarse[i, k]), k))
        for k in others[: config.candidates]:
            candidates.add((min(i, k), max(i, k)))
    fine = torch.full((m, m), math.nan, dtype=torch.float64)
    results: dict[tuple[int, int], tuple[icp.ICPResult, float]] = {}
    tic = time.perf_counter()
    for i, k in _bar(sorted(candidates), "refining the candidate pairs", progress_bar):
        start = time.perf_counter()
        hypotheses = kept[(i, k)]
        best = None
        for stage, ((small, normal_sets)) in zip(stages[1:], levels[1:], strict=True):
            src, tgt = small[k], small[i]
            runs = icp._run(fn, src, tgt, hypotheses, stage.config, normal_sets[i])
            best, order = icp._select(runs, src, tgt, _yardstick(stage), fn)
            hypotheses = runs.transform[order[: stage.keep]]
        if best is None:  # a single level: the coarse result
            src, tgt = levels[0][0][k], levels[0][0][i]
            runs = icp._run(fn, src, tgt, hypotheses[:1], first.config, levels[0][1][i])
            best, _ = icp._select(runs, src, tgt, _yardstick(first), fn)
        last = levels[-1][0]
        fine[i, k] = fine[k, i] = _symmetric_overlap(
            fn, best.transform, last[k], last[i], _yardstick(stages[-1])
        )
        results[(i, k)] = (best, time.perf_counter() - start)
    say(
        f"fine alignment of {len(candidates)} candidate pairs (each scan's best "
        f"{config.candidates}): {time.perf_counter() - tic:.1f} s"
    )
    voxel = config.voxel
    centroids = torch.stack([c.mean(0) for c in clouds]).to(torch.float64).cpu()
    transforms = {p: r.transform.detach().to(torch.float64).cpu() for p, (r, _) in results.items()}
    edges, rejected = _maximum_spanning_tree(
        m, {p: float(fine[p]) for p in candidates}, transforms, centroids, (5.0, 5 * voxel)
    )
    for a, b in rejected:
        say(
            f"  pair {label[a]} – {label[b]} (overlap {float(fine[a, b]):.3f}) left out: "
            "it contradicts the pairs around it"
        )
    if len(edges) < m - 1:
        # Scans the candidates leave apart: try the remaining pairs by their coarse score.
        reached = _components(m, edges)
        apart = ", ".join(label[k] for k in range(m) if reached[k] != reached[0])
        raise ValueError(
            f"{fn}: the scans fall apart into {len(set(reached))} groups that no registered "
            f"pair connects ({apart} vs {label[0]}); do they overlap? Try more candidates "
            "or hypotheses"
        )
    relative, pair_results, pair_seconds = [], [], []
    poses: list[Tensor | None] = [None] * m
    poses[0] = se3.identity(dtype=clouds[0].dtype, device=clouds[0].device)
    for parent, child in edges:
        best, seconds = results[(min(parent, child), max(parent, child))]
        T = best.transform if parent < child else se3.inverse(best.transform)
        relative.append(T)
        pair_results.append(best)
        pair_seconds.append(seconds)
        parent_pose = poses[parent]
        assert parent_pose is not None
        poses[child] = se3.compose(parent_pose, T)
        score = float(fine[parent, child])
        warning = " (low: do these scans overlap?)" if score < 0.2 else ""
        say(f"  tree edge {label[parent]} ← {label[child]}: overlap {score:.3f}{warning}")
    return ChainResult(
        torch.stack(relative),
        torch.stack([p for p in poses if p is not None]),
        pair_results,
        pair_seconds,
        edges,
        coarse,
        fine,
    )


def _level(
    fn: str, clouds: Sequence[Tensor], stage: icp.Stage
) -> tuple[list[Tensor], list[Tensor | None]]:
    """The clouds of one pairwise level and, for point-to-plane, their normals."""
    small = [
        icp._downsample(fn, c, stage.voxel_size) if stage.voxel_size > 0 else c for c in clouds
    ]
    for k, c in enumerate(small):
        if c.shape[0] < 3:
            raise ValueError(
                f"{fn}: scan {k} keeps {c.shape[0]} points on the {stage.voxel_size:g} voxel "
                "grid, need ≥ 3; use a smaller voxel size"
            )
    normals: list[Tensor | None] = [None] * len(small)
    if stage.config.method == "point_to_plane":
        normals = [
            icp._normals(fn, c, min(stage.normal_neighbors, c.shape[0]), None) for c in small
        ]
    return small, normals


def _yardstick(stage: icp.Stage) -> float:
    return stage.voxel_size if stage.fitness_distance is None else stage.fitness_distance


def _symmetric_overlap(
    fn: str, T: Tensor, source: Tensor, target: Tensor, distance: float
) -> float:
    """min(fraction of source within ``distance`` of target at T, and the reverse)."""
    forward, _ = icp._fitness(T[None], source, target, distance, fn)
    backward, _ = icp._fitness(se3.inverse(T)[None], target, source, distance, fn)
    return float(torch.minimum(forward, backward)[0])


def _components(m: int, edges: Sequence[tuple[int, int]]) -> list[int]:
    """The connected component (its smallest scan index) of every scan."""
    parent = list(range(m))

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a, b in edges:
        ra, rb = root(a), root(b)
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    return [root(a) for a in range(m)]


def _maximum_spanning_tree(
    m: int,
    scores: dict[tuple[int, int], float],
    transforms: dict[tuple[int, int], Tensor],
    centroids: Tensor,
    tolerance: tuple[float, float],
) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """Kruskal on descending scores (ties by index) with a loop check, then oriented away
    from scan 0: ``(edges (parent, child) in breadth-first order, rejected pairs)``.

    ``transforms[(i, k)]`` (i < k) maps scan k into scan i. An edge that joins two groups
    of scans is accepted unless the other registered pairs between the two groups mostly
    disagree with it (weighted by their scores): a pair (x, y) agrees when its own
    transform and the one the joined tree predicts differ by at most ``tolerance`` =
    (degrees, distance moved by y's centroid). A wrong match of two views (e.g. the back of
    a near-symmetric object matched to its front) scores well on its own but contradicts
    the pairs around it.
    """
    group = list(range(m))  # scan → its group's label
    # pose of every scan in the frame of its group's first scan (identity for singletons)
    frame = [torch.eye(4, dtype=centroids.dtype) for _ in range(m)]
    chosen, rejected = [], []
    finite = [(p, s) for p, s in scores.items() if math.isfinite(s) and s > 0]
    for (a, b), _ in sorted(finite, key=lambda item: (-item[1], item[0])):
        ga, gb = group[a], group[b]
        if ga == gb:
            continue
        # Members of b's group in the frame of a's group: X ↦ F_a T_ab F_b⁻¹ X.
        bridge = frame[a] @ transforms[(a, b)] @ torch.linalg.inv(frame[b])
        agree = disagree = 0.0
        for (x, y), score in finite:
            if (x, y) == (a, b) or {group[x], group[y]} != {ga, gb}:
                continue
            fx = frame[x] if group[x] == ga else bridge @ frame[x]
            fy = frame[y] if group[y] == ga else bridge @ frame[y]
            predicted = torch.linalg.inv(fx) @ fy  # maps y into x
            error = torch.linalg.inv(transforms[(x, y)]) @ predicted
            cos = ((error[0, 0] + error[1, 1] + error[2, 2] - 1) / 2).clamp(-1.0, 1.0)
            angle = math.degrees(math.acos(float(cos)))
            c = centroids[y]
            shift = float(torch.linalg.vector_norm(error[:3, :3] @ c + error[:3, 3] - c))
            if angle <= tolerance[0] and shift <= tolerance[1]:
                agree += score
            else:
                disagree += score
        if disagree > agree:
            rejected.append((a, b))
            continue
        for k in range(m):
            if group[k] == gb:
                frame[k] = bridge @ frame[k]
                group[k] = ga
        chosen.append((a, b))
    # Groups that only contradicted pairs join: the best of those edges, unchecked.
    for a, b in list(rejected):
        ga, gb = group[a], group[b]
        if ga != gb:
            for k in range(m):
                if group[k] == gb:
                    group[k] = ga
            chosen.append((a, b))
            rejected.remove((a, b))
    neighbours: dict[int, list[int]] = {k: [] for k in range(m)}
    for a, b in chosen:
        neighbours[a].append(b)
        neighbours[b].append(a)
    oriented, seen, queue = [], {0}, [0]
    while queue:
        a = queue.pop(0)
        for b in sorted(neighbours[a]):
            if b not in seen:
                seen.add(b)
                oriented.append((a, b))
                queue.append(b)
    return oriented, rejected


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
    trees = [KDTree(w) for w in world]
    overlap = np.eye(m)
    for i, k in itertools.permutations(range(m), 2):
        d, _ = trees[k].query(world[i], distance_upper_bound=distance, workers=icp.query_workers())
        overlap[i, k] = float(np.isfinite(d).mean())
    pairs = [
        (i, k)
        for i, k in itertools.combinations(range(m), 2)
        if min(overlap[i, k], overlap[k, i]) >= min_overlap
    ]
    return pairs, torch.from_numpy(overlap)


def boundary_mask(
    points: Tensor, neighbors: int = 12, threshold: float = 0.3, normals: Tensor | None = None
) -> Tensor:
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
        normals: unit normals of ``points`` (N, 3), any sign (e.g. from
            :func:`~torchslam.registration.neighbors.estimate_normals` with the same
            ``neighbors``), instead of the PCA of each neighbourhood here.

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
    if normals is not None:
        normals = _checks.as_points(fn, "normals", normals, like=points)
        if normals.shape != points.shape:
            raise ValueError(
                f"{fn}: argument 'normals' must have the shape of 'points' "
                f"{tuple(points.shape)}, got {tuple(normals.shape)}"
            )
    k = min(neighbors, points.shape[0])
    distance, index = KDTree(x).query(x, k=k, workers=icp.query_workers())
    if normals is not None:
        normals = normals.detach().cpu().numpy().astype(np.float64, copy=False)
    mask = _boundary_from_neighbours(x, distance, index, threshold, normals)
    return torch.from_numpy(mask).to(points.device)


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
    # the options in force (voxel_size resolved)
    config: RegisterConfig = field(default_factory=RegisterConfig)
    # Marginal covariances of the poses at the last round's solution, (m, 6, 6): (ω, v) order,
    # right perturbation of T_i0 = T_0i⁻¹ (world → scan i), scan 0 the gauge (zero), scaled by
    # the a-posteriori variance factor σ̂² = 2F / (3·observations − unknowns), since the
    # weights are not calibrated noise models; None when no round ran or the Hessian was
    # singular. Approximate: point-to-plane information is nearly rank 1 per observation, so
    # counting 3 residuals each underestimates σ̂² (by up to 3×).
    pose_covariances: Tensor | None = None


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
    normals: Sequence[Tensor] | None = None,
    covariances: bool = True,
    interior: Sequence[Tensor] | None = None,
) -> RefineResult:
    """Joint ICP-SLAM refinement: rounds of point tracks + the point-map least-squares solve.

    Args:
        clouds: m downsampled clouds (track level, ``config.voxel_size``) in their scan frames.
        poses: initial T_0i (e.g. chained), shape (m, 4, 4).
        config: options.
        pairs: scan pairs to match; by default those of :func:`overlapping_pairs` at
            ``poses`` with ``config.min_overlap``.
        progress: called with one line per round.
        normals: unit normals of the clouds (m tensors of their shapes, any sign), e.g. kept
            from an earlier stage; by default estimated here (PCA over
            ``config.normal_neighbors`` neighbours).
        covariances: compute :attr:`RefineResult.pose_covariances` (a marginalization of
            the last round's Hessian); False leaves them None.
        interior: the points of each cloud that may make tracks (m bool tensors of shape
            (N_i,)), e.g. computed with the normals at an earlier stage
            (:class:`torchslam.slam.Odometry`'s keyframes); by default those off the scans'
            boundaries (:func:`boundary_mask` with ``config.boundary_threshold``; every point
            when it is None). Given masks are used whatever ``config.boundary_threshold`` is.

    Returns:
        :class:`RefineResult`, poses in the frame of scan 0 (its pose is the gauge).
    """
    fn = "refine"
    clouds = check_clouds(fn, clouds, minimum=2, min_points=2)
    check_poses(fn, poses, len(clouds))
    config = check_config(fn, config).resolved(clouds, fn)
    if progress is not None and not callable(progress):
        raise TypeError(f"{fn}: argument 'progress' must be callable or None")
    if pairs is not None:
        pairs = _checks.check_index_pairs(fn, pairs, len(clouds))
    _checks.check_bool(fn, "covariances", covariances)
    poses = relative_to_first(poses.detach().clone().to(clouds[0].dtype), 0)
    if pairs is None:
        pairs, _ = overlapping_pairs(clouds, poses, config.voxel, config.min_overlap)
    pairs = list(pairs)
    # given normals also serve the boundary test (its neighbourhood's own PCA otherwise)
    given = normals is not None
    if normals is None:
        normals = [icp.estimate_normals(c, min(config.normal_neighbors, len(c))) for c in clouds]
    else:
        normals = _check_normals(fn, normals, clouds)
    if interior is not None:
        interior = _check_interior(fn, interior, clouds)
    elif config.boundary_threshold is not None:
        interior = [
            ~boundary_mask(
                c, config.normal_neighbors, config.boundary_threshold, n if given else None
            )
            for c, n in zip(clouds, normals, strict=True)
        ]
    if interior is not None:
        # Tracks only on interior points; Tracks.source_index then indexes these subsets.
        clouds = [c[keep] for c, keep in zip(clouds, interior, strict=True)]
        normals = [n[keep] for n, keep in zip(normals, interior, strict=True)]
    solver = SolverConfig(max_iterations=config.max_iterations, function_tolerance=1e-8)
    radius = config.track_radius * config.voxel
    rounds: list[RoundInfo] = []
    tracks = None
    pose_covariances = None
    for index in range(config.rounds if pairs else 0):
        tic = time.perf_counter()
        tracks = build_tracks(clouds, poses, radius, pairs=pairs)
        if tracks.num_points == 0:
            break
        problem = _problem(tracks, poses, normals, config)
        result = solve(problem, solver)
        updated = se3.inverse(result.poses[0].detach())
        finite = bool(torch.isfinite(updated).all())
        # A failed solve (non-finite poses) keeps the poses it started from; its status says so.
        rotation_change, translation_change = (
            _pose_change(poses, updated) if finite else (math.nan, math.nan)
        )
        if finite:
            poses = relative_to_first(updated, 0)
            if covariances:
                pose_covariances = _pose_covariances(problem, result, solver)
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
        if not finite or (
            rotation_change <= config.rotation_tolerance_deg
            and translation_change <= config.translation_tolerance * config.voxel
        ):
            break
    return RefineResult(poses, rounds, tracks, pairs, clouds, normals, config, pose_covariances)


def _per_cloud(fn: str, name: str, value: object, clouds: Sequence[Tensor], kind: str, item: str):
    """``value`` as a sequence of one entry per cloud (``kind``: what the entries are, for the
    messages; ``item``: one entry's name)."""
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        raise TypeError(
            f"{fn}: argument '{name}' must be a sequence of {kind} or None, got "
            f"{_checks.describe(value)}"
        )
    if len(value) != len(clouds):
        raise ValueError(
            f"{fn}: argument '{name}' must hold one {item} per cloud ({len(clouds)}), got "
            f"{len(value)}"
        )
    return value


def _check_normals(fn: str, normals: object, clouds: Sequence[Tensor]) -> list[Tensor]:
    normals = _per_cloud(fn, "normals", normals, clouds, "(N, 3) tensors", "tensor")
    checked = []
    for k, (n, c) in enumerate(zip(normals, clouds, strict=True)):
        n = _checks.as_points(fn, f"normals[{k}]", n, like=c)
        if n.shape != c.shape:
            raise ValueError(
                f"{fn}: argument 'normals[{k}]' must have the shape of clouds[{k}] "
                f"{tuple(c.shape)}, got {tuple(n.shape)}"
            )
        checked.append(n)
    return checked


def _check_interior(fn: str, interior: object, clouds: Sequence[Tensor]) -> list[Tensor]:
    interior = _per_cloud(fn, "interior", interior, clouds, "bool (N,) tensors", "mask")
    checked = []
    for k, (mask, c) in enumerate(zip(interior, clouds, strict=True)):
        if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
            raise TypeError(
                f"{fn}: argument 'interior[{k}]' must be a bool tensor, got "
                f"{_checks.describe(mask)}"
            )
        if mask.shape != c.shape[:1]:
            raise ValueError(
                f"{fn}: argument 'interior[{k}]' must have shape ({c.shape[0]},) (one entry per "
                f"point of clouds[{k}]), got {tuple(mask.shape)}"
            )
        checked.append(mask.to(c.device))
    return checked


def _pose_covariances(problem: PointMapProblem, result, solver: SolverConfig) -> Tensor | None:
    """The poses' marginal covariances of a solved round (:attr:`RefineResult.pose_covariances`),
    or None when its Hessian is singular."""
    from torchslam.covariance import marginal_covariances

    covariances = marginal_covariances(problem, result, points=False, config=solver)
    if not bool(covariances.ok[0]):
        return None
    residuals = 3 * int(problem.data.valid.sum())
    unknowns = 6 * int((~problem.data.fixed_poses).sum()) + 3 * problem.num_points
    dof = max(residuals - unknowns, 1)
    variance = 2.0 * float(result.final_cost[0]) / dof
    return covariances.poses[0].detach() * variance


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
        config: the options that define Ω and ρ; None: those of the refinement (a config
            without ``voxel_size`` takes the refinement's).

    Returns:
        The cost (nan when the refinement has no tracks).
    """
    fn = "joint_cost"
    if not isinstance(refinement, RefineResult):
        raise TypeError(
            f"{fn}: argument 'refinement' must be a RefineResult, "
            f"got {_checks.describe(refinement)}"
        )
    config = refinement.config if config is None else check_config(fn, config)
    if config.voxel_size is None:
        config = replace(config, voxel_size=refinement.config.voxel)
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

    # scan names, input order (every per-scan field follows it)
    names: list[str]
    # index of the reference scan whose frame the poses are in
    frame: int
    # initial poses from pairwise ICP (chain or spanning tree) T_0i, shape (m, 4, 4)
    chained: Tensor
    # jointly optimized poses T_0i, shape (m, 4, 4) (the chained ones if rounds = 0)
    poses: Tensor
    # the pairwise chain or spanning tree (indices: input order)
    chain: ChainResult
    # the joint refinement (indices: input order)
    refinement: RefineResult
    # track-level clouds (voxel_size) in their scan frames
    clouds: list[Tensor]
    # overlap matrix at the chained poses, (m, m)
    overlap: Tensor
    # RMS point-to-plane distance between matched scans: chained, joint
    residual_chained: float
    residual_joint: float
    # voxel pitch of ``clouds`` (derived from the scans unless given)
    voxel_size: float = 0.0
    # wall seconds per stage (chain, overlap, refine, total)
    seconds: dict[str, float] = field(default_factory=dict)
    # the options in force (voxel_size resolved)
    config: RegisterConfig = field(default_factory=RegisterConfig)
    # the scans' spacing and size (units check), and messages about odd scans
    scale: ScanScale | None = None

    @property
    def ok(self) -> bool:
        """True when every pose is finite and no joint solve failed (NON_FINITE or
        LINEAR_SOLVE_FAILED)."""
        failed = {Status.NON_FINITE, Status.LINEAR_SOLVE_FAILED}
        return bool(torch.isfinite(self.poses).all()) and not any(
            info.status in failed for info in self.refinement.rounds
        )


def register(
    names: Sequence[str],
    clouds: Sequence[Tensor],
    config: RegisterConfig | None = None,
    *,
    frame: int | str = 0,
    progress: Progress | None = None,
    progress_bar: bool = False,
) -> Registration:
    """The whole pipeline (module docstring) on scans in any order and any unit.

    With ``config.order == "any"`` (the default) the initial poses come from
    :func:`register_tree` (all pairs aligned coarsely, the most reliable ones finely, their
    maximum spanning tree); the scans are processed in the order of their names, so the
    result does not depend on the order they are given in. With ``"chain"`` successive scans
    are registered along the given order (:func:`register_chain`). ``voxel_size`` None (the
    default) derives every length from the scans (:func:`~torchslam.registration.config.
    auto_voxel_size`); implausible scans (mixed units, coinciding points, coordinates the
    dtype cannot resolve) are refused with a ValueError.

    Args:
        names: scan names, m ≥ 2.
        clouds: full-resolution scans in their own frames, shapes (N_i, 3): torch tensors or
            numpy arrays (float32/float64).
        config: options.
        frame: index or name of the scan whose frame the poses are expressed in.
        progress: called with one line per stage (and per pair and round).
        progress_bar: a tqdm bar on stderr over the pairs of the all-pairs stages.

    Returns:
        :class:`Registration` (check :attr:`Registration.ok`).

    Raises:
        TypeError, ValueError: bad arguments (names must be distinct single words, as
            :func:`write_poses` writes them; clouds float (N_i, 3) of one dtype and device,
            finite; ``frame`` an int index or a name among ``names``), implausible scans.
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
    say = progress or (lambda _line: None)
    start = time.perf_counter()
    scale = scan_scale(clouds, names, fn=fn)
    if config.voxel_size is None:
        config = replace(config, voxel_size=auto_voxel_size(scale))
        say(
            f"  scale: point spacing {float(np.median(scale.spacing)):.3g}, RMS radius "
            f"{float(np.median(scale.radius)):.3g} (scan units) → voxel size "
            f"{config.voxel:g}"
        )
    for line in scale.warnings:
        say(f"  warning: {line}")
    _check_point_counts(names, clouds, config)
    if config.order == "any":
        # Name order inside: the result is the same for any input order.
        order = sorted(range(len(names)), key=lambda k: names[k])
        inner = _register(
            [names[k] for k in order], [clouds[k] for k in order], config, say, progress_bar
        )
        inner = _permuted(inner, order)
    else:
        inner = _register(names, clouds, config, say, progress_bar)
    chain, refinement, small, overlap, seconds = inner
    distance = config.voxel
    # The consistency check uses the clouds the joint problem saw (boundary points removed).
    pairs = refinement.pairs
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
        config.voxel,
        seconds,
        config,
        scale,
    )


def _register(
    names: list[str],
    clouds: list[Tensor],
    config: RegisterConfig,
    say: Progress,
    progress_bar: bool = False,
) -> tuple[ChainResult, RefineResult, list[Tensor], Tensor, dict[str, float]]:
    """Pairwise initial poses, overlapping pairs, joint refinement (scans in working order)."""
    seconds: dict[str, float] = {}
    tic = time.perf_counter()
    if config.order == "chain":
        say(f"pairwise ICP along the chain: {len(clouds) - 1} pairs …")
        chain = register_chain(clouds, config, lambda line: say("  " + line), names)
    else:
        say(f"pairwise ICP, scans in any order: {len(clouds)} scans …")
        chain = register_tree(
            clouds, config, lambda line: say("  " + line), names, progress_bar=progress_bar
        )
    seconds["chain"] = time.perf_counter() - tic

    tic = time.perf_counter()
    small = [icp.voxel_downsample(c, config.voxel) for c in clouds]
    pairs, overlap = overlapping_pairs(small, chain.poses, config.voxel, config.min_overlap)
    edge_pairs = {(min(a, b), max(a, b)) for a, b in chain.tree_edges}
    pairs = sorted(set(pairs) | edge_pairs)
    extra = [p for p in pairs if p not in edge_pairs]
    seconds["overlap"] = time.perf_counter() - tic
    kind = "chain" if config.order == "chain" else "spanning tree"
    say(
        f"overlapping pairs at the initial poses: {len(pairs)}, {len(extra)} besides the "
        f"{kind} (overlap ≥ {config.min_overlap:g} within {config.voxel:g})"
    )
    for i, k in extra:
        say(f"  {names[i]} – {names[k]}: overlap {overlap[i, k]:.2f} / {overlap[k, i]:.2f}")

    say(
        f"joint ICP-SLAM on {sum(len(c) for c in small)} points ({config.voxel:g} voxels), "
        f"{config.rounds} rounds at most …"
    )
    tic = time.perf_counter()
    refinement = refine(
        small, chain.poses, config, pairs=pairs, progress=lambda line: say("  " + line)
    )
    seconds["refine"] = time.perf_counter() - tic
    return chain, refinement, small, overlap, seconds


def _permuted(
    inner: tuple[ChainResult, RefineResult, list[Tensor], Tensor, dict[str, float]],
    order: list[int],
) -> tuple[ChainResult, RefineResult, list[Tensor], Tensor, dict[str, float]]:
    """Results computed on the scans ``[input[k] for k in order]``, back in input order.

    Poses stay in the frame of the working order's first scan (the caller re-expresses them)."""
    chain, refinement, small, overlap, seconds = inner
    m = len(order)
    back = [0] * m  # working index → input index
    for working, original in enumerate(order):
        back[working] = original
    position = [0] * m  # input index → working index
    for working, original in enumerate(order):
        position[original] = working
    idx = torch.tensor(position)

    def remap(pairs: Sequence[tuple[int, int]], *, sort: bool) -> list[tuple[int, int]]:
        out = [(back[a], back[b]) for a, b in pairs]
        return sorted((min(a, b), max(a, b)) for a, b in out) if sort else out

    def matrix(x: Tensor | None) -> Tensor | None:
        return None if x is None else x[idx][:, idx]

    chain = ChainResult(
        chain.relative,
        chain.poses[idx],
        chain.pair_results,
        chain.pair_seconds,
        remap(chain.tree_edges, sort=False),
        matrix(chain.coarse_score),
        matrix(chain.fine_score),
    )
    tracks = refinement.tracks
    if tracks is not None:
        inverse = torch.tensor(back)
        tracks = replace(tracks, pose_index=inverse[tracks.pose_index])
    refinement = RefineResult(
        refinement.poses[idx],
        refinement.rounds,
        tracks,
        remap(refinement.pairs, sort=True),
        [refinement.track_clouds[p] for p in position],
        [refinement.track_normals[p] for p in position],
        refinement.config,
        None if refinement.pose_covariances is None else refinement.pose_covariances[idx],
    )
    return chain, refinement, [small[p] for p in position], matrix(overlap), seconds


def _check_point_counts(
    names: Sequence[str], clouds: Sequence[Tensor], config: RegisterConfig
) -> None:
    """Every scan keeps enough points at every voxel size of the pipeline (ValueError)."""
    sizes = sorted({s.voxel_size for s in config.pairwise_stages()} | {config.voxel})
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
