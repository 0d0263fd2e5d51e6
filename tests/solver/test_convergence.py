"""The solver reaches the right minimum: ground truth without noise, scipy's minimum with
noise, the same answer from every algorithm, and a monotone cost where the method promises it."""

from __future__ import annotations

import math

import pytest
import torch

import torchslam
from torchslam import SolverConfig, Status
from torchslam.data.synthetic import benchmark_case
from torchslam.initialization import initialize_scene
from torchslam.lie import se3
from torchslam.metrics import evaluate

from . import (
    TIGHT,
    drifted,
    free_gradient_max,
    ground_truth_errors,
    max_rotation_drift_deg,
    problem_from,
    scipy_least_squares,
    single,
)

ALGORITHMS = [
    pytest.param({"algorithm": "levenberg_marquardt", "damping": "marquardt"}, id="lm-marquardt"),
    pytest.param({"algorithm": "levenberg_marquardt", "damping": "levenberg"}, id="lm-levenberg"),
    pytest.param({"algorithm": "gauss_newton"}, id="gauss-newton"),
]

# float32 solves: ε = 1.2e-7 times coordinates of a few metres times the conditioning of the
# reduced pose system (~10–100 here) gives errors of 1e-6 to 1e-5; 1e-4 leaves a margin.
FLOAT32_SOLVE_TOL = 1e-4


@pytest.mark.parametrize("options", ALGORITHMS)
@pytest.mark.parametrize(
    ("trajectory", "rotation_per_frame_deg"), [("loop", 10.0), ("random_walk", 20.0)]
)
def test_noise_free_converges_to_ground_truth_from_drifted_odometry(
    options, trajectory, rotation_per_frame_deg
):
    scene, init = drifted(
        8,
        60,
        trajectory=trajectory,
        rotation_per_frame_deg=rotation_per_frame_deg,
        rotation_noise_deg=8.0,
    )
    assert max_rotation_drift_deg(init.poses, scene) >= 20.0
    problem = problem_from(scene, init.poses, init.points)
    result = torchslam.solve(problem, SolverConfig(**options))
    assert all(result.converged), result.summary()
    rotation, translation, point = ground_truth_errors(result.pose_tangent, result.points, scene)
    assert rotation <= 1e-8
    assert translation <= 1e-8
    assert point <= 1e-8
    assert torch.all(result.final_cost <= 1e-12 * result.initial_cost)


@pytest.mark.parametrize("method", ["trf", "lm"])
@pytest.mark.parametrize("weighting", ["unit", "information"])
def test_noisy_problem_reaches_scipy_least_squares_minimum(method, weighting):
    scene, init = drifted(8, 60, noise_std=0.02, rotation_noise_deg=8.0, seed=2)
    assert max_rotation_drift_deg(init.poses, scene) >= 20.0
    weights = None
    if weighting == "information":
        # Anisotropic SPD information Ω = A Aᵀ + ½ I per observation (the block path).
        gen = torch.Generator().manual_seed(5)
        A = torch.randn(*scene.valid.shape, 3, 3, generator=gen, dtype=torch.float64)
        weights = A @ A.transpose(-1, -2) + 0.5 * torch.eye(3, dtype=torch.float64)
    problem = problem_from(scene, init.poses, init.points, weights=weights)
    result = torchslam.solve(problem, SolverConfig(**TIGHT))
    assert all(result.converged), result.summary()
    for b in range(scene.batch_size):
        cost, poses, points, reference = scipy_least_squares(
            init.poses[b : b + 1], init.points[b : b + 1], single(problem.data, b), method
        )
        assert reference.status > 0, reference.message
        assert cost > 1e-3  # a noisy minimum, not a zero-residual one
        assert abs(float(result.final_cost[b]) - cost) <= 1e-8 * cost
        torch.testing.assert_close(result.poses[b], poses[0], rtol=0, atol=1e-8)
        torch.testing.assert_close(result.points[b], points[0], rtol=0, atol=1e-8)


def test_lm_accepted_cost_never_increases_per_problem():
    # Three problems with large drift (≥ 20°), each with its own λ: the cost history of every
    # problem is non-increasing whatever steps its LM takes or rejects on this machine.
    scene, init = drifted(8, 60, batch_size=3, noise_std=0.01, rotation_noise_deg=8.0)
    assert max_rotation_drift_deg(init.poses, scene) >= 20.0
    for damping in ("marquardt", "levenberg"):
        problem = problem_from(scene, init.poses, init.points)
        seen = []
        config = SolverConfig(damping=damping, initial_lambda=1e-12)
        result = torchslam.solve(problem, config, callback=seen.append)
        history = result.cost_history
        assert torch.all(history[:, 1:] <= history[:, :-1])
        assert torch.all(result.final_cost < 0.5 * result.initial_cost)
        # The callback saw the same costs; a step a running problem rejected left its cost
        # exactly unchanged.
        costs = torch.stack([info.cost for info in seen], dim=1)
        torch.testing.assert_close(costs, history[:, 1:], rtol=0, atol=0)
        for k, info in enumerate(seen):
            rejected = info.active & ~info.accepted  # still running, step not taken
            assert torch.all(history[rejected, k + 1] == history[rejected, k])


