"""Synthetic scenes: conventions, invariants (well-posedness), determinism, presets."""

from __future__ import annotations

import math

import pytest
import torch

from torchslam.data import BENCHMARK_CASES, SyntheticScene, benchmark_case, make_scene
from torchslam.lie import se3, so3

TRAJECTORIES = ["loop", "helix", "random_walk"]
VISIBILITIES = ["fraction", "range"]


def _clean_observations(scene: SyntheticScene) -> torch.Tensor:
    """T_i0 X_j for every edge, (B, E, 3)."""
    b = torch.arange(scene.batch_size)[:, None]
    T = scene.poses_gt[b, scene.pose_index]
    X = scene.points_gt[b, scene.point_index]
    return se3.act(T, X)


def _assert_invariants(scene: SyntheticScene) -> None:
    B, m, n = scene.batch_size, scene.num_poses, scene.num_points
    _, seen = scene.to_dense()
    assert (seen.sum(1) >= 2).all(), "a point is seen by fewer than 2 frames"
    assert (seen.sum(2) >= 3).all(), "a frame sees fewer than 3 points"
    assert ((seen[:, :-1] & seen[:, 1:]).sum(-1) >= 3).all(), "successive frames share < 3"
    # Padding is a suffix, zero, with index 0; real edges sorted by (pose, point), unique.
    valid = scene.valid
    assert (valid.cummin(dim=-1).values == valid).all()
    assert (scene.pose_index[~valid] == 0).all() and (scene.point_index[~valid] == 0).all()
    assert (scene.observations[~valid] == 0).all()
    key = scene.pose_index * n + scene.point_index
    for b in range(B):
        k = key[b, valid[b]]
        assert (k[1:] > k[:-1]).all()
    assert int(seen.sum()) == int(valid.sum())
    assert scene.pose_index.max() < m and scene.point_index.max() < n


@pytest.mark.parametrize("trajectory", TRAJECTORIES)
@pytest.mark.parametrize("visibility", VISIBILITIES)
def test_conventions_and_invariants(trajectory, visibility):
    scene = make_scene(
        12, 150, batch_size=3, trajectory=trajectory, visibility=visibility, noise_std=0.0, seed=3
    )
    B, m, n = 3, 12, 150
    assert scene.poses_gt.shape == (B, m, 4, 4)
    assert scene.points_gt.shape == (B, n, 3)
    E = scene.valid.shape[1]
    for x in (scene.pose_index, scene.point_index):
        assert x.shape == (B, E) and x.dtype == torch.long
    assert scene.observations.shape == (B, E, 3)
    assert scene.valid.dtype == torch.bool and scene.is_outlier.dtype == torch.bool
    assert scene.poses_gt.dtype == torch.float64
    # Gauge: T_00 is exactly the identity; all poses are rigid transforms.
    assert torch.equal(scene.poses_gt[:, 0], torch.eye(4, dtype=torch.float64).expand(B, 4, 4))
    R = scene.poses_gt[..., :3, :3]
    eye = torch.eye(3, dtype=torch.float64)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, eye.expand_as(R), atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(B, m, dtype=torch.float64))
    # Noise-free observations are exactly X_ij = T_i0 X_j (seed eq. 0.1).
    expected = _clean_observations(scene)
    torch.testing.assert_close(
        scene.observations[scene.valid], expected[scene.valid], atol=1e-12, rtol=0
    )
    assert not scene.is_outlier.any()
    _assert_invariants(scene)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"visibility": "fraction", "visible_fraction": 0.01},  # k = 2 frames per point
        {"visibility": "range", "max_range": 0.3},  # almost nothing in range
        {"visibility": "range", "max_range": 0.3, "trajectory": "random_walk"},
    ],
    ids=["tiny-fraction", "tiny-range", "tiny-range-walk"],
)
def test_guarantees_hold_when_repairs_are_needed(kwargs):
    scene = make_scene(30, 40, batch_size=2, seed=5, **kwargs)
    _assert_invariants(scene)


def test_fraction_visibility_counts():
    m, n, fraction = 20, 300, 0.25
    scene = make_scene(m, n, batch_size=2, visible_fraction=fraction, seed=1)
    _, seen = scene.to_dense()
    views = seen.sum(1)
    k = round(fraction * m)
    # Exactly k views per point unless a guarantee added some.
    assert (views >= k).all()
    assert (views == k).float().mean() > 0.99
    assert scene.num_observations.tolist() == [int(v) for v in views.sum(-1)]


def test_range_visibility_is_within_range():
    scene = make_scene(15, 400, visibility="range", max_range=4.0, noise_std=0.0, seed=2)
    ranges = scene.observations[scene.valid].norm(dim=-1)
    # The sensor sits at the origin of its frame, so ‖X_ij‖ is the range; only the guarantees
    # may add observations beyond it.
    assert (ranges <= 4.0 + 1e-9).float().mean() > 0.95
    assert ranges.max() > 0.5  # not a trivial scene


def test_noise_statistics():
    scene = make_scene(30, 1000, noise_std=0.02, seed=4)
    residual = scene.observations - _clean_observations(scene)
    r = residual[scene.valid]
    assert r.shape[0] > 8000
    assert abs(r.std().item() - 0.02) < 0.02 * 0.03
    assert r.mean().abs().item() < 0.001


