"""Builders shared by the solver tests: small drifted synthetic problems, single problems cut
out of a batch, ground-truth errors, and an independent scipy reference solve.

Every problem here is small (m ≤ 10 poses, n ≤ 80 points) so that the whole solver suite runs
in seconds; the benchmark sizes live in ``experiments/``.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import scipy.optimize
import torch
from torch import Tensor

import torchslam
from torchslam import jacobians
from torchslam.data.synthetic import SyntheticScene, make_scene
from torchslam.initialization import Initialization, initialize_scene
from torchslam.lie import se3
from torchslam.metrics import evaluate
from torchslam.objective.data import (
    PointMapData,
    jacobian_blocks,
    per_observation,
    raw_residuals_from_poses,
)

# Tight tolerances for the comparisons against an independent solver: both sides run to the
# round-off floor, so what is compared is the minimum, not where each stopped.
TIGHT = {
    "function_tolerance": 1e-15,
    "gradient_tolerance": 1e-13,
    "parameter_tolerance": 1e-15,
    "max_iterations": 200,
}

ALL = slice(None)

# Gradient tests: solves run to round-off (Levenberg-Marquardt then stops at ‖∇F‖ ≈ 1e-10,
# since its cost-based acceptance cannot verify smaller steps), and Gauss-Newton polishing of
# a converged solve for finite differences of the whole solve.
CONVERGED = torchslam.SolverConfig(function_tolerance=1e-14, gradient_tolerance=1e-14)
POLISH = torchslam.SolverConfig(
    algorithm="gauss_newton",
    max_iterations=12,
    function_tolerance=0.0,
    gradient_tolerance=0.0,
    parameter_tolerance=0.0,
)


def downstream_objective(pose_tangent: Tensor, points: Tensor) -> Tensor:
    """A downstream loss of a solution, per problem (B,): nonlinear in every entry."""
    coefficients = torch.linspace(-1.0, 1.0, 6, dtype=pose_tangent.dtype)
    return (
        (pose_tangent * coefficients).sum((-1, -2))
        + (points**2).sum((-1, -2))
        + (pose_tangent**2).sum((-1, -2))
    )


def drifted(
    num_poses: int = 6,
    num_points: int = 40,
    *,
    batch_size: int = 2,
    noise_std: float = 0.0,
    outlier_fraction: float = 0.0,
    rotation_noise_deg: float = 5.0,
    translation_noise: float = 0.1,
    trajectory: str = "loop",
    rotation_per_frame_deg: float = 10.0,
    visible_fraction: float = 0.6,
    seed: int = 1,
    dtype: torch.dtype = torch.float64,
) -> tuple[SyntheticScene, Initialization]:
    """A seeded scene and its drifted odometry initialization (each step off by exactly
    ``rotation_noise_deg`` and ``translation_noise``; the chained drift grows along the
    trajectory)."""
    scene = make_scene(
        num_poses,
        num_points,
        batch_size=batch_size,
        trajectory=trajectory,
        rotation_per_frame_deg=rotation_per_frame_deg,
        visible_fraction=visible_fraction,
        noise_std=noise_std,
        outlier_fraction=outlier_fraction,
        seed=seed,
        dtype=dtype,
    )
    init = initialize_scene(
        scene,
        method="odometry",
        rotation_noise_deg=rotation_noise_deg,
        translation_noise=translation_noise,
        seed=3,
    )
    return scene, init


def problem_from(
    scene: SyntheticScene,
    poses: Tensor,
    points: Tensor,
    *,
    valid: Tensor | None = None,
    weights: Tensor | None = None,
    fixed_points: Tensor | None = None,
    loss: object | None = None,
    terms: tuple = (),
) -> torchslam.PointMapProblem:
    """A :class:`PointMapProblem` on the scene's observations starting at (poses, points)."""
    return torchslam.PointMapProblem(
        poses,
        points,
        scene.pose_index,
        scene.point_index,
        scene.observations,
        valid=scene.valid if valid is None else valid,
        weights=weights,
        fixed_points=fixed_points,
        loss=loss,
        terms=terms,
    )


