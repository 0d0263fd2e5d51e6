"""examples/bundle_adjustment.py: a pinhole reprojection term that writes only a residual.

The bundle adjustment (5 cameras, 40 points, 0.5 px noise, camera 0 and point 0 held fixed)
is solved by torchslam (points eliminated by Schur) and by ``scipy.optimize.least_squares``
on the same residuals and the same parametrization (free cameras by ξ with T_i0 = Exp(ξ),
free points in R³), and both must reach the same minimum. The reprojection blocks jacrev
gives are checked against analytic ones and central differences.
"""

from __future__ import annotations

import inspect
import re
import runpy

import numpy as np
import pytest
import scipy.optimize
import torch
from torch import Tensor

from tests.helpers import load_example
from torchslam import SolverConfig, solve
from torchslam.lie import se3, so3
from torchslam.objective.data import cost as problem_cost
from torchslam.objective.terms import term_blocks, term_points, term_poses

F64 = torch.float64
FD_STEP = 1e-6
TIGHT = dict(function_tolerance=1e-15, gradient_tolerance=1e-10, parameter_tolerance=1e-15)


example = load_example("bundle_adjustment")
ReprojectionTerm = example.ReprojectionTerm


class AnalyticReprojection(ReprojectionTerm):
    """The same term with analytic blocks. X_c = R X + t; T ← T·Exp(δ) moves X_c by
    R (ω × X + v), so ∂X_c/∂δ = [−R [X]× | R] and ∂X_c/∂X = R; with
    ∂π/∂X_c = [[fx/z, 0, −fx x/z²], [0, fy/z, −fy y/z²]] and r = u − π."""

    def jacobians(self, poses, points, pixels):
        T = poses[..., 0, :, :]
        R = T[..., :3, :3]
        Xc = (R @ points[..., None])[..., 0] + T[..., :3, 3]
        x, y, z = Xc.unbind(-1)
        zero = torch.zeros_like(z)
        P = torch.stack(
            (
                torch.stack((self.fx / z, zero, -self.fx * x / z**2), -1),
                torch.stack((zero, self.fy / z, -self.fy * y / z**2), -1),
            ),
            -2,
        )
        J_xi = -P @ torch.cat((-R @ so3._hat(points), R), -1)
        return self.residual(poses, points, pixels), J_xi[..., None, :], -P @ R


def test_reprojection_term_is_only_a_residual():
    source = inspect.getsource(ReprojectionTerm)
    assert len(source.splitlines()) < 40, source
    assert "jacobians" not in ReprojectionTerm.__dict__  # jacrev gives the blocks


def test_reprojection_blocks_match_analytic_and_central_differences():
    scene = example.make_scene()
    K = scene["pixels"].shape[0]
    term = AnalyticReprojection(
        scene["pose_index"], scene["point_index"], scene["pixels"], example.INTRINSICS
    )
    poses, points = scene["initial_poses"], scene["initial_points"]
    bound = term.bind(1, poses.shape[0], points, points.shape[0])
    P, X = term_poses(bound, poses[None]), term_points(bound, points[None])
    r, J, J_X = term_blocks(bound, P, X, "analytic")
    r_ref, J_ref, J_X_ref = term_blocks(bound, P, X, "jacrev")
    assert torch.equal(r, r_ref)
    # Same products in another order: round-off of entries up to fx·|X|/z² ≈ 500.
    assert torch.allclose(J, J_ref, rtol=0, atol=1e-10)
    assert torch.allclose(J_X, J_X_ref, rtol=0, atol=1e-10)
    for k in range(0, K, 17):
        T, Xk, u = P[0, k, 0], X[0, k], bound.constants["pixels"][0, k]

        def f(x, T=T, Xk=Xk, u=u):
            return term.residual((T @ se3.exp(x[:6]))[None], (Xk + x[6:])[None], u[None])[0]

        cd = torch.stack(
            [(f(FD_STEP * e) - f(-FD_STEP * e)) / (2 * FD_STEP) for e in torch.eye(9, dtype=F64)],
            -1,
        )
        # Truncation O(h²·|∂³r|) and round-off O(ε·|r|/h) ≈ 1e-7 for pixels of O(500).
        assert torch.allclose(J[0, k, :, 0], cd[:, :6], rtol=0, atol=1e-5)
        assert torch.allclose(J_X[0, k], cd[:, 6:], rtol=0, atol=1e-5)


def _torchslam_solution(config: SolverConfig) -> tuple[Tensor, Tensor, float, object]:
    problem = example.build_problem(example.make_scene())
    result = solve(problem, config)
    assert result.converged[0], result.reason
    return result.pose_tangent[0], result.points[0], float(result.final_cost[0]), problem


def _vector_residuals(problem, x: Tensor) -> Tensor:
    """All reprojection residuals (2K,) at x = (ξ of cameras 1…, points 1…): T = Exp(ξ), the
    parametrization of both solvers (torchslam keeps ξ = Log T, updated on the manifold)."""
    m, n = problem.num_poses, problem.num_points
    xi = torch.cat((problem.pose_tangent.detach()[0, :1], x[: 6 * (m - 1)].reshape(m - 1, 6)))
    X = torch.cat((problem.points.detach()[0, :1], x[6 * (m - 1) :].reshape(n - 1, 3)))
    (term,) = problem.data.terms
    T = se3._exp(xi)[None]
    r = term.residual(term_poses(term, T), term_points(term, X[None]), term.constants["pixels"])
    return r.reshape(-1)