def test_substantial_rotation_between_frames():
    for trajectory in TRAJECTORIES:
        scene = make_scene(40, 100, trajectory=trajectory, batch_size=4, seed=7)
        T = scene.poses_gt
        relative = T[:, 1:] @ se3.inverse(T[:, :-1])
        angle = so3.log(relative[..., :3, :3]).norm(dim=-1).rad2deg()
        assert angle.min() >= 5.0, trajectory
        accumulated = so3.log(T[..., :3, :3]).norm(dim=-1).rad2deg()
        assert (accumulated.amax(dim=1) >= 30.0).all(), trajectory
    walk = make_scene(20, 50, trajectory="random_walk", rotation_per_frame_deg=7.0, seed=1)
    T = walk.poses_gt
    angle = so3.log((T[:, 1:] @ se3.inverse(T[:, :-1]))[..., :3, :3]).norm(dim=-1)
    torch.testing.assert_close(angle, torch.full_like(angle, math.radians(7.0)))


def test_deterministic_for_a_seed():
    a = make_scene(10, 100, batch_size=2, outlier_fraction=0.1, seed=11)
    b = make_scene(10, 100, batch_size=2, outlier_fraction=0.1, seed=11)
    c = make_scene(10, 100, batch_size=2, outlier_fraction=0.1, seed=12)
    for name in ("poses_gt", "points_gt", "pose_index", "point_index", "observations"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert torch.equal(a.is_outlier, b.is_outlier)
    assert not torch.equal(a.points_gt, c.points_gt)
    # Problems in a batch differ from each other.
    assert not torch.allclose(a.poses_gt[0], a.poses_gt[1])


def test_dtype_and_device(device):
    f64 = make_scene(8, 60, seed=9)
    f32 = make_scene(8, 60, seed=9, dtype=torch.float32, device=device)
    assert f32.observations.dtype == torch.float32 and f32.observations.device.type == device.type
    assert f32.pose_index.dtype == torch.long
    torch.testing.assert_close(f32.observations.cpu(), f64.observations.float())
    assert torch.equal(f32.pose_index.cpu(), f64.pose_index)


def test_outliers():
    scene = make_scene(20, 300, batch_size=3, visibility="range", outlier_fraction=0.2, seed=6)
    count = scene.is_outlier.sum(-1)
    expected = torch.round(0.2 * scene.num_observations.double()).long()
    assert torch.equal(count, expected)
    assert not (scene.is_outlier & ~scene.valid).any()
    error = (scene.observations - _clean_observations(scene)).norm(dim=-1)
    inlier = scene.valid & ~scene.is_outlier
    assert error[inlier].max() < 0.1  # 0.01 noise: ≤ ~6σ · √3
    assert error[scene.is_outlier].median() > 1.0
    # Outliers lie in the points' bounding box (mapped into their frame).
    b = torch.arange(3)[:, None]
    world = se3.act(se3.inverse(scene.poses_gt[b, scene.pose_index]), scene.observations)
    lower = scene.points_gt.amin(1, keepdim=True) - 1e-9
    upper = scene.points_gt.amax(1, keepdim=True) + 1e-9
    inside = ((world >= lower) & (world <= upper)).all(-1)
    assert inside[scene.is_outlier].all()


def test_padding_with_different_sizes_and_to_dense():
    scene = make_scene(10, 120, batch_size=3, visibility="range", seed=8)
    sizes = scene.num_observations
    assert len(set(sizes.tolist())) > 1  # problems really differ in E
    assert scene.valid.shape[1] == int(sizes.max())
    dense, seen = scene.to_dense()
    assert dense.shape == (3, 10, 120, 3) and seen.shape == (3, 10, 120)
    assert torch.equal(seen.sum((1, 2)), sizes)
    b, e = scene.valid.nonzero(as_tuple=True)
    torch.testing.assert_close(
        dense[b, scene.pose_index[b, e], scene.point_index[b, e]], scene.observations[b, e]
    )
    assert (dense[~seen] == 0).all()


def test_benchmark_cases():
    expected = {"S": (1, 10, 200, 1400), "M": (1, 50, 1000, 15000), "BATCH": (64, 10, 200, 1400)}
    for name, (B, m, n, E) in expected.items():
        scene = benchmark_case(name)
        assert (scene.batch_size, scene.num_poses, scene.num_points) == (B, m, n)
        assert (scene.num_observations == E).all(), name
        assert scene.noise_std == 0.01
        _assert_invariants(scene)
    large = benchmark_case("L")
    assert (large.num_poses, large.num_points) == (200, 5000)
    assert int(large.num_observations[0]) == 100_000
    outliers = benchmark_case("O")
    assert int(outliers.is_outlier.sum()) == 1500
    assert set(BENCHMARK_CASES) == {"S", "M", "L", "O", "BATCH"}
    assert not torch.equal(benchmark_case("S", seed=1).points_gt, benchmark_case("S").points_gt)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"num_poses": 1}, "'num_poses' must be an int >= 2, got 1"),
        ({"num_points": 2}, "'num_points' must be an int >= 3"),
        ({"batch_size": 0}, "'batch_size' must be an int >= 1"),
        ({"trajectory": "circle"}, "'trajectory' must be 'loop', 'helix' or 'random_walk'"),
        ({"visibility": "fov"}, "'visibility' must be 'fraction' or 'range'"),
        ({"visible_fraction": 0.0}, r"'visible_fraction' must be in \(0, 1\]"),
        ({"max_range": -1.0}, "'max_range' must be > 0"),
        ({"noise_std": float("nan")}, "'noise_std' must be >= 0"),
        ({"outlier_fraction": 1.0}, r"'outlier_fraction' must be in \[0, 1\)"),
    ],
)
def test_bad_arguments(kwargs, match):
    arguments = {"num_poses": 5, "num_points": 20, **kwargs}
    with pytest.raises(ValueError, match=match):
        make_scene(**arguments)


def test_bad_dtype_and_case_name():
    with pytest.raises(TypeError, match=r"'dtype' must be torch.float32 or torch.float64"):
        make_scene(5, 20, dtype=torch.float16)
    with pytest.raises(ValueError, match="'name' must be one of"):
        benchmark_case("XL")  # type: ignore[arg-type]
