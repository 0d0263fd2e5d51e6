"""Closed-loop scenes: shapes, conventions, determinism, visibility structure, argument errors."""

from __future__ import annotations

import math

import pytest
import torch

from torchslam.data.loop import LoopScene, make_loop_scene
from torchslam.lie import se3


def _relative(scene: LoopScene, pairs: torch.Tensor) -> torch.Tensor:
    """T_i0 T_j0⁻¹ for each (i, j) of pairs, (K, 4, 4)."""
    T = scene.scene.poses_gt[0]
    return T[pairs[:, 0]] @ se3.inverse(T[pairs[:, 1]])


def test_shapes_and_dtypes():
    m, k, w = 12, 5, 3
    ls = make_loop_scene(num_poses=m, points_per_frame=k, window=w, seed=1)
    s = ls.scene
    n = (m - 1) * k
    # Point born at frame i is seen by min(w, m - i) frames.
    E = sum(k * min(w, m - i) for i in range(m - 1))
    assert s.poses_gt.shape == (1, m, 4, 4)
    assert s.points_gt.shape == (1, n, 3)
    assert s.pose_index.shape == s.point_index.shape == s.valid.shape == (1, E)
    assert s.observations.shape == (1, E, 3)
    assert s.valid.all() and not s.is_outlier.any()
    assert s.pose_index.dtype == s.point_index.dtype == torch.long
    assert ls.odometry.shape == (m - 1, 4, 4) and ls.loop.shape == (1, 4, 4)
    assert torch.equal(ls.odometry_pairs, torch.stack((torch.arange(m - 1), torch.arange(1, m)), 1))
    assert torch.equal(ls.loop_pairs, torch.tensor([[m - 1, 0]]))
    assert ls.odometry_pairs.dtype == ls.loop_pairs.dtype == torch.long
    assert ls.birth_frame.shape == (n,)
    assert ls.num_poses == m and ls.window == w and ls.noise_std == 0.01
    assert ls.odometry_rotation_std == pytest.approx(math.radians(0.5))
    assert ls.loop_translation_std == 0.005
    # Gauge and rigid poses.
    assert torch.equal(s.poses_gt[0, 0], torch.eye(4, dtype=torch.float64))
    R = s.poses_gt[0, :, :3, :3]
    torch.testing.assert_close(
        R.transpose(-1, -2) @ R, torch.eye(3, dtype=torch.float64).expand_as(R)
    )
    # Edge list sorted by (pose, point), unique.
    key = s.pose_index[0] * n + s.point_index[0]
    assert (key[1:] > key[:-1]).all()


def test_float32_and_information():
    ls = make_loop_scene(num_poses=8, points_per_frame=4, dtype=torch.float32)
    for x in (ls.scene.poses_gt, ls.scene.observations, ls.odometry, ls.loop):
        assert x.dtype == torch.float32
    info = ls.odometry_information()
    assert info.shape == (6, 6) and info.dtype == torch.float32
    expected = [math.radians(0.5) ** -2] * 3 + [0.02**-2] * 3
    torch.testing.assert_close(info, torch.diag(torch.tensor(expected)))
    torch.testing.assert_close(
        ls.loop_information().diagonal(),
        torch.tensor([math.radians(0.1) ** -2] * 3 + [0.005**-2] * 3),
    )
    with pytest.raises(ValueError, match="must be > 0"):
        make_loop_scene(num_poses=8, loop_translation=0.0).loop_information()


def test_trajectory_closes():
    """Frame m-1 is one ordinary step before frame 0 (the loop comes back to its start)."""
    ls = make_loop_scene(num_poses=40, noise_std=0.0, seed=3)
    T = ls.scene.poses_gt[0]
    centres = se3.inverse(T)[:, :3, 3]
    steps = (centres[1:] - centres[:-1]).norm(dim=-1)
    closing = (centres[-1] - centres[0]).norm()
    assert 0.5 * steps.mean() < closing < 1.5 * steps.mean()
    # The loop's relative motion is about as large as an odometry step, in angle too.
    step_angles = se3.log(_relative(ls, ls.odometry_pairs))[:, :3].norm(dim=-1)
    loop_angle = se3.log(_relative(ls, ls.loop_pairs))[:, :3].norm(dim=-1)
    assert loop_angle < 2 * step_angles.max()
    # It really goes round: the farthest centre is ~ a diameter away from the start.
    assert (centres - centres[0]).norm(dim=-1).max() > 1.5 * 4.0


def test_deterministic_by_seed():
    a = make_loop_scene(num_poses=10, points_per_frame=4, seed=7)
    b = make_loop_scene(num_poses=10, points_per_frame=4, seed=7)
    c = make_loop_scene(num_poses=10, points_per_frame=4, seed=8)
    for x, y in (
        (a.scene.poses_gt, b.scene.poses_gt),
        (a.scene.points_gt, b.scene.points_gt),
        (a.scene.observations, b.scene.observations),
        (a.odometry, b.odometry),
        (a.loop, b.loop),
    ):
        assert torch.equal(x, y)
    assert not torch.equal(a.scene.observations, c.scene.observations)
    assert not torch.equal(a.odometry, c.odometry)