def max_rotation_drift_deg(poses: Tensor, scene: SyntheticScene, problems: slice = ALL) -> float:
    """Largest rotation error (degrees) of any pose of the selected problems."""
    return evaluate(poses[problems], scene.poses_gt[problems]).max_rotation_error_deg


def ground_truth_errors(
    pose_tangent: Tensor, points: Tensor, scene: SyntheticScene, problems: slice = ALL
) -> tuple[float, float, float]:
    """(max rotation error in radians, max sensor position error, max point error) over the
    selected problems."""
    errors = evaluate(
        se3.exp(pose_tangent[problems]),
        scene.poses_gt[problems],
        points[problems],
        scene.points_gt[problems],
    )
    return (
        math.radians(errors.max_rotation_error_deg),
        float(errors.translation_error.max()),
        float(errors.point_error.max()),
    )


def single(data: PointMapData, b: int) -> PointMapData:
    """Problem ``b`` of a batch as a batch of one (same padding length E)."""
    cut = {}
    for field in dataclasses.fields(data):
        value = getattr(data, field.name)
        cut[field.name] = value[b : b + 1] if isinstance(value, Tensor) else value
    return PointMapData(**cut)


def free_gradient_max(problem: torchslam.PointMapProblem) -> Tensor:
    """Max |∂F/∂x| over the free poses and points of each problem, by autograd on the
    problem's own cost (independent of the solver's normal equations), shape (B,)."""
    problem.zero_grad()
    problem.cost().sum().backward()
    g_pose = problem.pose_tangent.grad.masked_fill(problem.data.fixed_poses[..., None], 0.0)
    g_point = problem.points.grad.masked_fill(problem.data.fixed_points[..., None], 0.0)
    return torch.maximum(g_pose.abs().flatten(1).amax(-1), g_point.abs().flatten(1).amax(-1))


def scipy_least_squares(
    poses: Tensor, points: Tensor, data: PointMapData, method: str = "trf"
) -> tuple[float, Tensor, Tensor, scipy.optimize.OptimizeResult]:
    """Minimize the same cost with ``scipy.optimize.least_squares`` (one problem, B = 1).

    Parameterization, on the same manifold as torchslam: a fixed chart at the start,
    T_i = T_i,start · Exp(δ_i) (right perturbation) and X_j = X_j,start + Δ_j, with x = (δ, Δ)
    over the free poses and points only (pose 0 stays the gauge) and x₀ = 0. The chart is
    valid for every rotation reached here (|δ| ≪ π).

    Residuals are the whitened residuals Lᵀ r_e (Ω = L Lᵀ) of the valid observations, so
    scipy's cost ½‖f‖² is torchslam's ½ Σ rᵀΩr. The Jacobian is analytic and exact in the
    chart: the right-perturbation blocks of ``problem.jacobian_blocks`` at T_i, times the
    right Jacobian Jr(δ_i) (Exp(δ + d) ≈ Exp(δ) Exp(Jr(δ) d)), whitened and assembled by
    ``jacobians.dense_jacobian``. It is dense on purpose: these problems are small, and the
    exact trust-region solve (``tr_solver="exact"``) or MINPACK's ``lm`` need a dense matrix;
    scipy's sparse path (``lsmr``) solves the subproblems only approximately.

    Returns:
        (final cost, poses (1, m, 4, 4), points (1, n, 3), scipy's result).
    """
    m, n = data.num_poses, data.num_points
    free = torch.cat(
        ((~data.fixed_poses[0]).repeat_interleave(6), (~data.fixed_points[0]).repeat_interleave(3))
    )
    valid = data.valid[0]
    start_poses, start_points = poses.detach(), points.detach()

    def unpack(x: np.ndarray) -> tuple[Tensor, Tensor, Tensor]:
        z = torch.zeros(6 * m + 3 * n, dtype=torch.float64)
        z[free] = torch.from_numpy(x)
        delta = z[: 6 * m].reshape(1, m, 6)
        return delta, start_poses @ se3.exp(delta), start_points + z[6 * m :].reshape(1, n, 3)

    def fun(x: np.ndarray) -> np.ndarray:
        _, T, X = unpack(x)
        r = data.whiten(raw_residuals_from_poses(T, X, data))
        return r[0][valid].reshape(-1).numpy()

    def jac(x: np.ndarray) -> np.ndarray:
        delta, T, X = unpack(x)
        J_xi, J_point = jacobian_blocks(se3.log(T), X, data)
        J_xi = J_xi @ per_observation(se3.jr(delta), data.flat_pose_index)
        J = jacobians.dense_jacobian(
            data.whiten(J_xi), data.whiten(J_point), data.pose_index, data.point_index, m, n
        )
        J = J[0].reshape(-1, 3, 6 * m + 3 * n)[valid].reshape(-1, 6 * m + 3 * n)
        return J[:, free].numpy()

    options = {"ftol": 1e-15, "xtol": 1e-15, "gtol": 1e-15, "x_scale": 1.0}
    if method == "trf":
        options["tr_solver"] = "exact"
    x0 = np.zeros(int(free.sum()))
    result = scipy.optimize.least_squares(fun, x0, jac=jac, method=method, **options)
    _, T, X = unpack(result.x)
    return float(result.cost), T, X, result


