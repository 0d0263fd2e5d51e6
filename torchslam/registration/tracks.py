"""Point tracks across scans: the data association of the multiview ICP-SLAM problem.

The seed's section 1 needs, for every world point j, its observations X_ij in the frames i that
see it. Here the scans are (downsampled) point clouds with current poses T_0i (scan i → world
frame 0, e.g. chained pairwise ICP), and a world point is a set of mutually corresponding
scan points:

1. for every pair of scans (i, k), points a of scan i and b of scan k match when each is the
   other's nearest neighbour in the world frame and they lie within ``radius`` (mutual nearest
   neighbours, KD-trees);
2. the matches are the edges of a graph over all scan points; connected points form a track,
   i.e. one world point j with its observations (i, a, X_ia);
3. a track must not hold two points of one scan. With many overlapping scans, chains of
   matches between neighbouring samples would link such points. ``conflicts="greedy"`` (the
   default) therefore merges matches in order of increasing distance and skips any merge that
   would put two points of one scan into one track (Kruskal-like); ``conflicts="drop"`` takes
   plain connected components and drops every inconsistent one;
4. tracks seen in fewer than ``min_views`` scans are dropped.

The initial world point is the average of its observations moved into the world frame,
X_0j = (1/|V_j|) Σ_i T_0i X_ij (seed eq. (0.2)). The residual of the joint problem is then
r_ij = X_ij − T_0i⁻¹ X_0j, i.e. X_ij − T_i0 X_0j of seed eq. (1.1) with T_i0 = T_0i⁻¹.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from torch import Tensor

from torchslam import _checks
from torchslam.lie import se3
from torchslam.registration.kdtree import KDTree
from torchslam.registration.neighbors import _host, query_workers

__all__ = ["Tracks", "build_tracks", "mutual_nearest_neighbors"]


@dataclass
class Tracks:
    """Point tracks as flat edge arrays, sorted by point and then by pose.

    Edge e says: world point ``point_index[e]`` is observed in scan ``pose_index[e]`` as the
    point ``source_index[e]`` of that scan's cloud, with coordinates ``observations[e]`` in
    the scan's frame.
    """

    # scan (pose) i of each observation, int64, shape (E,)
    pose_index: Tensor
    # world point (track) j of each observation, int64, shape (E,), values 0 … n − 1
    point_index: Tensor
    # index of the observed point in its scan's cloud, int64, shape (E,)
    source_index: Tensor
    # X_ij: the observed point in scan i's frame, shape (E, 3)
    observations: Tensor
    # X_0j initial estimates: mean of T_0i X_ij over the track, shape (n, 3)
    points: Tensor
    # number of scans m (poses), including scans without observations
    num_poses: int
    # matches skipped (conflicts="greedy") or components dropped ("drop") to keep every
    # track free of two points of one scan
    num_conflicts: int

    @property
    def num_points(self) -> int:
        """Number of tracks n."""
        return int(self.points.shape[0])

    @property
    def num_edges(self) -> int:
        """Number of observations E."""
        return int(self.pose_index.shape[0])

    def views_per_point(self) -> Tensor:
        """Number of observations of each track, int64, shape (n,)."""
        return torch.bincount(self.point_index, minlength=self.num_points)

    def padded(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The tracks as padded per-point arrays.

        Returns:
            ``(pose_index, source_index, observations, mask)`` of shapes (n, K), (n, K),
            (n, K, 3) and (n, K) with K the longest track; padding has pose and source index
            −1, zero coordinates and ``mask`` False. Within a row, poses are increasing.
        """
        n = self.num_points
        counts = self.views_per_point()
        width = int(counts.max()) if n > 0 else 0
        starts = torch.cumsum(counts, 0) - counts
        slot = torch.arange(self.num_edges) - starts[self.point_index]
        pose = torch.full((n, width), -1, dtype=torch.int64)
        source = torch.full((n, width), -1, dtype=torch.int64)
        observations = self.observations.new_zeros(n, width, 3)
        mask = torch.zeros(n, width, dtype=torch.bool)
        pose[self.point_index, slot] = self.pose_index
        source[self.point_index, slot] = self.source_index
        observations[self.point_index, slot] = self.observations
        mask[self.point_index, slot] = True
        return pose, source, observations, mask


