"""Batching: B problems solved together behave exactly as B solo solves (own λ, own
accept/reject, own convergence), a stopped problem stays put, and an ill-posed or failing
problem neither crashes the solve nor disturbs its neighbours."""

from __future__ import annotations

import warnings

import pytest
import torch

import torchslam
from torchslam import SolverConfig, Status

from . import drifted, ground_truth_errors, max_rotation_drift_deg, problem_from, single

# Stopping rules that trigger decisively (quadratic convergence jumps over them), so that
# round-off differences between a batched and a solo solve cannot change an iteration count.
DECISIVE = {"function_tolerance": 1e-9, "gradient_tolerance": 1e-10}
FIRST = slice(0, 1)


def _mixed_difficulty_batch():
    """Three noisy problems started at 0.2°, 3° and 8° of odometry error per step."""
    scene, _ = drifted(8, 60, batch_size=3, noise_std=0.01)
    poses, points = [], []
    for b, (rotation, translation) in enumerate(((0.2, 0.005), (3.0, 0.1), (8.0, 0.2))):
        _, init = drifted(
            8,
            60,
            batch_size=3,
            noise_std=0.01,
            rotation_noise_deg=rotation,
            translation_noise=translation,
        )
        poses.append(init.poses[b])
        points.append(init.points[b])
    return scene, torch.stack(poses), torch.stack(points)


def _solo(problem: torchslam.PointMapProblem, b: int, config: SolverConfig):
    return torchslam.solve_tensors(
        problem.pose_tangent[b : b + 1],
        problem.points[b : b + 1],
        single(problem.data, b),
        config,
    )


def _assert_same_as_solo(batched, solo, b: int) -> None:
    assert batched.status[b] == solo.status[0]
    assert int(batched.iterations[b]) == int(solo.iterations[0])
    K = solo.cost_history.shape[1]
    # Costs agree to 1e-12 relative; a noise-free problem ends at its round-off floor (cost
    # ~1e-24 for an initial O(1)), where batched and solo kernels (other GEMM shapes, CPUs)
    # round differently: there only |Δcost| ≤ 1e-12·initial cost is meaningful.
    initial = float(solo.cost_history[0, 0])
    torch.testing.assert_close(
        batched.cost_history[b, :K], solo.cost_history[0], rtol=1e-12, atol=1e-12 * initial
    )
    # λ follows the gain ratios, which are rounding noise once the cost it starts from is at
    # the floor: compare the λ of steps taken from costs above 1e-16 × the initial cost.
    above = solo.cost_history[0, : K - 1] > 1e-16 * initial
    steps = torch.cat((torch.tensor([True]), above))
    torch.testing.assert_close(
        batched.lambda_history[b, :K][steps], solo.lambda_history[0][steps], rtol=1e-12, atol=0
    )
    torch.testing.assert_close(batched.pose_tangent[b], solo.pose_tangent[0], rtol=0, atol=1e-12)
    torch.testing.assert_close(batched.points[b], solo.points[0], rtol=0, atol=1e-12)


@pytest.mark.parametrize("algorithm", ["levenberg_marquardt", "gauss_newton"])
def test_batched_solve_equals_solo_solves(algorithm):
    scene, poses, points = _mixed_difficulty_batch()
    problem = problem_from(scene, poses, points)
    config = SolverConfig(algorithm=algorithm, **DECISIVE)
    batched = torchslam.solve_tensors(problem.pose_tangent, problem.points, problem.data, config)
    assert all(batched.converged), batched.summary()
    for b in range(scene.batch_size):
        _assert_same_as_solo(batched, _solo(problem, b, config), b)


def test_batched_solve_equals_solo_solves_without_negligible_steps():
    # Each problem stops where its own model predicts a negligible step, the others going on
    # (the problems of this batch stop at different iterations).
    scene, poses, points = _mixed_difficulty_batch()
    problem = problem_from(scene, poses, points)
    config = SolverConfig(take_negligible_steps=False, **DECISIVE)
    batched = torchslam.solve_tensors(problem.pose_tangent, problem.points, problem.data, config)
    assert all(batched.converged), batched.summary()
    assert len(set(batched.iterations.tolist())) > 1
    for b in range(scene.batch_size):
        solo = _solo(problem, b, config)
        _assert_same_as_solo(batched, solo, b)
        assert int(batched.linearizations[b]) == int(solo.linearizations[0])