class _Cubic(torchslam.Term):
    """r = (u³ − 1, ω) with u = t + u₀ (per axis): translation t and rotation vector ω of
    one pose. From u₀ = 0.1 the Gauss-Newton step is δu = (1 − u₀³)/(3u₀²) = 33.3, and
    ½|r|² at u = 33.4 is ~10¹³ times the start's; from u₀ = 0.5, δu = 7/6 and the cost
    still rises 17-fold; from u₀ = 0.9 the step lands at u = 0.9905 and the cost falls
    ~60-fold. These margins are orders of magnitude beyond any rounding, so every machine
    must reject the first two steps and accept the third."""

    def __init__(self, u0: torch.Tensor):
        B = u0.shape[0]
        pose_index = torch.ones(B, 1, 1, dtype=torch.int64)
        super().__init__(pose_index, {"u0": u0[:, None, None].expand(B, 1, 3).clone()})

    def residual(self, poses, u0):
        T = poses[..., 0, :, :]
        u = T[..., :3, 3] + u0
        omega = se3.log(T)[..., :3]
        return torch.cat((u**3 - 1, omega), -1)


@pytest.mark.parametrize("damping", ["marquardt", "levenberg"])
def test_lm_rejects_an_overshooting_step_and_raises_lambda_per_problem(damping):
    u0 = torch.tensor([0.1, 0.5, 0.9], dtype=torch.float64)
    B = u0.shape[0]
    poses = torch.eye(4, dtype=torch.float64).expand(B, 2, 4, 4).clone()
    none = torch.zeros(B, 0, dtype=torch.int64)
    empty = poses.new_zeros(B, 0, 3)
    problem = torchslam.PointMapProblem(poses, empty, none, none, empty, terms=[_Cubic(u0)])
    seen = []
    config = SolverConfig(damping=damping, initial_lambda=1e-12)
    result = torchslam.solve(problem, config, callback=seen.append)
    first = seen[0]
    assert first.accepted.tolist() == [False, False, True]
    lam, history = result.lambda_history, result.cost_history
    # Rejected: cost kept exactly, λ raised; accepted: cost lowered, λ lowered.
    assert history[0, 1] == history[0, 0] and history[1, 1] == history[1, 0]
    assert lam[0, 1] > lam[0, 0] and lam[1, 1] > lam[1, 0]
    assert history[2, 1] < history[2, 0] / 10 and lam[2, 1] < lam[2, 0]
    # Each problem still reaches u = 1, ω = 0 (cost ≈ 0) with its own damping.
    assert all(result.converged), result.summary()
    assert torch.all(history[:, 1:] <= history[:, :-1])
    assert torch.all(result.final_cost < 1e-20)


def test_gauss_newton_and_levenberg_marquardt_agree_on_a_well_conditioned_problem():
    scene, init = drifted(8, 60, noise_std=0.01, rotation_noise_deg=2.0)
    results = {}
    for algorithm in ("gauss_newton", "levenberg_marquardt"):
        problem = problem_from(scene, init.poses, init.points)
        results[algorithm] = torchslam.solve(problem, SolverConfig(algorithm=algorithm, **TIGHT))
        assert all(results[algorithm].converged), results[algorithm].summary()
    gn, lm = results["gauss_newton"], results["levenberg_marquardt"]
    torch.testing.assert_close(gn.final_cost, lm.final_cost, rtol=1e-8, atol=0)
    torch.testing.assert_close(gn.poses, lm.poses, rtol=0, atol=1e-8)
    torch.testing.assert_close(gn.points, lm.points, rtol=0, atol=1e-8)
    assert torch.all(gn.lambda_history == 0)


