"""Metrics: zero on ground truth, known values on known perturbations, alignment, batching."""

from __future__ import annotations

import math

import pytest
import torch

from torchslam.data import make_scene
from torchslam.initialization import chain_relative_poses
from torchslam.lie import se3, so3
from torchslam.metrics import (
    absolute_trajectory_error,
    align_trajectories,
    evaluate,
    point_errors,
    pose_errors,
    relative_pose_error,
)


@pytest.fixture
def scene():
    return make_scene(12, 80, batch_size=3, noise_std=0, seed=21)


def _random_axes(count, generator):
    a = torch.randn(count, 3, generator=generator, dtype=torch.float64)
    return a / a.norm(dim=-1, keepdim=True)


def test_ground_truth_against_itself_is_zero(scene):
    errors = evaluate(scene.poses_gt, scene.poses_gt, scene.points_gt, scene.points_gt)
    assert errors.rotation_error_deg.shape == (3, 12)
    assert errors.translation_error.shape == (3, 12)
    assert errors.ate.shape == (3,)
    assert errors.rpe_rotation_deg.shape == (3, 11)
    assert errors.point_error.shape == (3, 80) and errors.point_rmse.shape == (3,)
    assert errors.rotation_error_deg.abs().max() < 1e-10
    assert errors.rpe_rotation_deg.abs().max() < 1e-10
    for x in (errors.translation_error, errors.ate, errors.rpe_translation, errors.point_rmse):
        assert x.abs().max() < 1e-12
    assert errors.max_rotation_error_deg < 1e-10 and errors.mean_point_rmse == 0.0
    assert errors.alignment is None


@pytest.mark.parametrize("side", ["left", "right"])
def test_known_rotation_error(scene, generator, side):
    angle = torch.tensor([1e-9, 0.3, 2.0, math.pi - 1e-6], dtype=torch.float64)
    poses = scene.poses_gt[0, :4]
    R_err = so3.exp(_random_axes(4, generator) * angle[:, None])
    E = se3.from_rotation_translation(R_err, torch.zeros(4, 3, dtype=torch.float64))
    perturbed = E @ poses if side == "left" else poses @ E
    rotation, _ = pose_errors(perturbed, poses)
    torch.testing.assert_close(rotation, torch.rad2deg(angle), rtol=1e-7, atol=1e-12)


def test_known_translation_error_and_ate(scene, generator):
    offsets = 0.1 * torch.randn(3, 12, 3, generator=generator, dtype=torch.float64)
    offsets[:, 0] = 0
    world_poses = se3.inverse(scene.poses_gt)  # T_0i: translation = sensor position
    world_poses[..., :3, 3] += offsets
    moved = se3.inverse(world_poses)
    rotation, translation = pose_errors(moved, scene.poses_gt)
    assert rotation.abs().max() < 1e-10
    torch.testing.assert_close(translation, offsets.norm(dim=-1), atol=1e-13, rtol=0)
    ate = absolute_trajectory_error(moved, scene.poses_gt)
    torch.testing.assert_close(ate, offsets.square().sum(-1).mean(-1).sqrt(), atol=1e-13, rtol=0)
    errors = evaluate(moved, scene.poses_gt)
    assert math.isclose(errors.mean_ate, float(ate.mean()), rel_tol=1e-12)
    assert math.isclose(errors.mean_translation_error, float(translation.mean()), rel_tol=1e-12)
    assert errors.point_error is None and errors.mean_point_rmse is None


def test_rpe_of_one_perturbed_step(scene):
    relative = scene.poses_gt[:, 1:] @ se3.inverse(scene.poses_gt[:, :-1])  # T_{i+1,i}
    theta, tau = math.radians(4.0), 0.3
    axis = torch.tensor([0.0, 0.6, 0.8], dtype=torch.float64)
    E = se3.from_rotation_translation(
        so3.exp(theta * axis), torch.tensor([0.0, tau, 0.0], dtype=torch.float64)
    )
    # Perturb the motion T_{i,i+1} of step 5 on the right: T̂_{6,5} = E⁻¹ T_{6,5}.
    relative[:, 5] = se3.inverse(E) @ relative[:, 5]
    estimate = chain_relative_poses(relative)
    rpe_rotation, rpe_translation = relative_pose_error(estimate, scene.poses_gt)
    expected_rotation = torch.zeros(3, 11, dtype=torch.float64)
    expected_rotation[:, 5] = 4.0
    expected_translation = torch.zeros(3, 11, dtype=torch.float64)
    expected_translation[:, 5] = tau
    torch.testing.assert_close(rpe_rotation, expected_rotation, atol=1e-9, rtol=0)
    torch.testing.assert_close(rpe_translation, expected_translation, atol=1e-12, rtol=0)
    # The absolute error after step 5 is 4° for every later frame (a rigid offset).
    rotation, _ = pose_errors(estimate, scene.poses_gt)
    torch.testing.assert_close(rotation[:, 6:], torch.full_like(rotation[:, 6:], 4.0))
    assert rotation[:, :6].abs().max() < 1e-10


