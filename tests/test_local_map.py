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


def test_map_far_from_the_origin_falls_back_to_bounding_box_keys():
    # Cells beyond the packed keys' range (2^20 voxels from the origin): the map keys the
    # merged cloud's bounding box instead, with the same newest-point-per-voxel answer; a map
    # mixing such a keyframe with near ones too. Voxel 0.5 and offsets of whole voxels keep
    # the coordinates exactly representable, so floor() is exact on both paths.
    generator = np.random.default_rng(11)
    voxel = 0.5
    local = LocalMap(voxel, max_keyframes=3, radius=1e9)
    clouds = []
    for k, shift in enumerate((0.0, 1e6, 1e6 + 1.0, 0.0)):
        cloud = np.round(generator.uniform(-2.0, 2.0, (300, 3)) * 64) / 64 + shift
        clouds.append(cloud)
        local.add(cloud, np.tile([0.0, 0.0, 1.0], (300, 1)), np.zeros(3))
        got = np.array(sorted(map(tuple, local.points.numpy())))
        assert np.array_equal(got, _brute_force(clouds[-3:], voxel)), k


def test_first_of_sorted_runs_matches_first_occurrences():
    from torchslam.slam.local_map import _first_of_sorted_runs, _Keyframe, _packed_keys

    generator = np.random.default_rng(13)
    for sizes in ((50, 0, 80, 1), (1,), (0, 30)):
        keyframes, keys = [], []
        for size in sizes:
            # few distinct voxels: duplicates within and across keyframes
            points = generator.integers(-3, 3, (size, 3)).astype(np.float64) + 0.5
            key = _packed_keys(points, 1.0)
            order = np.argsort(key, kind="stable")
            keyframes.append(_Keyframe(points, points, np.zeros(3), key[order], order))
            keys.append(key)
        assert np.array_equal(
            _first_of_sorted_runs(keyframes), _first_occurrences(np.concatenate(keys))
        )
