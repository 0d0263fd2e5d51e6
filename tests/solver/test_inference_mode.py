"""The no-grad solves run in ``torch.inference_mode`` (torchslam._inference); nothing made there
may leak: results, callback records, problem parameters and every cache kept across calls
(index tensors, per-term factors, constant tables, sparse sum matrices) are normal tensors
that a later autograd solve can save for its backward and a user can edit in place."""

from __future__ import annotations

import dataclasses
import warnings

import pytest
import torch

import torchslam
from tests.solver import drifted, problem_from
from torchslam.lie import _series, se3
from torchslam.solver import segments


def _tensors(value) -> list[torch.Tensor]:
    if isinstance(value, torch.Tensor):
        return [value]
    if dataclasses.is_dataclass(value):
        return [t for f in dataclasses.fields(value) for t in _tensors(getattr(value, f.name))]
    return []


def _relative_terms(init, B: int) -> torchslam.RelativePoseTerm:
    """Odometry terms between successive poses (measured at the initial poses)."""
    T = init.poses
    index = torch.tensor([[0, 1], [1, 2], [2, 3]])
    Z = T[:, index[:, 0]] @ se3.inverse(T[:, index[:, 1]])
    weight = torch.full((B, 3), 2.0, dtype=T.dtype)
    return torchslam.RelativePoseTerm(index.expand(B, 3, 2), Z, weight=weight)


def test_solve_results_and_callback_records_are_normal_tensors():
    scene, init = drifted(5, 30)
    problem = problem_from(scene, init.poses, init.points)
    records = []
    result = torchslam.solve(problem, callback=records.append)
    assert records
    for t in _tensors(result) + [t for info in records for t in _tensors(info)]:
        assert not t.is_inference()
    assert not problem.pose_tangent.is_inference() and not problem.points.is_inference()
    # Usable as a user would: in place, and under autograd.
    result.points.add_(0.0)
    w = torch.ones((), dtype=torch.float64, requires_grad=True)
    (result.pose_tangent * w).sum().backward()
    assert w.grad is not None


def test_caches_made_in_a_no_grad_solve_serve_a_later_autograd_solve():
    """A no-grad solve first (its caches are built then), then a differentiable solve of the
    same data and terms: the caches must be normal tensors for the backward to save them."""
    scene, init = drifted(5, 30, batch_size=2)
    term = _relative_terms(init, 2)
    problem = problem_from(scene, init.poses, init.points, terms=(term,))
    xi0, X0 = problem.pose_tangent.detach().clone(), problem.points.detach().clone()
    first = torchslam.solve_tensors(xi0, X0, problem.data)
    data = problem.data
    assert not data.flat_pose_index.is_inference()
    assert not data.flat_point_index.is_inference()
    for name, cached in vars(term).items():
        if name.endswith("_cache") and cached is not None:
            assert not any(t.is_inference() for t in _tensors(cached[2]) if t is not None)
    assert not any(t.is_inference() for t in _series._TABLES.values())
    for entry in list(segments._CSR.values()):
        assert not entry[4].is_inference()

    xi = xi0.clone().requires_grad_(True)
    for backward in ("unrolled", "implicit"):
        result = torchslam.solve_differentiable(xi, X0, data, backward=backward)
        (grad,) = torch.autograd.grad(result.pose_tangent.square().sum(), xi)
        assert torch.isfinite(grad).all()
    # The same solve again gives the same result (caches reused, not corrupted).
    again = torchslam.solve_tensors(xi0, X0, data)
    assert torch.equal(again.pose_tangent, first.pose_tangent)
    assert torch.equal(again.points, first.points)


def test_solve_inside_a_users_inference_mode_matches():
    """Inputs made in the user's own inference mode (no version counters) are solved the
    same; nothing is cached by version for them."""
    scene, init = drifted(5, 30)
    problem = problem_from(scene, init.poses, init.points)
    xi, X = problem.pose_tangent.detach().clone(), problem.points.detach().clone()
    reference = torchslam.solve_tensors(xi, X, problem.data)
    with torch.inference_mode():
        inner = problem_from(scene, init.poses.clone(), init.points.clone())
        result = torchslam.solve_tensors(
            inner.pose_tangent.detach().clone(), inner.points.detach().clone(), inner.data
        )
    assert torch.equal(result.pose_tangent, reference.pose_tangent)
    assert torch.equal(result.points, reference.points)
    assert result.status == reference.status


def test_the_callback_runs_outside_inference_mode():
    """What a callback keeps or computes is a normal tensor, and it can turn gradients on."""
    scene, init = drifted(5, 30)
    problem = problem_from(scene, init.poses, init.points)
    kept, flags = [], []
    w = torch.ones((), dtype=torch.float64, requires_grad=True)

    def callback(info):
        kept.append(info.cost * 1.0)
        with torch.enable_grad():
            flags.append((w * info.cost.sum()).requires_grad)

    torchslam.solve(problem, torchslam.SolverConfig(max_iterations=2), callback=callback)
    assert kept and all(flags)
    assert not kept[0].is_inference()
    kept[0].add_(1.0)
    (w * kept[0]).sum().backward()
    assert w.grad is not None


def test_solve_with_data_that_require_grad_points_to_solve_differentiable():
    # Weights that require grad tell that the caller may want gradients of the solution: solve
    # warns, naming the tensor and solve_differentiable (issue 28 §4), instead of leaving the
    # user to torch's generic "does not require grad" at the backward. Its result stays plain:
    # it warm-starts a differentiable solve, whose gradients are then the usual ones.
    scene, init = drifted(5, 30)
    weights = torch.ones(scene.valid.shape, dtype=torch.float64, requires_grad=True)
    problem = problem_from(scene, init.poses, init.points, weights=weights)
    with pytest.warns(UserWarning, match=r"data\.weights requires grad.*solve_differentiable"):
        result = torchslam.solve(problem)
    assert not result.points.requires_grad
    result.points.numpy()
    plain = problem_from(scene, init.poses, init.points, weights=weights.detach())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        reference = torchslam.solve(plain)
        with torch.no_grad():
            torchslam.solve(problem_from(scene, init.poses, init.points, weights=weights))
    assert torch.equal(result.pose_tangent, reference.pose_tangent)
    warm = torchslam.solve_differentiable(result.pose_tangent, result.points, problem.data)
    (grad,) = torch.autograd.grad(warm.points.square().sum(), weights)
    assert torch.isfinite(grad).all()