def test_point_error(scene, generator):
    offsets = torch.randn(3, 80, 3, generator=generator, dtype=torch.float64)
    errors = point_errors(scene.points_gt + offsets, scene.points_gt)
    torch.testing.assert_close(errors, offsets.norm(dim=-1), atol=1e-13, rtol=0)
    result = evaluate(scene.poses_gt, scene.poses_gt, scene.points_gt + offsets, scene.points_gt)
    torch.testing.assert_close(result.point_rmse, offsets.square().sum(-1).mean(-1).sqrt())


def test_alignment_removes_a_global_rigid_motion(scene, generator):
    S = se3.exp(torch.randn(3, 6, generator=generator, dtype=torch.float64))
    # Another gauge: every world pose T_0i and point moved by S.
    poses = scene.poses_gt @ se3.inverse(S)[:, None]
    points = se3.act(S[:, None], scene.points_gt)
    unaligned = evaluate(poses, scene.poses_gt, points, scene.points_gt)
    assert unaligned.mean_ate > 0.1 and unaligned.mean_point_rmse > 0.1
    # The RPE does not see a global motion.
    assert unaligned.rpe_rotation_deg.abs().max() < 1e-9
    assert unaligned.rpe_translation.abs().max() < 1e-12
    aligned = evaluate(poses, scene.poses_gt, points, scene.points_gt, align="se3")
    torch.testing.assert_close(aligned.alignment, se3.inverse(S), atol=1e-12, rtol=0)
    assert aligned.max_rotation_error_deg < 1e-9
    assert aligned.mean_ate < 1e-12 and aligned.mean_point_rmse < 1e-12
    torch.testing.assert_close(align_trajectories(poses, scene.poses_gt), se3.inverse(S))


def test_arbitrary_leading_dims_and_summary(scene, generator):
    poses = scene.poses_gt @ se3.exp(0.05 * torch.randn(3, 12, 6, generator=generator).double())
    flat = evaluate(poses, scene.poses_gt)
    nested = evaluate(poses.reshape(3, 1, 12, 4, 4), scene.poses_gt.reshape(3, 1, 12, 4, 4))
    assert nested.rotation_error_deg.shape == (3, 1, 12) and nested.ate.shape == (3, 1)
    torch.testing.assert_close(nested.rotation_error_deg.reshape(3, 12), flat.rotation_error_deg)
    assert math.isclose(flat.mean_rotation_error_deg, float(flat.rotation_error_deg.mean()))
    assert math.isclose(flat.max_rotation_error_deg, float(flat.rotation_error_deg.max()))
    assert math.isclose(flat.mean_rpe_rotation_deg, float(flat.rpe_rotation_deg.mean()))
    assert "ATE" in flat.summary()


def test_differentiable(scene):
    xi = torch.full((3, 12, 6), 0.01, dtype=torch.float64, requires_grad=True)
    errors = evaluate(scene.poses_gt @ se3.exp(xi), scene.poses_gt)
    (errors.rotation_error_deg.sum() + errors.ate.sum()).backward()
    assert torch.isfinite(xi.grad).all() and xi.grad.abs().sum() > 0


def test_bad_input(scene):
    with pytest.raises(ValueError, match="'poses' and 'poses_gt' must have the same shape"):
        evaluate(scene.poses_gt[:, 1:], scene.poses_gt)
    with pytest.raises(ValueError, match=r"'poses' must have shape \(\.\.\., m, 4, 4\)"):
        pose_errors(scene.poses_gt[0, 0], scene.poses_gt[0, 0])
    with pytest.raises(TypeError, match=r"'poses' is torch.float32 but 'poses_gt' is"):
        evaluate(scene.poses_gt.float(), scene.poses_gt)
    with pytest.raises(ValueError, match="pass both 'points' and 'points_gt' or neither"):
        evaluate(scene.poses_gt, scene.poses_gt, scene.points_gt)
    with pytest.raises(ValueError, match="'align' must be 'none' or 'se3'"):
        evaluate(scene.poses_gt, scene.poses_gt, align="sim3")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="'points' must have the batch dims of 'poses'"):
        evaluate(scene.poses_gt, scene.poses_gt, scene.points_gt[:1], scene.points_gt[:1])
    bad = scene.poses_gt.clone()
    bad[0, 1, :3, :3] *= 2
    with pytest.raises(ValueError, match="'poses_gt' must hold rotation matrices"):
        evaluate(scene.poses_gt, bad)