def test_a_converged_problem_stops_changing_while_the_others_go_on():
    scene, poses, points = _mixed_difficulty_batch()
    problem = problem_from(scene, poses, points)
    config = SolverConfig(**DECISIVE)
    seen = []
    batched = torchslam.solve_tensors(
        problem.pose_tangent, problem.points, problem.data, config, callback=seen.append
    )
    assert all(batched.converged), batched.summary()
    iterations = batched.iterations.tolist()
    early = min(range(3), key=iterations.__getitem__)
    late = max(range(3), key=iterations.__getitem__)
    k = iterations[early]
    assert k < iterations[late]
    # After it stopped: flat histories, reported inactive, never accepting a step.
    assert torch.all(batched.cost_history[early, k:] == batched.cost_history[early, k])
    assert torch.all(batched.lambda_history[early, k:] == batched.lambda_history[early, k])
    for info in seen[k:]:
        assert not bool(info.active[early])
        assert not bool(info.accepted[early])
    assert bool(seen[k - 1].active[late])
    # Its estimate is the one it had when it stopped: the same as a batched solve cut off
    # after k iterations, and as its solo solve.
    cut = torchslam.solve_tensors(
        problem.pose_tangent,
        problem.points,
        problem.data,
        SolverConfig(max_iterations=k, **DECISIVE),
    )
    assert torch.equal(cut.pose_tangent[early], batched.pose_tangent[early])
    assert torch.equal(cut.points[early], batched.points[early])
    _assert_same_as_solo(batched, _solo(problem, early, config), early)


def test_ill_posed_pose_and_single_view_point_do_not_poison_the_batch():
    scene, init = drifted(6, 40, rotation_noise_deg=5.0)
    valid = scene.valid.clone()
    pose_index, point_index = scene.pose_index[1], scene.point_index[1]
    # Problem 1: pose 4 keeps only 2 observations, point 0 only its view from frame 2.
    seen_by_4 = (valid[1] & (pose_index == 4)).nonzero().squeeze(1)
    valid[1, seen_by_4[2:]] = False
    lone = int(point_index[valid[1] & (pose_index == 2)][0])
    valid[1, (point_index == lone) & (pose_index != 2)] = False
    assert int((valid[1] & (point_index == lone)).sum()) == 1

    # The weak pose starts (and, held fixed, stays) at its true value, so that the rest of
    # problem 1 can reach the ground truth too.
    poses = init.poses.clone()
    poses[1, 4] = scene.poses_gt[1, 4]
    with pytest.warns(UserWarning, match="pose 4"):
        problem = problem_from(scene, poses, init.points, valid=valid)
    assert any("problem 1: pose 4" in line and "held fixed" in line for line in problem.diagnostics)
    assert bool(problem.data.fixed_poses[1, 4]) and not bool(problem.data.fixed_poses[0, 4])
    start = problem.pose_tangent.detach().clone()

    for algorithm in ("levenberg_marquardt", "gauss_newton"):
        result = torchslam.solve_tensors(
            problem.pose_tangent, problem.points, problem.data, SolverConfig(algorithm=algorithm)
        )
        assert all(result.converged), result.summary()
        assert torch.isfinite(result.pose_tangent).all() and torch.isfinite(result.points).all()
        # Both reach the ground truth; problem 0 is untouched by its neighbour.
        rotation, translation, point = ground_truth_errors(
            result.pose_tangent, result.points, scene
        )
        assert max(rotation, translation, point) <= 1e-8
        _assert_same_as_solo(result, _solo(problem, 0, SolverConfig(algorithm=algorithm)), 0)
        # Problem 1: the weak pose is held where it was; the lone point sits on its only view.
        assert torch.equal(result.pose_tangent[1, 4], start[1, 4])
        assert float(result.final_cost[1]) < 1e-20 * float(result.initial_cost[1])
        e = int((valid[1] & (point_index == lone)).nonzero())
        T = torchslam.se3.exp(result.pose_tangent[1, 2])
        predicted = torchslam.se3.act(T, result.points[1, lone])
        torch.testing.assert_close(predicted, scene.observations[1, e], rtol=0, atol=1e-9)