def solution_distance_bound(problem: torchslam.PointMapProblem, b: int) -> float:
    """How far problem ``b``'s current estimate may lie from the exact minimizer, in the
    right-perturbation chart (2-norm over the free poses' δ and the free points' ΔX).

    A least-squares problem that is not exactly at its minimum x* is off by about one Newton
    step, ‖x − x*‖ ≈ ‖H⁻¹ g(x)‖ (H = JᵀJ, g = Jᵀr; the second-order remainder is ≪ this near
    x*). The gradient itself cannot be evaluated below the round-off of its sum, about
    ε·‖|J|ᵀ|r|‖ (each product and partial sum rounds at relative ε, whatever the order or the
    CPU's kernels), so the minimizer is only defined to ε·‖|J|ᵀ|r|‖ / σ_min(H). The bound is
    the sum of the two, times 4 for the remainder terms neglected; it depends on the
    problem's conditioning, not on the machine. For the small, point-observation-only
    problems of these tests (the dense Jacobian is formed).
    """
    data = problem.data
    free = torch.cat(
        ((~data.fixed_poses[b]).repeat_interleave(6), (~data.fixed_points[b]).repeat_interleave(3))
    )
    with torch.no_grad():
        J = problem.dense_jacobian()[b][:, free]
        r = problem.residuals()[b].reshape(-1)
    H = J.T @ J
    g = J.T @ r
    newton = torch.linalg.solve(H, g).norm()
    sigma_min = torch.linalg.eigvalsh(H)[0]
    eps = torch.finfo(H.dtype).eps
    floor = eps * (J.abs().T @ r.abs()).norm() / sigma_min
    return float(4 * (newton + floor))


def solution_distance(a: torchslam.PointMapProblem, c: torchslam.PointMapProblem, b: int) -> float:
    """Distance of problem ``b``'s estimates in ``a`` and ``c``, in the chart of
    :func:`solution_distance_bound`: δ_i = Log(T_i,a⁻¹ T_i,c) for the poses, X_c − X_a for
    the points (2-norm over all)."""
    with torch.no_grad():
        delta = se3.log(se3.inverse(a.poses[b]) @ c.poses[b])
        dX = c.points[b] - a.points[b]
    return float(torch.cat((delta.reshape(-1), dX.reshape(-1))).norm())


def factorize(
    lin,
    data,
    lam: torch.Tensor,
    damping: str = "marquardt",
    linear_solver: str = "schur",
    reduced_solver: str = "dense",
    chunk_size: int = 1 << 20,
):
    """The solver's plan for ``data`` with these options, factorizing ``lin`` at λ = ``lam``."""
    from torchslam.solver.plan import LinearPlan

    config = torchslam.SolverConfig(
        damping=damping,
        linear_solver=linear_solver,
        reduced_solver=reduced_solver,
        schur_chunk_size=chunk_size,
    )
    return LinearPlan.build(data, config).factorize(lin, lam)


def solve_step(lin, data, lam: torch.Tensor, damping: str = "marquardt", *args, **kwargs):
    """(δp, δl, ok): the damped step of ``lin`` by :func:`factorize` (same options)."""
    f = factorize(lin, data, lam, damping, *args, **kwargs)
    dp, dl = f.solve(lin.pose_gradient, lin.point_gradient)
    return dp, dl, f.ok