def test_noise_free_is_exact():
    ls = make_loop_scene(
        num_poses=15,
        points_per_frame=5,
        noise_std=0.0,
        odometry_rotation_deg=0.0,
        odometry_translation=0.0,
        loop_rotation_deg=0.0,
        loop_translation=0.0,
        seed=2,
    )
    s = ls.scene
    expected = se3.act(s.poses_gt[0, s.pose_index[0]], s.points_gt[0, s.point_index[0]])
    torch.testing.assert_close(s.observations[0], expected, atol=1e-12, rtol=0)
    torch.testing.assert_close(ls.odometry, _relative(ls, ls.odometry_pairs), atol=1e-12, rtol=0)
    torch.testing.assert_close(ls.loop, _relative(ls, ls.loop_pairs), atol=1e-12, rtol=0)
    # Z_{m-1,0} = T_{m-1,0} since T_00 = I.
    torch.testing.assert_close(ls.loop[0], s.poses_gt[0, -1], atol=1e-12, rtol=0)


def test_noise_has_the_requested_size():
    ls = make_loop_scene(
        num_poses=200,
        points_per_frame=10,
        noise_std=0.05,
        odometry_rotation_deg=2.0,
        odometry_translation=0.1,
        seed=4,
    )
    s = ls.scene
    clean = se3.act(s.poses_gt[0, s.pose_index[0]], s.points_gt[0, s.point_index[0]])
    std = (s.observations[0] - clean).std()
    assert abs(float(std) - 0.05) < 0.003
    # Right perturbation: ε = Log((T_i0 T_j0⁻¹)⁻¹ Z_ij).
    eps = se3.log(se3.inverse(_relative(ls, ls.odometry_pairs)) @ ls.odometry)
    assert abs(float(eps[:, :3].std()) - math.radians(2.0)) < 0.15 * math.radians(2.0)
    assert abs(float(eps[:, 3:].std()) - 0.1) < 0.015


@pytest.mark.parametrize("seed", [0, 5])
@pytest.mark.parametrize(("m", "k", "w"), [(10, 3, 2), (30, 6, 4), (8, 4, 7)])
def test_visibility_structure(seed, m, k, w):
    ls = make_loop_scene(num_poses=m, points_per_frame=k, window=w, seed=seed)
    _, seen = ls.scene.to_dense()
    seen = seen[0]  # (m, n)
    assert (seen.sum(1) >= 3).all(), "a frame sees fewer than 3 points"
    assert (seen.sum(0) >= 2).all(), "a point is seen by fewer than 2 frames"
    assert ((seen[:-1] & seen[1:]).sum(-1) >= 3).all(), "successive frames share < 3 points"
    # No data association across the loop.
    assert not (seen[0] & seen[-1]).any()
    # Point j is seen exactly by frames birth_j, ..., min(birth_j + w, m) - 1.
    frames = torch.arange(m)[:, None]
    birth = ls.birth_frame
    assert torch.equal(seen, (frames >= birth) & (frames < birth + w))
    assert torch.equal(birth.bincount(minlength=m - 1), torch.full((m - 1,), k))
    # Points are born near their sensor: 1-4 m from it.
    centres = se3.inverse(ls.scene.poses_gt[0])[:, :3, 3]
    distance = (ls.scene.points_gt[0] - centres[birth]).norm(dim=-1)
    assert (distance >= 1.0 - 1e-9).all() and (distance <= 4.0 + 1e-9).all()


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"num_poses": 2, "window": 2}, ValueError, r"'num_poses' must be an int >= 3, got 2"),
        ({"num_poses": 10.0}, TypeError, r"'num_poses' must be an int, got 10.0"),
        ({"points_per_frame": 2}, ValueError, r"'points_per_frame' must be an int >= 3, got 2"),
        ({"window": 1}, ValueError, r"'window' must be an int in \[2, num_poses - 1\]"),
        ({"num_poses": 6, "window": 6}, ValueError, r"\[2, 5\], got 6"),
        ({"window": True}, TypeError, r"'window' must be an int, got True"),
        ({"seed": "0"}, TypeError, r"'seed' must be an int"),
        ({"noise_std": -0.1}, ValueError, r"'noise_std' must be a finite number >= 0, got -0.1"),
        ({"odometry_rotation_deg": math.nan}, ValueError, r"'odometry_rotation_deg'.*got nan"),
        ({"odometry_translation": -1}, ValueError, r"'odometry_translation'.*>= 0, got -1"),
        ({"loop_rotation_deg": math.inf}, ValueError, r"'loop_rotation_deg'.*got inf"),
        ({"loop_translation": "1"}, TypeError, r"'loop_translation' must be a real number"),
        ({"radius": 0.0}, ValueError, r"'radius' must be a finite number > 0, got 0.0"),
        ({"dtype": torch.int64}, TypeError, r"'dtype' must be torch.float32 or torch.float64"),
    ],
)
def test_argument_errors(kwargs, error, match):
    with pytest.raises(error, match="make_loop_scene: argument " + ".*" + match):
        make_loop_scene(**kwargs)
