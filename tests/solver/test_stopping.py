"""Stopping rules and reporting, configuration checks, failure statuses, and what solve() and
solve_tensors() do to their inputs."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

import torchslam
from torchslam import SolverConfig, Status

from . import drifted, problem_from

NEVER = {"function_tolerance": 0.0, "gradient_tolerance": 0.0, "parameter_tolerance": 0.0}


def _noisy_problem(**kwargs) -> torchslam.PointMapProblem:
    scene, init = drifted(6, 40, noise_std=0.01, rotation_noise_deg=5.0)
    return problem_from(scene, init.poses, init.points, **kwargs)


@pytest.mark.parametrize("algorithm", ["levenberg_marquardt", "gauss_newton", "gradient_descent"])
def test_max_iterations_is_reported_with_its_reason(algorithm):
    problem = _noisy_problem()
    result = torchslam.solve(problem, SolverConfig(algorithm=algorithm, max_iterations=2))
    assert result.status == [Status.MAX_ITERATIONS] * 2
    assert result.converged == [False, False]
    assert result.iterations.tolist() == [2, 2]
    assert result.cost_history.shape == (2, 3)
    assert result.lambda_history.shape == (2, 3)
    assert all("max_iterations" in reason for reason in result.reason)
    summary = result.summary()
    for b in range(2):
        assert f"problem {b}: MAX_ITERATIONS after 2 iterations" in summary
    assert torch.all(result.final_cost < result.initial_cost)
    torch.testing.assert_close(result.cost_history[:, -1], result.final_cost, rtol=0, atol=0)
    torch.testing.assert_close(result.cost_history[:, 0], result.initial_cost, rtol=0, atol=0)


def test_zero_iterations_return_the_start():
    problem = _noisy_problem()
    start = problem.pose_tangent.detach().clone()
    result = torchslam.solve(problem, SolverConfig(max_iterations=0))
    assert result.status == [Status.MAX_ITERATIONS] * 2
    assert result.iterations.tolist() == [0, 0]
    assert torch.equal(result.pose_tangent, start)
    assert torch.equal(result.final_cost, result.initial_cost)
    torch.testing.assert_close(result.initial_cost, problem.cost().detach(), rtol=1e-14, atol=0)


def test_function_tolerance_is_configurable():
    loose = torchslam.solve(_noisy_problem(), SolverConfig(function_tolerance=1e-3))
    tight = torchslam.solve(_noisy_problem(), SolverConfig(function_tolerance=1e-14))
    assert loose.status == [Status.CONVERGED_FUNCTION] * 2
    assert torch.all(loose.iterations < tight.iterations)
    assert torch.all(tight.final_cost <= loose.final_cost)
    assert all("function_tolerance" in reason for reason in loose.reason)
    # The last accepted step decreased the cost by less than 1e-3 relative; the ones before
    # it by more.
    for b in range(2):
        k = int(loose.iterations[b])
        history = loose.cost_history[b, : k + 1]
        relative = (history[:-1] - history[1:]) / history[:-1]
        accepted = relative > 0
        assert float(relative[accepted][-1]) <= 1e-3
        assert torch.all(relative[accepted][:-1] > 1e-3)


def test_negligible_steps_are_neither_evaluated_nor_taken_when_configured():
    # As Ceres: a step the model promises to gain at most function_tolerance·F ends the
    # solve at the point before it, saving that step's linearization.
    config = SolverConfig(function_tolerance=1e-6)
    take = torchslam.solve(_noisy_problem(), config)
    seen = []
    skip = torchslam.solve(
        _noisy_problem(),
        dataclasses.replace(config, take_negligible_steps=False),
        callback=seen.append,
    )
    assert skip.status == [Status.CONVERGED_FUNCTION] * 2
    assert take.linearizations.tolist() == (take.iterations + 1).tolist()
    assert skip.linearizations.tolist() == skip.iterations.tolist()
    for b in range(2):
        k = int(skip.iterations[b])
        # The same iterates up to the step not taken (the same arithmetic), which was tried
        # (a step norm) but left the estimate and its cost as they were.
        assert torch.equal(skip.cost_history[b, :k], take.cost_history[b, :k])
        assert skip.cost_history[b, k] == skip.cost_history[b, k - 1]
        assert float(skip.step_norm_history[b, k - 1]) > 0
        (last,) = [info for info in seen if info.iteration == k]
        assert not bool(last.accepted[b])
        # The step left out gains at most ~function_tolerance·F (its model says so and
        # near the minimum the model is the cost to first order): the minimum to 1e-5.
        gap = float((skip.final_cost[b] - take.final_cost[b]) / take.final_cost[b])
        assert 0.0 <= gap <= 1e-5


def test_gradient_tolerance_is_configurable():
    problem = _noisy_problem()
    result = torchslam.solve_tensors(
        problem.pose_tangent,
        problem.points,
        problem.data,
        SolverConfig(gradient_tolerance=1e-4, function_tolerance=0.0, parameter_tolerance=0.0),
    )
    assert result.status == [Status.CONVERGED_GRADIENT] * 2
    assert torch.all(result.gradient_norm <= 1e-4)
    assert all("gradient_tolerance" in reason for reason in result.reason)
    # Already satisfied at the start: no iteration at all.
    start = torchslam.solve_tensors(
        problem.pose_tangent, problem.points, problem.data, SolverConfig(gradient_tolerance=1e6)
    )
    assert start.status == [Status.CONVERGED_GRADIENT] * 2
    assert start.iterations.tolist() == [0, 0]
    assert torch.equal(start.pose_tangent, problem.pose_tangent.detach())


def test_parameter_tolerance_is_configurable():
    problem = _noisy_problem()
    result = torchslam.solve_tensors(
        problem.pose_tangent,
        problem.points,
        problem.data,
        SolverConfig(parameter_tolerance=1e-6, function_tolerance=0.0, gradient_tolerance=0.0),
    )
    assert result.status == [Status.CONVERGED_PARAMETER] * 2
    assert all("parameter_tolerance" in reason for reason in result.reason)
    strict = torchslam.solve_tensors(
        problem.pose_tangent,
        problem.points,
        problem.data,
        SolverConfig(parameter_tolerance=1e-12, function_tolerance=0.0, gradient_tolerance=0.0),
    )
    assert torch.all(result.iterations < strict.iterations)


def test_without_tolerances_lm_stops_at_the_damping_limit():
    problem = _noisy_problem()
    result = torchslam.solve_tensors(
        problem.pose_tangent, problem.points, problem.data, SolverConfig(**NEVER)
    )
    assert result.status == [Status.DAMPING_LIMIT] * 2
    assert torch.all(result.lambda_history[:, -1] > SolverConfig().max_lambda)
    assert all("max_lambda" in reason for reason in result.reason)
    # Still at the minimum: every accepted step before the limit decreased the cost.
    reference = torchslam.solve_tensors(problem.pose_tangent, problem.points, problem.data)
    torch.testing.assert_close(result.final_cost, reference.final_cost, rtol=1e-9, atol=0)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("algorithm", "newton"),
        ("damping", "nielsen"),
        ("jacobian", "finite_differences"),
        ("linear_solver", "cg"),
        ("max_iterations", -1),
        ("function_tolerance", -1e-6),
        ("gradient_tolerance", -1.0),
        ("parameter_tolerance", float("nan")),
        ("initial_lambda", -1.0),
        ("max_lambda", float("nan")),
        ("min_lambda", -1e-3),
        ("step_size", -0.1),
        ("schur_chunk_size", 0),
        ("initial_lambda", 0.0),
        ("initial_lambda", float("inf")),
        ("min_lambda", float("inf")),
        ("max_lambda", 0.0),
        ("function_tolerance", float("inf")),
        ("gradient_tolerance", float("nan")),
        ("step_size", 0.0),
        ("step_size", float("nan")),
        ("dense_max_variables", -1),
        ("reduced_solver", "cholmod"),
        ("ordering", "amd"),
    ],
)
def test_config_rejects_bad_values_naming_the_field(field, value):
    with pytest.raises(ValueError, match=f"SolverConfig: '{field}'"):
        SolverConfig(**{field: value})


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("max_iterations", 2.5),
        ("max_iterations", True),
        ("max_iterations", "10"),
        ("schur_chunk_size", float("nan")),
        ("schur_chunk_size", 1e6),
        ("dense_max_variables", None),
        ("initial_lambda", "1e-4"),
        ("function_tolerance", None),
        ("gradient_tolerance", False),
        ("step_size", torch.tensor(0.1)),
        ("algorithm", None),
        ("jacobian", 1),
        ("take_negligible_steps", 1),
        ("take_negligible_steps", "no"),
    ],
)
def test_config_rejects_wrong_types_naming_the_field(field, value):
    # Options follow one convention: any unusable value, of any type, is a ValueError.
    with pytest.raises(ValueError, match=f"SolverConfig: '{field}' must be"):
        SolverConfig(**{field: value})


def test_config_relations_and_accepted_edge_values():
    with pytest.raises(ValueError, match=r"'min_lambda' \(1\.0\) must not exceed 'max_lambda'"):
        SolverConfig(min_lambda=1.0, max_lambda=0.5)
    # max_lambda = inf (never give up), zero tolerances and integer floats are fine.
    config = SolverConfig(max_lambda=math.inf, function_tolerance=0, initial_lambda=1)
    assert config.max_lambda == math.inf and isinstance(config.initial_lambda, float)
    assert SolverConfig(max_iterations=np.int64(3)).max_iterations == 3


def test_config_is_frozen_and_keeps_its_values():
    config = SolverConfig(algorithm="gauss_newton", max_iterations=7, function_tolerance=1e-6)
    assert (config.algorithm, config.max_iterations, config.function_tolerance) == (
        "gauss_newton",
        7,
        1e-6,
    )
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.max_iterations = 3  # type: ignore[misc]


@pytest.mark.parametrize("linear_solver", ["schur", "dense"])
def test_gauss_newton_on_a_singular_system_reports_linear_solve_failed(linear_solver):
    # Every observation of pose 3 has weight 0: nothing constrains it, so JᵀJ has six exact
    # zero rows and columns and Cholesky must fail; Gauss-Newton has no damping to fall back on.
    scene, init = drifted(6, 40, noise_std=0.01, rotation_noise_deg=5.0)
    weights = torch.ones(scene.valid.shape, dtype=torch.float64)
    weights[scene.pose_index == 3] = 0.0
    problem = problem_from(scene, init.poses, init.points, weights=weights)
    start = problem.pose_tangent.detach().clone()
    config = SolverConfig(algorithm="gauss_newton", linear_solver=linear_solver)
    result = torchslam.solve(problem, config)
    assert result.status == [Status.LINEAR_SOLVE_FAILED] * 2
    assert result.iterations.tolist() == [1, 1]
    assert torch.equal(result.pose_tangent, start)  # nothing was applied
    assert torch.equal(result.final_cost, result.initial_cost)
    for reason in result.reason:
        assert "not positive definite" in reason and "Levenberg-Marquardt" in reason
    summary = result.summary()
    assert "problem 0: LINEAR_SOLVE_FAILED after 1 iterations" in summary
    assert "problem 1: LINEAR_SOLVE_FAILED" in summary


def test_solve_updates_the_problem_in_place():
    problem = _noisy_problem()
    pose_parameter, point_parameter = problem.pose_tangent, problem.points
    start = problem.pose_tangent.detach().clone()
    result = torchslam.solve(problem, SolverConfig())
    assert problem.pose_tangent is pose_parameter and problem.points is point_parameter
    assert torch.equal(problem.pose_tangent.detach(), result.pose_tangent)
    assert torch.equal(problem.points.detach(), result.points)
    assert not torch.equal(problem.pose_tangent.detach(), start)
    torch.testing.assert_close(problem.cost().detach(), result.final_cost, rtol=1e-12, atol=0)
    # The result does not alias the parameters: a second solve leaves it alone.
    kept = result.pose_tangent.clone()
    torchslam.solve(problem, SolverConfig(max_iterations=1))
    assert torch.equal(result.pose_tangent, kept)


def test_solve_tensors_leaves_its_inputs_untouched():
    problem = _noisy_problem()
    xi = problem.pose_tangent.detach().clone()
    points = problem.points.detach().clone()
    xi_in, points_in = xi.clone(), points.clone()
    observations = problem.data.observations.clone()
    result = torchslam.solve_tensors(xi, points, problem.data, SolverConfig())
    assert all(result.converged), result.summary()
    assert torch.equal(xi, xi_in) and torch.equal(points, points_in)
    assert torch.equal(problem.data.observations, observations)
    assert torch.equal(problem.pose_tangent.detach(), xi_in)
    assert result.pose_tangent.data_ptr() != xi.data_ptr()
    assert not torch.equal(result.pose_tangent, xi_in)


def test_fixed_poses_and_points_stay_exactly_where_they_were():
    # A gauge away from the identity and a few more fixed poses and points: their values come
    # back bit for bit (their step is exactly zero), the free ones still converge.
    scene, init = drifted(6, 40, noise_std=0.01, rotation_noise_deg=5.0)
    offset = torchslam.se3.exp(torch.tensor([0.3, -0.2, 0.1, 1.0, 2.0, -0.5], dtype=torch.float64))
    poses = init.poses @ offset
    fixed_poses = torch.zeros(2, scene.num_poses, dtype=torch.bool)
    fixed_poses[:, [0, 3]] = True
    fixed_points = torch.zeros(2, scene.num_points, dtype=torch.bool)
    fixed_points[:, ::5] = True
    problem = torchslam.PointMapProblem(
        poses,
        init.points,
        scene.pose_index,
        scene.point_index,
        scene.observations,
        valid=scene.valid,
        fixed_poses=fixed_poses,
        fixed_points=fixed_points,
    )
    start_xi = problem.pose_tangent.detach().clone()
    start_points = problem.points.detach().clone()
    for algorithm in ("levenberg_marquardt", "gauss_newton", "gradient_descent"):
        result = torchslam.solve_tensors(
            problem.pose_tangent,
            problem.points,
            problem.data,
            SolverConfig(algorithm=algorithm, max_iterations=20),
        )
        assert torch.equal(result.pose_tangent[fixed_poses], start_xi[fixed_poses])
        assert torch.equal(result.points[fixed_points], start_points[fixed_points])
        assert not torch.equal(result.pose_tangent[~fixed_poses], start_xi[~fixed_poses])
        assert torch.all(result.final_cost < result.initial_cost)