def test_under_determined_pose_is_regularized_by_lm_damping_when_not_held_fixed():
    # With validation off the problem does not hold the weak pose fixed; Levenberg-Marquardt's
    # damping keeps the system solvable, and its neighbour is unaffected.
    scene, init = drifted(6, 40, rotation_noise_deg=5.0)
    valid = scene.valid.clone()
    seen_by_4 = (valid[1] & (scene.pose_index[1] == 4)).nonzero().squeeze(1)
    valid[1, seen_by_4[2:]] = False
    with torchslam.validation(False), warnings.catch_warnings():
        warnings.simplefilter("error")
        problem = problem_from(scene, init.poses, init.points, valid=valid)
    assert not bool(problem.data.fixed_poses[1, 4])
    result = torchslam.solve(problem, SolverConfig())
    assert all(result.converged), result.summary()
    assert float(result.final_cost[1]) < 1e-12 * float(result.initial_cost[1])
    rotation, translation, point = ground_truth_errors(
        result.pose_tangent, result.points, scene, FIRST
    )
    assert max(rotation, translation, point) <= 1e-8


def test_failing_problem_does_not_stop_the_others():
    # Problem 1 has all observations of pose 3 at weight 0 (pose 3 is unconstrained, so its
    # Gauss-Newton system is exactly singular); problem 0 is healthy.
    scene, init = drifted(6, 40, noise_std=0.01, rotation_noise_deg=5.0)
    assert max_rotation_drift_deg(init.poses, scene, FIRST) > 5.0
    weights = torch.ones(scene.valid.shape, dtype=torch.float64)
    weights[1][scene.pose_index[1] == 3] = 0.0
    for solver in ("schur", "dense"):
        problem = problem_from(scene, init.poses, init.points, weights=weights)
        config = SolverConfig(algorithm="gauss_newton", linear_solver=solver)
        result = torchslam.solve_tensors(problem.pose_tangent, problem.points, problem.data, config)
        assert result.status[1] == Status.LINEAR_SOLVE_FAILED
        assert result.status[0].converged
        _assert_same_as_solo(result, _solo(problem, 0, config), 0)
        assert torch.isfinite(result.pose_tangent).all() and torch.isfinite(result.points).all()
        # Levenberg-Marquardt solves both (damping makes the system definite).
        lm = torchslam.solve(problem_from(scene, init.poses, init.points, weights=weights))
        assert all(lm.converged), lm.summary()
        assert float(lm.final_cost[1]) < 1e-2 * float(lm.initial_cost[1])


def test_non_finite_data_in_one_problem_is_reported_and_isolated():
    scene, init = drifted(6, 40, rotation_noise_deg=5.0)
    observations = scene.observations.clone()
    observations[1, 3, 0] = float("nan")
    with torchslam.validation(False):  # the constructor would reject the NaN otherwise
        problem = torchslam.PointMapProblem(
            init.poses,
            init.points,
            scene.pose_index,
            scene.point_index,
            observations,
            valid=scene.valid,
        )
    for algorithm in ("levenberg_marquardt", "gauss_newton", "gradient_descent"):
        config = SolverConfig(algorithm=algorithm)
        result = torchslam.solve_tensors(problem.pose_tangent, problem.points, problem.data, config)
        assert result.status[1] == Status.NON_FINITE
        assert "non-finite" in result.reason[1]
        assert int(result.iterations[1]) == 0
        assert torch.equal(result.pose_tangent[1], problem.pose_tangent[1].detach())
        _assert_same_as_solo(result, _solo(problem, 0, config), 0)
