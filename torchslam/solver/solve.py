"""The hand-written damped Gauss-Newton / Levenberg-Marquardt loop, batched over problems.

One straight path per iteration: linearize (:mod:`.linearize`) → linear solve (:mod:`.linear`)
→ retract (poses T ← T·Exp(δ) through the SE3Tangent plus, points X ← X + δX) → accept or
reject. Each of the B problems has its own damping λ, its own accept/reject decisions and its
own convergence; a problem that stopped keeps its values while the others go on.

Levenberg-Marquardt uses the gain ratio ϱ = (F(x) − F(x ⊞ δ)) / (L(0) − L(δ)), with the
model decrease L(0) − L(δ) = −(r̃ᵀJ̃δ + ½‖J̃δ‖²) evaluated exactly from the blocks, and
Nielsen's update: accepted (ϱ > 0): λ ← λ·max(⅓, 1 − (2ϱ − 1)³), ν ← 2; rejected: λ ← λ·ν,
ν ← 2ν. Gauss-Newton is the undamped step, always taken. Gradient descent is the seed's
δ = −α Jᵀr with α halved after a step that does not decrease the cost.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import torch
from torch import Tensor

from torchslam import _checks
from torchslam.lie import se3
from torchslam.problem import PointMapData, PointMapProblem
from torchslam.solver import linear
from torchslam.solver.config import SolverConfig
from torchslam.solver.linearize import (
    StructuredLinearization,
    linearize,
    model_decrease,
    whitening_factors,
)
from torchslam.solver.result import SolveResult, Status

__all__ = ["IterationInfo", "solve", "solve_tensors"]

logger = logging.getLogger("torchslam.solver")

IterationInfo = dict
"""Per-iteration progress passed to ``callback``: iteration, cost (B,), lambda (B,),
step_norm (B,), accepted (B,), active (B,), seconds."""


def retract(pose_tangent: Tensor, points: Tensor, dp: Tensor, dl: Tensor) -> tuple[Tensor, Tensor]:
    """x ⊞ δ: ξ ← Log(Exp(ξ)·Exp(δp)) (seed eq. L1/L2), X ← X + δl.

    A pose whose step is exactly zero (a fixed pose) keeps its ξ bit for bit: the Log∘Exp
    round trip would move it by a few ulps.
    """
    moved = se3._log(se3._exp(pose_tangent) @ se3._exp(dp))
    unmoved = (dp == 0).all(dim=-1, keepdim=True)
    return torch.where(unmoved, pose_tangent, moved), points + dl


def _gradient_norm(lin) -> Tensor:
    return torch.maximum(
        lin.pose_gradient.abs().flatten(1).amax(-1), lin.point_gradient.abs().flatten(1).amax(-1)
    )


def solve_tensors(
    pose_tangent: Tensor,
    points: Tensor,
    data: PointMapData,
    config: SolverConfig | None = None,
    callback: Callable[[IterationInfo], None] | None = None,
) -> SolveResult:
    """Solve B problems given as tensors; returns new tensors (the inputs are not modified).

    Runs under ``torch.no_grad`` (see the gradients documentation for differentiable solves).

    Args:
        pose_tangent: initial ξ = (ω, v), (B, m, 6).
        points: initial world points, (B, n, 3).
        data: observations and structure (:class:`torchslam.problem.PointMapData`).
        config: solver options; default :class:`SolverConfig()`.
        callback: called after every iteration with an :data:`IterationInfo` dict.
    """
    config = config or SolverConfig()
    start = time.perf_counter()
    with torch.no_grad(), _checks.validation(False):
        xi, X = pose_tangent.detach().clone(), points.detach().clone()
        B = xi.shape[0]
        device, dtype = xi.device, xi.dtype
        factor = whitening_factors(data)
        structure = None  # observation pairs, built on first use by the block Schur path
        algorithm = config.algorithm
        lam = torch.full((B,), config.initial_lambda, dtype=dtype, device=device)
        if algorithm == "gauss_newton":
            lam.zero_()
        elif algorithm == "gradient_descent":
            lam.fill_(config.step_size)
        nu = torch.full((B,), 2.0, dtype=dtype, device=device)
        status = torch.zeros(B, dtype=torch.long, device=device)  # Status.RUNNING
        iterations = torch.zeros(B, dtype=torch.long, device=device)

        structured = config.linear_solver == "schur"
        lin = linearize(xi, X, data, factor, config.jacobian, structured)
        initial_cost = lin.cost.clone()
        cost = lin.cost.clone()
        costs, lambdas = [cost.clone()], [lam.clone()]
        gradient_norm = _gradient_norm(lin)
        status = torch.where(
            gradient_norm <= config.gradient_tolerance, int(Status.CONVERGED_GRADIENT), status
        )
        status = torch.where(torch.isfinite(cost), status, int(Status.NON_FINITE))

        for it in range(config.max_iterations):
            active = status == int(Status.RUNNING)
            if not bool(active.any()):
                break
            iterations += active.long()
            if algorithm == "gradient_descent":
                dp, dl = (
                    -lam[:, None, None] * lin.pose_gradient,
                    -lam[:, None, None] * (lin.point_gradient),
                )
                ok = torch.ones(B, dtype=torch.bool, device=device)
            else:
                if structure is None and not isinstance(lin, StructuredLinearization):
                    structure = linear.SchurStructure.build(data)
                dp, dl, ok = linear.solve_step(
                    lin,
                    data,
                    structure,
                    lam,
                    config.damping,
                    config.linear_solver,
                    config.schur_chunk_size,
                )
            step_norm = torch.sqrt(dp.square().flatten(1).sum(-1) + dl.square().flatten(1).sum(-1))
            x_norm = torch.sqrt(xi.square().flatten(1).sum(-1) + X.square().flatten(1).sum(-1))
            xi_new, X_new = retract(xi, X, dp, dl)
            # Linearize at the candidate right away: its cost decides acceptance, and an
            # accepted step then needs no second pass over the observations.
            lin_new = linearize(xi_new, X_new, data, factor, config.jacobian, structured)
            new_cost = lin_new.cost
            finite = torch.isfinite(new_cost) & torch.isfinite(step_norm)

            if algorithm == "levenberg_marquardt":
                predicted = model_decrease(lin, data, dp, dl)
                gain = (cost - new_cost) / predicted
                accepted = active & ok & finite & (predicted > 0) & (gain > 0)
                factor_up = torch.clamp(1 - (2 * gain - 1) ** 3, min=1 / 3)
                lam = torch.where(accepted, (lam * factor_up).clamp_min(config.min_lambda), lam)
                rejected = active & ~accepted
                lam = torch.where(rejected, lam * nu, lam)
                nu = torch.where(accepted, 2.0, torch.where(rejected, nu * 2, nu))
            elif algorithm == "gauss_newton":
                accepted = active & ok & finite
            else:
                accepted = active & finite & (new_cost < cost)
                lam = torch.where(active & ~accepted, lam * 0.5, lam)

            # Convergence tests (Ceres-like), on accepted steps.
            decrease = cost - new_cost
            f_conv = accepted & (decrease.abs() <= config.function_tolerance * cost)
            if algorithm == "levenberg_marquardt":
                # Nothing left to gain: even the model predicts a negligible decrease (the
                # step is then typically rejected at round-off level, and λ would only grow).
                f_conv = f_conv | (
                    active & ok & (predicted.abs() <= config.function_tolerance * cost)
                )
            p_conv = (
                active
                & ok
                & (step_norm <= config.parameter_tolerance * (x_norm + config.parameter_tolerance))
            )
            xi = torch.where(accepted[:, None, None], xi_new, xi)
            X = torch.where(accepted[:, None, None], X_new, X)
            cost = torch.where(accepted, new_cost, cost)

            lin = _select(accepted, lin_new, lin)
            if lin is None:  # the two forms differ (rare): relinearize at the kept estimates
                lin = linearize(xi, X, data, factor, config.jacobian, structured)
            gradient_norm = _gradient_norm(lin)
            g_conv = active & (gradient_norm <= config.gradient_tolerance)

            status = torch.where(active & f_conv, int(Status.CONVERGED_FUNCTION), status)
            status = torch.where(
                (status == int(Status.RUNNING)) & g_conv, int(Status.CONVERGED_GRADIENT), status
            )
            status = torch.where(
                (status == int(Status.RUNNING)) & p_conv, int(Status.CONVERGED_PARAMETER), status
            )
            if algorithm == "gauss_newton":
                status = torch.where(
                    (status == int(Status.RUNNING)) & active & ~ok,
                    int(Status.LINEAR_SOLVE_FAILED),
                    status,
                )
            if algorithm == "levenberg_marquardt":
                status = torch.where(
                    (status == int(Status.RUNNING)) & (lam > config.max_lambda),
                    int(Status.DAMPING_LIMIT),
                    status,
                )
            status = torch.where(
                (status == int(Status.RUNNING)) & active & ~torch.isfinite(cost),
                int(Status.NON_FINITE),
                status,
            )
            costs.append(cost.clone())
            lambdas.append(lam.clone())
            if callback is not None or logger.isEnabledFor(logging.INFO):
                info = {
                    "iteration": it + 1,
                    "cost": cost.clone(),
                    "lambda": lam.clone(),
                    "step_norm": step_norm,
                    "accepted": accepted,
                    "active": status == int(Status.RUNNING),
                    "seconds": time.perf_counter() - start,
                }
                if callback is not None:
                    callback(info)
                logger.info(
                    "iter %3d  cost %.6e  lambda %.2e  |step| %.2e  accepted %d/%d",
                    it + 1,
                    float(cost.sum()),
                    float(lam.max()),
                    float(step_norm.max()),
                    int(accepted.sum()),
                    int(active.sum()),
                )
        status = torch.where(status == int(Status.RUNNING), int(Status.MAX_ITERATIONS), status)

    return SolveResult(
        pose_tangent=xi,
        points=X,
        status=[Status(int(s)) for s in status.tolist()],
        iterations=iterations,
        initial_cost=initial_cost,
        final_cost=cost,
        cost_history=torch.stack(costs, dim=1),
        lambda_history=torch.stack(lambdas, dim=1),
        gradient_norm=gradient_norm,
        time_seconds=time.perf_counter() - start,
    )


def _select(mask: Tensor, new, old):
    """Per-problem choice between two linearizations of the same form (mask (B,) → new);
    None when their forms differ."""
    if type(new) is not type(old):
        return None
    fields = {}
    for name in type(new).__dataclass_fields__:
        a, b = getattr(new, name), getattr(old, name)
        fields[name] = torch.where(mask.reshape(-1, *([1] * (a.dim() - 1))), a, b)
    return type(new)(**fields)


def solve(
    problem: PointMapProblem,
    config: SolverConfig | None = None,
    callback: Callable[[IterationInfo], None] | None = None,
) -> SolveResult:
    """Solve a :class:`PointMapProblem` in place: its parameters are set to the solution.

    Args:
        problem: the batched problem; its current parameters are the initial guess.
        config: solver options (algorithm, damping, tolerances, Jacobian mode, linear solver).
        callback: called after each iteration with progress (see :data:`IterationInfo`).

    Returns:
        A :class:`SolveResult` with per-problem status, reason, iterations, costs and history.
    """
    result = solve_tensors(problem.pose_tangent, problem.points, problem.data, config, callback)
    with torch.no_grad():
        problem.pose_tangent.copy_(result.pose_tangent)
        problem.points.copy_(result.points)
    return result