def _assert_same_minimum(problem, a: tuple[Tensor, float], b: tuple[Tensor, float]) -> None:
    """Two stopped solvers' (x, cost) at one minimum, to what the optimum's conditioning
    allows: near a minimum x − x* ≈ H⁻¹ g, so they differ by at most ‖H⁻¹‖ (‖g_a‖ + ‖g_b‖)
    (to second order, with a factor 4 of margin for the neglected terms); the costs differ
    at second order only, ≤ ‖H‖ bound², plus the cost's round-off."""
    J = torch.func.jacrev(lambda v: _vector_residuals(problem, v))(a[0])
    H = J.T @ J
    h_min, h_max = torch.linalg.eigvalsh(H)[[0, -1]]
    gradients = []
    for x, _ in (a, b):
        x = x.clone().requires_grad_(True)
        r = _vector_residuals(problem, x)
        (g,) = torch.autograd.grad(0.5 * (r * r).sum(), x)
        gradients.append(g.norm())
    bound = float(4 * (gradients[0] + gradients[1]) / h_min)
    # Both really converged: their distance bound is far below the noise-level uncertainty
    # of the points (0.5 px at 6 m and f = 500: σ ≈ 6 mm).
    assert bound < 1e-5, (gradients, h_min)
    assert float((a[0] - b[0]).abs().max()) <= bound + 1e-12 * float(a[0].abs().max())
    assert abs(a[1] - b[1]) <= 1e-12 * a[1] + float(h_max) * bound**2


def _flat(xi: Tensor, X: Tensor) -> Tensor:
    """x = (ξ of cameras 1…, points 1…): the free variables (camera 0, point 0 fixed)."""
    return torch.cat((xi[1:].reshape(-1), X[1:].reshape(-1)))


def test_bundle_adjustment_matches_scipy_least_squares():
    xi, X, cost, problem = _torchslam_solution(SolverConfig(linear_solver="schur", **TIGHT))
    # scipy from the same initial guess (build_problem again: solve() moved the parameters).
    start = example.build_problem(example.make_scene())
    x0 = _flat(start.pose_tangent.detach()[0], start.points.detach()[0])

    def fun(x):
        return _vector_residuals(start, torch.from_numpy(x)).numpy()

    def jac(x):
        return torch.func.jacrev(lambda v: _vector_residuals(start, v))(torch.from_numpy(x)).numpy()

    ref = scipy.optimize.least_squares(
        fun, x0.numpy(), jac=jac, method="lm", ftol=1e-15, xtol=1e-15, gtol=1e-15
    )
    assert ref.success, ref.message
    _assert_same_minimum(start, (_flat(xi, X), cost), (torch.from_numpy(ref.x), ref.cost))
    # The cost torchslam reports is the objective at its solution.
    assert abs(cost - float(problem_cost(xi[None], X[None], problem.data)[0])) <= 1e-12 * cost


def test_dense_and_schur_solves_agree():
    (xi_a, X_a, cost_a, problem), (xi_b, X_b, cost_b, _) = [
        _torchslam_solution(SolverConfig(linear_solver=solver, **TIGHT))
        for solver in ("schur", "dense")
    ]
    _assert_same_minimum(problem, (_flat(xi_a, X_a), cost_a), (_flat(xi_b, X_b), cost_b))


def test_example_runs_as_a_script(capsys):
    runpy.run_path(example.__file__, run_name="__main__")
    out = capsys.readouterr().out
    match = re.search(r"reprojection rms ([0-9.]+) px", out)
    assert match, out
    # 0.5 px noise, 400 residual entries, 141 free variables: rms ≈ 0.5·√(259/400) ≈ 0.40.
    assert 0.3 < float(match.group(1)) < 0.5, out
    assert "CONVERGED" in out, out


@pytest.mark.parametrize("fixed", ["point", "none"])
def test_scale_gauge(fixed):
    """Without the fixed point the scale is free: a direction of zero curvature."""
    scene = example.make_scene()
    problem = example.build_problem(scene)
    if fixed == "none":
        problem.data.fixed_points[0, 0] = False
    m, n = problem.num_poses, problem.num_points
    x = torch.cat(
        (
            problem.pose_tangent.detach()[0, 1:].reshape(-1),
            problem.points.detach()[0, 1:].reshape(-1),
        )
    )
    if fixed == "none":
        x = torch.cat((x, problem.points.detach()[0, 0]))

    def residuals(v):
        if fixed == "point":
            return _vector_residuals(problem, v)
        # Point 0 free too (appended last).
        X = torch.cat((v[-3:][None], v[6 * (m - 1) : -3].reshape(n - 1, 3)))
        (term,) = problem.data.terms
        xi = torch.cat((problem.pose_tangent.detach()[0, :1], v[: 6 * (m - 1)].reshape(m - 1, 6)))
        r = term.residual(
            term_poses(term, se3._exp(xi)[None]),
            term_points(term, X[None]),
            term.constants["pixels"],
        )
        return r.reshape(-1)

    J = torch.func.jacrev(residuals)(x)
    eigenvalues = torch.linalg.eigvalsh(J.T @ J)
    ratio = float(eigenvalues[0] / eigenvalues[-1])
    if fixed == "point":
        assert ratio > 1e-12
    else:
        assert ratio < 1e-6
    assert np.isfinite(ratio)
