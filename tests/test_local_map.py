"""The odometry's local map: one point per voxel, the newest keyframe's winning; keyframes
forgotten by count and by distance; the voxel keys against a brute-force dictionary."""

from __future__ import annotations

import numpy as np
import torch

from torchslam.slam.local_map import LocalMap, _first_occurrences


def _brute_force(clouds: list[np.ndarray], voxel: float) -> np.ndarray:
    """The merged map by a dictionary: newest cloud first, the first point of a voxel wins."""
    cells: dict[tuple[int, int, int], np.ndarray] = {}
    for cloud in reversed(clouds):
        for point in cloud:
            cells.setdefault(tuple(np.floor(point / voxel).astype(np.int64)), point)
    return np.array(sorted(map(tuple, cells.values())))


def test_map_keeps_the_newest_point_per_voxel():
    generator = np.random.default_rng(5)
    voxel = 0.25
    local = LocalMap(voxel, max_keyframes=3, radius=100.0)
    clouds = []
    for k in range(5):
        # overlapping clouds, negative coordinates included (floor, not truncation)
        cloud = generator.uniform(-2.0, 2.0, (400, 3)) + 0.1 * k
        clouds.append(cloud)
        local.add(cloud, np.tile([0.0, 0.0, 1.0], (400, 1)), np.zeros(3))
        expected = _brute_force(clouds[-3:], voxel)  # the newest max_keyframes
        got = np.array(sorted(map(tuple, local.points.numpy())))
        assert np.array_equal(got, expected)
        assert local.num_keyframes == min(k + 1, 3)
        # the KD-tree indexes the merged points
        assert np.array_equal(local.tree.data, local.points.numpy())


def test_map_forgets_keyframes_beyond_the_radius_and_empty_keyframes_give_an_empty_map():
    local = LocalMap(0.5, max_keyframes=10, radius=5.0)
    near = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    normals = np.tile([0.0, 0.0, 1.0], (2, 1))
    local.add(near, normals, np.zeros(3))
    local.add(near + 20.0, normals, np.full(3, 20.0))  # the first is now 34 m away
    assert local.num_keyframes == 1
    assert torch.equal(local.points, torch.from_numpy(near + 20.0))
    empty = LocalMap(0.5, max_keyframes=1, radius=5.0)
    empty.add(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(3))
    assert len(empty) == 0 and empty.tree is None


def test_first_occurrences_matches_numpy_unique():
    generator = np.random.default_rng(7)
    key = generator.integers(0, 50, 1000)
    assert np.array_equal(_first_occurrences(key), np.sort(np.unique(key, return_index=True)[1]))
    assert _first_occurrences(np.zeros(0, dtype=np.int64)).size == 0
