"""The odometry's local map: a voxel map of the newest keyframes near the sensor.

Each keyframe brings its downsampled cloud and PCA normals, both in the world frame. The map
keeps the newest ``max_keyframes`` keyframes whose sensor position lies within ``radius`` of
the current one and merges them into one point (with its normal) per voxel of pitch ``voxel``,
the newest keyframe's point winning a voxel. Older keyframes are forgotten, so the map's size
is bounded whatever the length of the sequence. The merged points, normals and their KD-tree
are rebuilt when a keyframe is added or forgotten (not per frame); each keyframe's voxel keys
are computed and sorted once, when it is added, so that a rebuild merges sorted runs.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from torchslam.registration.kdtree import KDTree

__all__ = ["LocalMap"]


# Voxel keys pack the three cell indices, offset by _OFFSET, into _BITS bits each of one
# int64; a cloud with a cell index beyond ±_OFFSET (2^20 voxels: 262 km at 0.25 m) has no keys
# and the map falls back to keys over the merged cloud's bounding box.
_BITS = 21
_OFFSET = 1 << (_BITS - 1)


@dataclass
class _Keyframe:
    points: np.ndarray  # (N, 3) world frame
    normals: np.ndarray  # (N, 3) world frame, unit
    position: np.ndarray  # (3,) sensor position in the world
    # the voxel keys of the points, sorted, and the stable order that sorts them (N,) each;
    # None where a cell index is out of the packing's range
    sorted_keys: np.ndarray | None
    order: np.ndarray | None


def _packed_keys(points: np.ndarray, voxel: float) -> np.ndarray | None:
    """One int64 per point naming its voxel (the packing above), None when out of range."""
    cells = np.floor(points / voxel).T.copy()  # three contiguous rows, float64
    if cells.size and float(np.abs(cells).max()) >= _OFFSET:
        return None
    x, y, z = (cells[k].astype(np.int64) + _OFFSET for k in range(3))
    return (x << (2 * _BITS)) | (y << _BITS) | z


class LocalMap:
    """A voxel map of recent keyframes (module docstring). Arrays are float64."""

    def __init__(self, voxel: float, max_keyframes: int, radius: float) -> None:
        self.voxel = float(voxel)
        self.max_keyframes = int(max_keyframes)
        self.radius = float(radius)
        self._keyframes: deque[_Keyframe] = deque()
        self.points = torch.zeros(0, 3, dtype=torch.float64)
        self.normals = torch.zeros(0, 3, dtype=torch.float64)
        self.tree: KDTree | None = None

    def __len__(self) -> int:
        return self.points.shape[0]

    @property
    def num_keyframes(self) -> int:
        return len(self._keyframes)

    def add(self, points: np.ndarray, normals: np.ndarray, position: np.ndarray) -> None:
        """Add a keyframe's cloud and normals (world frame, (N, 3)) seen from ``position``."""
        keys = _packed_keys(points, self.voxel)
        order = None if keys is None else np.argsort(keys, kind="stable")
        sorted_keys = None if keys is None else keys[order]
        position = np.asarray(position, np.float64)
        self._keyframes.append(_Keyframe(points, normals, position, sorted_keys, order))
        while len(self._keyframes) > self.max_keyframes:
            self._keyframes.popleft()
        self._forget(position)
        self._rebuild()

    def _forget(self, position: np.ndarray) -> None:
        kept = [k for k in self._keyframes if np.linalg.norm(k.position - position) <= self.radius]
        if len(kept) < len(self._keyframes):
            self._keyframes = deque(kept)

    def _rebuild(self) -> None:
        newest_first = list(reversed(self._keyframes))
        points = np.concatenate([k.points for k in newest_first])
        normals = np.concatenate([k.normals for k in newest_first])
        if points.shape[0] == 0:  # keyframes without points: an empty map, no tree
            self.points = torch.zeros(0, 3, dtype=torch.float64)
            self.normals = torch.zeros(0, 3, dtype=torch.float64)
            self.tree = None
            return
        # One point per voxel, the first (newest) one.
        if all(k.sorted_keys is not None for k in newest_first):
            first = _first_of_sorted_runs(newest_first)
        else:
            # voxel indices as three contiguous rows (reductions over a (N, 3) array's columns
            # are several times slower), offset to 0 … extent − 1, then one key per voxel
            cells = np.floor(points / self.voxel).astype(np.int64).T.copy()
            low = cells.min(1)
            extent = cells.max(1) - low + 1
            x, y, z = (cells[k] - low[k] for k in range(3))
            first = _first_occurrences((x * extent[1] + y) * extent[2] + z)
        points, normals = points[first], normals[first]
        self.points = torch.from_numpy(np.ascontiguousarray(points))
        self.normals = torch.from_numpy(np.ascontiguousarray(normals))
        self.tree = KDTree(points)

    def state(self) -> tuple[Tensor, Tensor]:
        """The merged map: points and unit normals, (M, 3) each, world frame."""
        return self.points, self.normals


def _first_of_sorted_runs(keyframes: list[_Keyframe]) -> np.ndarray:
    """:func:`_first_occurrences` of the keys of the concatenated ``keyframes`` (in this order),
    from each one's sorted keys: a stable sort of the concatenated sorted runs (a merge, about
    twice as fast as sorting the keys afresh) puts each voxel's entries in the order of their
    index, so the first of each run of equal keys is the voxel's first occurrence."""
    offsets = np.cumsum([0] + [len(k.points) for k in keyframes[:-1]])
    keys = np.concatenate([k.sorted_keys for k in keyframes])  # type: ignore[misc]
    index = np.concatenate([k.order + o for k, o in zip(keyframes, offsets, strict=True)])  # type: ignore[operator]
    merged = np.argsort(keys, kind="stable")
    keys, index = keys[merged], index[merged]
    starts = np.concatenate(([True], keys[1:] != keys[:-1]))
    first = index[starts]
    first.sort()
    return first


def _first_occurrences(key: np.ndarray) -> np.ndarray:
    """The index of the first occurrence of every distinct value of ``key`` (N,), ascending:
    ``np.unique(key, return_index=True)[1]`` sorted, from an unstable sort (the smallest
    index per run of equal keys), about twice as fast as np.unique's stable one."""
    if key.size == 0:
        return np.zeros(0, dtype=np.int64)
    order = np.argsort(key)
    ordered = key[order]
    starts = np.flatnonzero(np.concatenate(([True], ordered[1:] != ordered[:-1])))
    first = np.minimum.reduceat(order, starts)
    first.sort()
    return first
