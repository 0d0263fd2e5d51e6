"""Initialization (seed section 0): Kabsch chaining, odometry drift, point averaging, fallbacks."""

from __future__ import annotations

import math
import warnings

import pytest
import torch

from torchslam.alignment import weighted_kabsch
from torchslam.data import make_scene
from torchslam.initialization import (
    average_points,
    chain_relative_poses,
    initialize,
    initialize_scene,
    odometry_relative_poses,
    relative_poses_kabsch,
)
from torchslam.lie import se3, so3
from torchslam.metrics import relative_pose_error


def _true_relative(poses_gt):
    """T_{i+1,i} = T_{i+1,0} T_{i0}⁻¹, (B, m-1, 4, 4)."""
    return poses_gt[:, 1:] @ se3.inverse(poses_gt[:, :-1])


def _angle_deg(R):
    return torch.rad2deg(so3.log(R).norm(dim=-1))


@pytest.mark.parametrize("trajectory", ["loop", "helix", "random_walk"])
@pytest.mark.parametrize("visibility", ["fraction", "range"])
def test_noise_free_kabsch_chaining_recovers_ground_truth(trajectory, visibility):
    scene = make_scene(
        15, 120, batch_size=3, trajectory=trajectory, visibility=visibility, noise_std=0, seed=2
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the generator's guarantees mean no fallback
        init = initialize_scene(scene)
    assert not init.fallback.any()
    torch.testing.assert_close(init.poses, scene.poses_gt, atol=1e-10, rtol=0)
    torch.testing.assert_close(init.points, scene.points_gt, atol=1e-10, rtol=0)
    torch.testing.assert_close(
        init.relative_poses, _true_relative(scene.poses_gt), atol=1e-10, rtol=0
    )
    assert torch.equal(init.poses[:, 0], torch.eye(4, dtype=torch.float64).expand(3, 4, 4))


def test_float32(device):
    scene = make_scene(
        8, 100, batch_size=2, noise_std=0, seed=1, dtype=torch.float32, device=device
    )
    init = initialize_scene(scene)
    assert init.poses.dtype == torch.float32 and init.poses.device.type == device.type
    torch.testing.assert_close(init.poses, scene.poses_gt, atol=1e-4, rtol=0)
    torch.testing.assert_close(init.points, scene.points_gt, atol=1e-4, rtol=0)


def test_kabsch_matches_pairwise_reference(generator):
    """The segmented, vectorized alignment equals weighted_kabsch on each pair's shared set."""
    scene = make_scene(6, 60, batch_size=2, visibility="range", noise_std=0.05, seed=4)
    weights = 0.5 + torch.rand(scene.valid.shape, generator=generator, dtype=torch.float64)
    relative = relative_poses_kabsch(
        scene.pose_index,
        scene.point_index,
        scene.observations,
        scene.num_poses,
        valid=scene.valid,
        weights=weights,
    )
    dense, seen = scene.to_dense()
    dense_w = torch.zeros(seen.shape, dtype=torch.float64)
    b, e = scene.valid.nonzero(as_tuple=True)
    dense_w[b, scene.pose_index[b, e], scene.point_index[b, e]] = weights[b, e]
    for b in range(2):
        for i in range(5):
            shared = seen[b, i] & seen[b, i + 1]
            w_a, w_b = dense_w[b, i, shared], dense_w[b, i + 1, shared]
            expected = weighted_kabsch(
                dense[b, i, shared], dense[b, i + 1, shared], w_a * w_b / (w_a + w_b)
            )
            torch.testing.assert_close(relative[b, i], expected, atol=1e-12, rtol=0)


def test_padding_content_is_ignored():
    scene = make_scene(8, 80, batch_size=3, visibility="range", noise_std=0.01, seed=5)
    assert not scene.valid.all()
    garbage = scene.observations.clone()
    garbage[~scene.valid] = float("nan")
    pose_index = scene.pose_index.clone()
    pose_index[~scene.valid] = 7  # a real frame: must not be used
    reference = initialize_scene(scene)
    init = initialize(
        pose_index,
        scene.point_index,
        garbage,
        scene.num_poses,
        scene.num_points,
        valid=scene.valid,
    )
    torch.testing.assert_close(init.poses, reference.poses, atol=1e-13, rtol=0)
    torch.testing.assert_close(init.points, reference.points, atol=1e-13, rtol=0)


def test_odometry_has_the_requested_drift():
    scene = make_scene(50, 300, batch_size=2, noise_std=0, seed=3)
    theta, tau = 5.0, 0.05
    relative = odometry_relative_poses(
        scene.poses_gt, rotation_noise_deg=theta, translation_noise=tau, seed=7
    )
    assert relative.shape == (2, 49, 4, 4)
    poses = chain_relative_poses(relative)
    # Every step is off by exactly θ and τ (RPE, Sturm et al.).
    rpe_rotation, rpe_translation = relative_pose_error(poses, scene.poses_gt)
    torch.testing.assert_close(rpe_rotation, torch.full_like(rpe_rotation, theta))
    torch.testing.assert_close(rpe_translation, torch.full_like(rpe_translation, tau))
    # Accumulated: a random walk, bounded by kθ, reaching tens of degrees.
    accumulated = _angle_deg(poses[..., :3, :3] @ scene.poses_gt[..., :3, :3].transpose(-1, -2))
    k = torch.arange(50, dtype=torch.float64)
    assert (accumulated <= k * theta + 1e-9).all()
    assert (accumulated.amax(dim=1) >= 20.0).all()
    assert accumulated[:, 0].abs().max() == 0
    # Seeded.
    again = odometry_relative_poses(
        scene.poses_gt, rotation_noise_deg=theta, translation_noise=tau, seed=7
    )
    other = odometry_relative_poses(
        scene.poses_gt, rotation_noise_deg=theta, translation_noise=tau, seed=8
    )
    assert torch.equal(relative, again) and not torch.allclose(relative, other)
    # Zero noise is the ground truth.
    exact = odometry_relative_poses(scene.poses_gt, rotation_noise_deg=0, translation_noise=0)
    torch.testing.assert_close(chain_relative_poses(exact), scene.poses_gt, atol=1e-12, rtol=0)


def test_initialize_scene_odometry_uses_the_drifted_poses():
    scene = make_scene(20, 200, noise_std=0, seed=6)
    init = initialize_scene(
        scene, method="odometry", rotation_noise_deg=3.0, translation_noise=0.02, seed=1
    )
    expected = chain_relative_poses(
        odometry_relative_poses(
            scene.poses_gt, rotation_noise_deg=3.0, translation_noise=0.02, seed=1
        )
    )
    torch.testing.assert_close(init.poses, expected, atol=0, rtol=0)
    points = average_points(
        init.poses,
        scene.pose_index,
        scene.point_index,
        scene.observations,
        scene.num_points,
        valid=scene.valid,
    )
    torch.testing.assert_close(init.points, points, atol=0, rtol=0)
    assert (init.points - scene.points_gt).norm(dim=-1).max() > 0.1  # really drifted
    assert not init.fallback.any()


def test_chain_equals_the_seed_product(generator):
    xi = torch.randn(2, 6, 6, generator=generator, dtype=torch.float64)
    relative = se3.exp(xi)  # T̂_{i+1,i}
    poses = chain_relative_poses(relative)
    assert poses.shape == (2, 7, 4, 4)
    torch.testing.assert_close(poses[:, 0], torch.eye(4, dtype=torch.float64).expand(2, 4, 4))
    # T̂_0i = T̂_01 T̂_12 ⋯ T̂_{i-1,i} with T̂_{i-1,i} = T̂_{i,i-1}⁻¹.
    product = torch.eye(4, dtype=torch.float64).expand(2, 4, 4)
    for i in range(1, 7):
        product = product @ se3.inverse(relative[:, i - 1])
        torch.testing.assert_close(se3.inverse(poses[:, i]), product, atol=1e-12, rtol=0)


def test_average_points_is_the_mean_of_mapped_views(generator):
    scene = make_scene(5, 30, batch_size=2, noise_std=0.05, seed=9)
    poses = scene.poses_gt @ se3.exp(0.1 * torch.randn(2, 5, 6, generator=generator).double())
    weights = torch.rand(scene.valid.shape, generator=generator, dtype=torch.float64) + 0.1
    points = average_points(
        poses,
        scene.pose_index,
        scene.point_index,
        scene.observations,
        30,
        valid=scene.valid,
        weights=weights,
    )
    for b in range(2):
        for j in range(0, 30, 7):
            edges = (scene.point_index[b] == j) & scene.valid[b]
            views = se3.act(
                se3.inverse(poses[b, scene.pose_index[b, edges]]), scene.observations[b, edges]
            )
            w = weights[b, edges]
            torch.testing.assert_close(points[b, j], (w[:, None] * views).sum(0) / w.sum())


def _drop_shared(scene, problem, frame, keep):
    """Mark invalid the observations in frame+1 of all but ``keep`` points shared with frame."""
    dense_seen = scene.to_dense()[1][problem]
    shared = (dense_seen[frame] & dense_seen[frame + 1]).nonzero().squeeze(-1)
    drop = shared[keep:]
    valid = scene.valid.clone()
    row = (scene.pose_index[problem] == frame + 1) & torch.isin(scene.point_index[problem], drop)
    valid[problem] &= ~row
    return valid


def test_fallback_to_identity_with_a_warning_naming_problem_and_frames():
    scene = make_scene(8, 100, batch_size=3, noise_std=0, seed=10)
    valid = _drop_shared(scene, problem=1, frame=3, keep=2)
    with pytest.warns(UserWarning, match=r"problem 1: frames 3 and 4"):
        init = initialize(
            scene.pose_index,
            scene.point_index,
            scene.observations,
            8,
            100,
            valid=valid,
        )
    expected_fallback = torch.zeros(3, 7, dtype=torch.bool)
    expected_fallback[1, 3] = True
    assert torch.equal(init.fallback, expected_fallback)
    eye = torch.eye(4, dtype=torch.float64)
    assert torch.equal(init.relative_poses[1, 3], eye)
    truth = _true_relative(scene.poses_gt)
    keep = ~expected_fallback
    torch.testing.assert_close(init.relative_poses[keep], truth[keep], atol=1e-10, rtol=0)
    # Problems 0 and 2 are untouched by the fallback.
    torch.testing.assert_close(init.poses[[0, 2]], scene.poses_gt[[0, 2]], atol=1e-10, rtol=0)


def test_fallback_on_collinear_shared_points():
    # Two frames, three shared points on a line: the rotation about the line is undetermined.
    line = torch.tensor([[0.0, 0, 1], [0.0, 0, 2], [0.0, 0, 3]], dtype=torch.float64)
    T = se3.exp(torch.tensor([0.1, 0.2, 0.3, 0.5, 0.0, 0.1], dtype=torch.float64))
    observations = torch.cat((line, se3.act(T, line)))[None]
    pose_index = torch.tensor([[0, 0, 0, 1, 1, 1]])
    point_index = torch.tensor([[0, 1, 2, 0, 1, 2]])
    with pytest.warns(UserWarning, match=r"only collinear ones.*problem 0: frames 0 and 1"):
        relative = relative_poses_kabsch(pose_index, point_index, observations, 2)
    assert torch.equal(relative[0, 0], torch.eye(4, dtype=torch.float64))


def test_gradients_are_finite_with_a_fallback():
    scene = make_scene(6, 60, noise_std=0.01, seed=11)
    valid = _drop_shared(scene, problem=0, frame=2, keep=1)
    observations = scene.observations.clone().requires_grad_(True)
    with pytest.warns(UserWarning, match="frames 2 and 3"):
        init = initialize(scene.pose_index, scene.point_index, observations, 6, 60, valid=valid)
    (init.poses.square().sum() + init.points.square().sum()).backward()
    assert torch.isfinite(observations.grad).all()
    assert observations.grad.abs().sum() > 0


def test_unobserved_point_is_zero_with_a_warning():
    scene = make_scene(6, 40, batch_size=2, noise_std=0, seed=12)
    valid = scene.valid & ~((scene.point_index == 17) & (torch.arange(2)[:, None] == 1))
    with pytest.warns(UserWarning, match=r"\(problem, point\): \(1, 17\)"):
        init = initialize(
            scene.pose_index, scene.point_index, scene.observations, 6, 40, valid=valid
        )
    assert torch.equal(init.points[1, 17], torch.zeros(3, dtype=torch.float64))
    torch.testing.assert_close(init.points[0], scene.points_gt[0], atol=1e-10, rtol=0)


def test_given_relative_poses():
    scene = make_scene(5, 50, batch_size=2, noise_std=0, seed=13)
    init = initialize(
        scene.pose_index,
        scene.point_index,
        scene.observations,
        5,
        50,
        valid=scene.valid,
        relative_poses=_true_relative(scene.poses_gt),
    )
    torch.testing.assert_close(init.poses, scene.poses_gt, atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match=r"'relative_poses' must have shape \(B, m-1, 4, 4\)"):
        initialize(
            scene.pose_index,
            scene.point_index,
            scene.observations,
            5,
            50,
            valid=scene.valid,
            relative_poses=_true_relative(scene.poses_gt)[:, 1:],
        )


def test_bad_input_messages():
    scene = make_scene(5, 30, batch_size=2, noise_std=0, seed=14)
    args = (scene.pose_index, scene.point_index, scene.observations, 5, 30)
    bad_pose = scene.pose_index.clone()
    bad_pose[1, 4] = 5
    with pytest.raises(ValueError, match=r"pose_index\[1, 4\] = 5 is out of range \[0, 5\)"):
        initialize(bad_pose, *args[1:])
    bad_point = scene.point_index.clone()
    bad_point[0, 2] = -1
    with pytest.raises(ValueError, match=r"point_index\[0, 2\] = -1 .*problem 0, observation 2"):
        initialize(args[0], bad_point, *args[2:])
    nan = scene.observations.clone()
    nan[1, 3, 0] = float("nan")
    with pytest.raises(ValueError, match=r"'observations' contains 1 non-finite.*\(1, 3, 0\)"):
        initialize(args[0], args[1], nan, 5, 30)
    with pytest.raises(TypeError, match="'pose_index' must be int64"):
        initialize(scene.pose_index.int(), *args[1:])
    with pytest.raises(ValueError, match=r"'observations' must have shape \(B, E, 3\)"):
        initialize(args[0], args[1], scene.observations[:1], 5, 30)
    with pytest.raises(ValueError, match="'num_poses' must be an int >= 2"):
        initialize(args[0], args[1], args[2], 1, 30)
    with pytest.raises(TypeError, match="'valid' must be a bool tensor"):
        initialize(*args, valid=scene.valid.long())
    with pytest.raises(ValueError, match="'weights' must be >= 0"):
        initialize(*args, weights=-torch.ones(scene.valid.shape, dtype=torch.float64))
    with pytest.raises(ValueError, match="'method' must be 'kabsch' or 'odometry'"):
        initialize_scene(scene, method="icp")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="'rotation_noise_deg' must be finite and >= 0"):
        odometry_relative_poses(scene.poses_gt, rotation_noise_deg=-1.0, translation_noise=0.0)
    with pytest.raises(ValueError, match=r"'poses_gt' must have shape \(\.\.\., m, 4, 4\)"):
        odometry_relative_poses(scene.poses_gt[:, :1], rotation_noise_deg=1, translation_noise=0)
    # Padding may hold out-of-range indices: only valid entries are checked.
    padded = scene.pose_index.clone()
    valid = scene.valid.clone()
    valid[0, -1] = False
    padded[0, -1] = 99
    initialize(padded, *args[1:], valid=valid)


def test_rotation_noise_is_in_degrees():
    poses = se3.identity(1, 3)
    relative = odometry_relative_poses(poses, rotation_noise_deg=90.0, translation_noise=1.0)
    angle = _angle_deg(relative[..., :3, :3])
    torch.testing.assert_close(angle, torch.full_like(angle, 90.0))
    assert math.isclose(float(relative[0, 0, :3, 3].norm()), 1.0, rel_tol=1e-12)
