"""What PointMapData keeps across solves (its free masks, unit weights, whether any slot is
padding) follows in-place edits of the tensors it derives from, and needs no gradient."""

from __future__ import annotations

import torch

import torchslam
from tests.solver import drifted, problem_from


def test_edited_masks_are_seen_by_the_next_solve():
    """Editing ``fixed_points`` / ``valid`` in place after a solve changes the next solve as
    a fresh problem with those values would (the kept values are rebuilt)."""
    scene, init = drifted(5, 30, batch_size=1)
    problem = problem_from(scene, init.poses, init.points)
    data = problem.data
    xi, X = problem.pose_tangent.detach().clone(), problem.points.detach().clone()
    torchslam.solve_tensors(xi, X, data)  # the kept values are built here
    assert data.all_valid()
    data.fixed_points[0, :5] = True
    data.valid[0, -3:] = False
    assert not data.all_valid()
    edited = torchslam.solve_tensors(xi, X, data)
    fresh = torchslam.PointMapData(
        pose_index=data.pose_index,
        point_index=data.point_index,
        observations=data.observations,
        valid=data.valid.clone(),
        weights=None,
        information=None,
        fixed_poses=data.fixed_poses.clone(),
        fixed_points=data.fixed_points.clone(),
        loss=None,
    )
    expected = torchslam.solve_tensors(xi, X, fresh)
    assert torch.equal(edited.points, expected.points)
    assert torch.equal(edited.pose_tangent, expected.pose_tangent)
    assert torch.equal(edited.points[0, :5], X[0, :5])  # held fixed


def test_observations_that_need_a_gradient_are_not_kept():
    """With every slot valid the observations are used as given: a gradient to them flows
    through each solve's graph (two backward passes on two solves of the same data)."""
    scene, init = drifted(5, 30, batch_size=1)
    observations = scene.observations.clone().requires_grad_(True)
    problem = torchslam.PointMapProblem(
        init.poses, init.points, scene.pose_index, scene.point_index, observations
    )
    data = problem.data
    assert data.all_valid()
    for _ in range(2):
        result = torchslam.solve_differentiable(
            problem.pose_tangent.detach(), problem.points.detach(), data, backward="unrolled"
        )
        (grad,) = torch.autograd.grad(result.points.sum(), observations)
        assert torch.isfinite(grad).all() and grad.abs().max() > 0