@pytest.mark.parametrize("step_size", [1e-3, 1e-1])
def test_gradient_descent_decreases_the_cost_monotonically(step_size):
    scene, init = drifted(6, 40, noise_std=0.01)
    problem = problem_from(scene, init.poses, init.points)
    config = SolverConfig(algorithm="gradient_descent", step_size=step_size, max_iterations=40)
    result = torchslam.solve(problem, config)
    history = result.cost_history
    assert history.shape == (scene.batch_size, 41)
    assert torch.all(history[:, 1:] <= history[:, :-1])
    assert torch.all(result.final_cost < 0.9 * result.initial_cost)
    assert result.status == [Status.MAX_ITERATIONS] * scene.batch_size
    alpha = result.lambda_history
    assert torch.all(alpha[:, 0] == step_size)
    if step_size == 1e-3:
        # Small enough that every step of the seed's δ = −α Jᵀr decreases the cost.
        assert torch.all(history[:, 1:] < history[:, :-1])
        assert torch.all(alpha == step_size)
    else:
        # Too long at first: rejected steps halve α and keep the cost.
        assert torch.all(alpha[:, -1] < step_size)
        assert torch.all(alpha[:, 1:] <= alpha[:, :-1])


@pytest.mark.parametrize(
    "loss",
    [torchslam.HuberLoss(0.03), torchslam.CauchyLoss(0.03), torchslam.TukeyLoss(0.1)],
    ids=["huber", "cauchy", "tukey"],
)
def test_robust_losses_converge_to_a_stationary_point_and_reject_outliers(loss):
    # Noise σ = 0.01 m per axis, 10% outliers; scales of 3σ (Huber, Cauchy) and 10σ (Tukey,
    # whose influence vanishes beyond the scale, so it needs a start inside it).
    scene, init = drifted(
        8, 60, noise_std=0.01, outlier_fraction=0.1, rotation_noise_deg=2.0, seed=4
    )
    robust = problem_from(scene, init.poses, init.points, loss=loss)
    initial_gradient = free_gradient_max(robust)
    result = torchslam.solve(robust, SolverConfig(**TIGHT))
    assert all(result.converged), result.summary()
    history = result.cost_history
    assert torch.all(history[:, 1:] <= history[:, :-1])
    # Stationary for the robust cost ½ Σ ρ(s), by autograd on the problem's own cost: the
    # IRLS normal equations have the right gradient.
    assert torch.all(free_gradient_max(robust) <= 1e-6 * initial_gradient)

    plain = problem_from(scene, init.poses, init.points)
    torchslam.solve(plain, SolverConfig())
    robust_error = evaluate(robust.poses.detach(), scene.poses_gt).mean_rotation_error_deg
    plain_error = evaluate(plain.poses.detach(), scene.poses_gt).mean_rotation_error_deg
    assert plain_error > 1.0  # least squares is ruined by the outliers
    assert robust_error < 0.3


def test_case_o_huber_lm_from_drifted_start_reaches_0_02_degrees():
    # Issue 4's case O: m = 50, n = 1,000, 30% visibility, 10% outliers, σ = 0.01 m.
    # Huber scale a = 3σ = 0.03 m (the 3-D inlier residual norm has RMS σ√3 ≈ 0.017 m, so
    # inliers stay quadratic and outliers get linear influence). Drifted start: odometry off
    # by 5° and 5 cm per step (≈ 30° mean, ≈ 48° max accumulated rotation error).
    scene = benchmark_case("O")
    init = initialize_scene(
        scene, method="odometry", rotation_noise_deg=5.0, translation_noise=0.05, seed=0
    )
    assert max_rotation_drift_deg(init.poses, scene) >= 20.0
    problem = torchslam.PointMapProblem.from_scene(
        scene, init.poses, init.points, loss=torchslam.HuberLoss(3 * scene.noise_std)
    )
    result = torchslam.solve(problem, SolverConfig(max_iterations=200))
    assert all(result.converged), result.summary()
    errors = evaluate(result.poses, scene.poses_gt)
    assert errors.mean_rotation_error_deg <= 0.02


def test_float32_noise_free_problem_converges_to_1e_4():
    scene, init = drifted(6, 40, rotation_noise_deg=5.0, dtype=torch.float32)
    assert max_rotation_drift_deg(init.poses, scene) >= 10.0
    problem = problem_from(scene, init.poses, init.points)
    result = torchslam.solve(problem, SolverConfig())
    assert all(result.converged), result.summary()
    assert result.pose_tangent.dtype == torch.float32
    assert result.cost_history.dtype == torch.float32
    rotation, translation, point = ground_truth_errors(result.pose_tangent, result.points, scene)
    assert rotation <= FLOAT32_SOLVE_TOL
    assert translation <= FLOAT32_SOLVE_TOL
    assert point <= FLOAT32_SOLVE_TOL
    assert math.isfinite(float(result.final_cost.sum()))