def mutual_nearest_neighbors(first: Tensor, second: Tensor, radius: float) -> Tensor:
    """Pairs (a, b) where first[a] and second[b] are each other's nearest neighbour, ≤ radius.

    Args:
        first: points, shape (N, 3), finite; a torch tensor or a numpy array
            (float32/float64).
        second: points, shape (M, 3), same frame, finite, same dtype.
        radius: largest accepted distance, a number > 0 (``inf``: no bound).

    Returns:
        Index pairs, int64, shape (K, 2), sorted by a; each a and each b appears at most once
        (on the CPU).
    """
    fn = "mutual_nearest_neighbors"
    like = _checks.first_tensor(first, second)
    first = _checks.as_points(fn, "first", first, like=like, finite=False)
    second = _checks.as_points(fn, "second", second, like=like, finite=False)
    _checks.check_same_kind(fn, first=first, second=second)
    bound = _checks.check_real(fn, "radius", radius, low=0.0, low_open=True, allow_inf=True)
    a_to_b = _mutual(_host(fn, "first", first), _host(fn, "second", second), None, None, bound)
    return torch.from_numpy(a_to_b).to(torch.int64)


def _mutual(
    a: np.ndarray,
    b: np.ndarray,
    tree_a: KDTree | None,
    tree_b: KDTree | None,
    radius: float,
) -> np.ndarray:
    """(K, 2) mutual nearest-neighbour index pairs between point arrays a and b."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    tree_a = KDTree(a) if tree_a is None else tree_a
    tree_b = KDTree(b) if tree_b is None else tree_b
    workers = query_workers()
    _, ab = tree_b.query(a, distance_upper_bound=radius, workers=workers)  # missing: len(b)
    _, ba = tree_a.query(b, distance_upper_bound=radius, workers=workers)  # missing: len(a)
    found = np.flatnonzero(ab < len(b))
    partner = ab[found]
    back = ba[partner]
    mutual = back == found
    return np.stack((found[mutual], partner[mutual]), axis=-1).astype(np.int64)


def _greedy_components(
    row: np.ndarray, col: np.ndarray, scan: np.ndarray, total: int
) -> tuple[np.ndarray, int]:
    """Union-find over matches in the given order, refusing merges that repeat a scan.

    Returns a component label per point and the number of refused merges.
    """
    parent = list(range(total))
    # Bit mask of the scans in each component (Python ints: any number of scans).
    scans = [1 << int(s) for s in scan.tolist()]

    def find(x: int) -> int:
        root = x
        while parent[root] != root:
            root = parent[root]
        while parent[x] != root:  # path compression
            parent[x], x = root, parent[x]
        return root

    refused = 0
    for a, b in zip(row.tolist(), col.tolist(), strict=True):
        ra, rb = find(a), find(b)
        if ra == rb:
            continue
        if scans[ra] & scans[rb]:
            refused += 1
            continue
        parent[rb] = ra
        scans[ra] |= scans[rb]
    # Every point's root by pointer jumping (parents point to their roots after
    # ⌈log₂ depth⌉ rounds): the labels find() gives, without a Python call per point.
    label = np.asarray(parent, dtype=np.int64)
    while True:
        jumped = label[label]
        if np.array_equal(jumped, label):
            return label, refused
        label = jumped


def build_tracks(
    clouds: Sequence[Tensor],
    poses: Tensor,
    radius: float,
    *,
    pairs: Sequence[tuple[int, int]] | None = None,
    min_views: int = 2,
    conflicts: Literal["greedy", "drop"] = "greedy",
) -> Tracks:
    """Build point tracks from scans and their current poses (module docstring).

    Args:
        clouds: a list or tuple of m ≥ 2 point clouds in their scan frames, shapes (N_i, 3),
            finite, one dtype and device; torch tensors or numpy arrays (float32/float64)
            (downsample them first, e.g. with ``icp.voxel_downsample``).
        poses: T_0i mapping scan i into the world frame, shape (m, 4, 4).
        radius: largest distance (world frame) between matched points, a number > 0
            (``inf``: no bound); about the downsampling pitch plus the pose error.
        pairs: scan pairs (i, k) of ints, 0 ≤ i, k < m, i ≠ k, to match; all pairs i < k by
            default.
        min_views: smallest number of scans a track must be seen in, an int ≥ 2.
        conflicts: ``"greedy"``: merge matches shortest first, skipping merges that would
            put two points of one scan into a track; ``"drop"``: connected components,
            dropping those that hold one scan twice.

    Returns:
        :class:`Tracks` (edge arrays sorted by point, then pose; X_0j initial points).
    """
    fn = "build_tracks"
    if not isinstance(clouds, (list, tuple)):
        raise TypeError(
            f"{fn}: argument 'clouds' must be a list or tuple of (N_i, 3) point clouds, got "
            f"{_checks.describe(clouds)}"
        )
    m = len(clouds)
    if m < 2:
        raise ValueError(f"{fn}: argument 'clouds' must hold at least 2 clouds, got {m}")
    like = _checks.first_tensor(*clouds)
    clouds = [
        _checks.as_points(fn, f"clouds[{i}]", cloud, like=like, finite=False)
        for i, cloud in enumerate(clouds)
    ]
    for i, cloud in enumerate(clouds):
        _checks.check_same_kind(fn, **{"clouds[0]": clouds[0], f"clouds[{i}]": cloud})
        _host(fn, f"clouds[{i}]", cloud)  # finite (always: KD-trees on the host)
    _checks.check_tensor(fn, "poses", poses, (4, 4))
    if poses.shape != (m, 4, 4):
        raise ValueError(
            f"{fn}: argument 'poses' must have shape ({m}, 4, 4) for {m} clouds, got "
            f"{tuple(poses.shape)}"
        )
    _checks.check_same_kind(fn, **{"clouds[0]": clouds[0], "poses": poses})
    _checks.check_pose_matrix(fn, "poses", poses)
    radius = _checks.check_real(fn, "radius", radius, low=0.0, low_open=True, allow_inf=True)
    min_views = _checks.check_int(fn, "min_views", min_views, minimum=2)
    if not isinstance(conflicts, str) or conflicts not in ("greedy", "drop"):
        raise ValueError(
            f"{fn}: argument 'conflicts' must be 'greedy' or 'drop', got "
            f"{_checks.describe(conflicts)}"
        )
    pairs = (
        list(itertools.combinations(range(m), 2))
        if pairs is None
        else _checks.check_index_pairs(fn, pairs, m)
    )

    dtype, device = clouds[0].dtype, clouds[0].device
    world = [_host(fn, "poses", se3.act(poses[i], clouds[i])) for i in range(m)]
    trees = [KDTree(w) if len(w) else None for w in world]
    sizes = np.array([len(w) for w in world], dtype=np.int64)
    offsets = np.concatenate(([0], np.cumsum(sizes)))
    total = int(offsets[-1])

    scan = np.repeat(np.arange(m, dtype=np.int64), sizes)
    local = np.arange(total, dtype=np.int64) - offsets[scan]
    all_world = np.concatenate(world) if total else np.zeros((0, 3))

    # 1. Mutual nearest neighbours of every pair: the edges of one graph over all points.
    rows, cols = [np.zeros(0, dtype=np.int64)], [np.zeros(0, dtype=np.int64)]
    for i, k in pairs:
        matches = _mutual(world[i], world[k], trees[i], trees[k], radius)
        rows.append(offsets[i] + matches[:, 0])
        cols.append(offsets[k] + matches[:, 1])
    row, col = np.concatenate(rows), np.concatenate(cols)

    # 2–3. Tracks without two points of one scan.
    if conflicts == "greedy":
        length = np.linalg.norm(all_world[row] - all_world[col], axis=-1)
        order = np.argsort(length, kind="stable")
        label, num_conflicts = _greedy_components(row[order], col[order], scan, total)
        keep = np.ones(total, dtype=bool)
    else:
        graph = coo_matrix((np.ones(len(row), dtype=np.int8), (row, col)), shape=(total, total))
        _, label = connected_components(graph, directed=False)
        key = label.astype(np.int64) * m + scan
        unique_keys, key_counts = np.unique(key, return_counts=True)
        bad_components = np.unique(unique_keys[key_counts > 1] // m)
        num_conflicts = len(bad_components)
        keep = ~np.isin(label, bad_components)

    # 4. Tracks with enough views.
    views = np.bincount(label[keep], minlength=total)
    keep &= views[label] >= min_views
    kept = np.flatnonzero(keep)
    components, point = np.unique(label[kept], return_inverse=True)
    order = np.lexsort((scan[kept], point))
    kept, point = kept[order], point[order]

    pose_index = torch.from_numpy(scan[kept]).to(device)
    point_index = torch.from_numpy(point.astype(np.int64)).to(device)
    source_index = torch.from_numpy(local[kept]).to(device)
    all_local = torch.cat([c.detach() for c in clouds]) if total else clouds[0].new_zeros(0, 3)
    observations = all_local[torch.from_numpy(kept).to(all_local.device)].to(dtype)
    moved = torch.from_numpy(all_world[kept]).to(dtype=dtype, device=device)
    n = len(components)
    sums = moved.new_zeros(n, 3).index_add_(0, point_index, moved)
    counts = torch.bincount(point_index, minlength=n).clamp_min(1).to(dtype)
    points = sums / counts[:, None]
    return Tracks(pose_index, point_index, source_index, observations, points, m, num_conflicts)
