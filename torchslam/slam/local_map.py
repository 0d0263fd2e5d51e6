"""The odometry's local map: a voxel map of the newest keyframes near the sensor.

Each keyframe brings its downsampled cloud and PCA normals, both in the world frame. The map
keeps the newest ``max_keyframes`` keyframes whose sensor position lies within ``radius`` of
the current one and merges them into one point (with its normal) per voxel of pitch ``voxel``,
the newest keyframe's point winning a voxel. Older keyframes are forgotten, so the map's size
is bounded whatever the length of the sequence. The merged points, normals and their KD-tree
are rebuilt when a keyframe is added or forgotten (not per frame).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

__all__ = ["LocalMap"]


@dataclass
class _Keyframe:
    points: np.ndarray  # (N, 3) world frame
    normals: np.ndarray  # (N, 3) world frame, unit
    position: np.ndarray  # (3,) sensor position in the world


class LocalMap:
    """A voxel map of recent keyframes (module docstring). Arrays are float64."""

    def __init__(self, voxel: float, max_keyframes: int, radius: float) -> None:
        self.voxel = float(voxel)
        self.max_keyframes = int(max_keyframes)
        self.radius = float(radius)
        self._keyframes: deque[_Keyframe] = deque()
        self.points = torch.zeros(0, 3, dtype=torch.float64)
        self.normals = torch.zeros(0, 3, dtype=torch.float64)
        self.tree: cKDTree | None = None

    def __len__(self) -> int:
        return self.points.shape[0]

    @property
    def num_keyframes(self) -> int:
        return len(self._keyframes)

    def add(self, points: np.ndarray, normals: np.ndarray, position: np.ndarray) -> None:
        """Add a keyframe's cloud and normals (world frame, (N, 3)) seen from ``position``."""
        self._keyframes.append(_Keyframe(points, normals, np.asarray(position, np.float64)))
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
        # voxel indices as three contiguous rows (reductions over a (N, 3) array's columns
        # are several times slower), offset to 0 … extent − 1, then one key per voxel
        cells = np.floor(points / self.voxel).astype(np.int64).T.copy()
        low = cells.min(1)
        extent = cells.max(1) - low + 1
        x, y, z = (cells[k] - low[k] for k in range(3))
        key = (x * extent[1] + y) * extent[2] + z
        # One point per voxel, the first (newest) one.
        first = _first_occurrences(key)
        points, normals = points[first], normals[first]
        self.points = torch.from_numpy(np.ascontiguousarray(points))
        self.normals = torch.from_numpy(np.ascontiguousarray(normals))
        self.tree = cKDTree(points, balanced_tree=False, compact_nodes=False)

    def state(self) -> tuple[Tensor, Tensor]:
        """The merged map: points and unit normals, (M, 3) each, world frame."""
        return self.points, self.normals


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
