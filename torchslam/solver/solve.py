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

import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from torchslam import _checks, losses
from torchslam.lie import se3
from torchslam.problem import PointMapData, PointMapProblem, check_data_values
from torchslam.solver import linear
from torchslam.solver.config import SolverConfig
from torchslam.solver.linearize import (
    StructuredLinearization,
    linearize,
    model_decrease,
    whitening_factors,
)
from torchslam.solver.result import SolveResult, Status

__all__ = ["IterationInfo", "check_solve_inputs", "solve", "solve_tensors"]

logger = logging.getLogger("torchslam.solver")

IterationInfo = dict
"""Per-iteration progress passed to ``callback``: iteration, cost (B,), lambda (B,),
step_norm (B,), accepted (B,), active (B,), seconds."""


def check_solve_inputs(
    fn: str,
    pose_tangent: object,
    points: object,
    data: object,
    config: object = None,
) -> SolverConfig:
    """Validate the arguments of a solve entry point; returns the config (default filled in).

    Checks (TypeError for types and dtypes, ValueError for shapes and values, each naming
    ``fn`` and the argument): ``data`` a :class:`PointMapData` (not the problem itself),
    ``pose_tangent`` (B, m, 6) and ``points`` (B, n, 3) matching it, in its dtype and device,
    ``config`` None or a :class:`SolverConfig`. When value checks are active
    (:func:`torchslam.validation`): finite starting values, and once per ``data`` its indices,
    observations and weights at the valid slots.
    """
    if isinstance(data, PointMapProblem) or isinstance(pose_tangent, PointMapProblem):
        raise TypeError(
            f"{fn}: got a PointMapProblem where tensors and its data are expected; pass "
            "(problem.pose_tangent, problem.points, problem.data), or call "
            "torchslam.solve(problem)"
        )
    if not isinstance(data, PointMapData):
        raise TypeError(
            f"{fn}: argument 'data' must be a torchslam.PointMapData (e.g. problem.data), got "
            f"{_checks.describe(data)}"
        )
    B, m, n = data.valid.shape[0], data.num_poses, data.num_points
    _checks.check_batched(
        fn, "pose_tangent", pose_tangent, ("B", "m"), (6,), (B, m), against="'data'"
    )
    _checks.check_batched(fn, "points", points, ("B", "n"), (3,), (B, n), against="'data'")
    _checks.check_same_kind(
        fn, observations=data.observations, pose_tangent=pose_tangent, points=points
    )
    if m == 0:
        raise ValueError(f"{fn}: 'data' has no poses (m = 0); there is nothing to solve")
    if config is None:
        config = SolverConfig()
    elif not isinstance(config, SolverConfig):
        raise TypeError(
            f"{fn}: argument 'config' must be a torchslam.SolverConfig or None, got "
            f"{_checks.describe(config)}; e.g. SolverConfig(algorithm='gauss_newton')"
        )
    if _checks.value_checks_active():
        _checks.check_finite(fn, "pose_tangent", pose_tangent)
        _checks.check_finite(fn, "points", points)
        check_data_values(fn, data)
        losses.check_loss_values(fn, data.loss, "data.loss")
        for k, term in enumerate(data.terms):
            losses.check_loss_values(fn, term.loss, f"data.terms[{k}].loss")
    return config


def _check_callback(fn: str, callback: object) -> None:
    if callback is not None and not callable(callback):
        raise TypeError(
            f"{fn}: argument 'callback' must be callable or None, got {_checks.describe(callback)}"
        )


def retract(pose_tangent: Tensor, points: Tensor, dp: Tensor, dl: Tensor) -> tuple[Tensor, Tensor]:
    """x ⊞ δ: ξ ← Log(Exp(ξ)·Exp(δp)) (seed eq. L1/L2), X ← X + δl.

    A pose whose step is exactly zero (a fixed pose) keeps its ξ bit for bit: the Log∘Exp
    round trip would move it by a few ulps.
    """
    moved = se3._log(se3._exp(pose_tangent) @ se3._exp(dp))
    unmoved = (dp == 0).all(dim=-1, keepdim=True)
    return torch.where(unmoved, pose_tangent, moved), points + dl


@dataclass
class _State:
    """The iterate of B problems and the solver's bookkeeping (see :mod:`.solve`)."""

    xi: Tensor
    X: Tensor
    lam: Tensor
    nu: Tensor
    status: Tensor
    iterations: Tensor
    cost: Tensor
    lin: object
    # Accepted iterations so far per problem, long (B,).
    accepted: Tensor
    # Step norm and acceptance of the last iteration, (B,) (zeros / False before the first).
    step_norm: Tensor | None = None
    last_accepted: Tensor | None = None


def _gradient_norm(lin) -> Tensor:
    # One cat, so that a problem without points (pose terms only) works too.
    g = torch.cat((lin.pose_gradient.flatten(1), lin.point_gradient.flatten(1)), dim=1)
    return g.abs().amax(-1)


def _initial_state(
    xi: Tensor, X: Tensor, data: PointMapData, factor: Tensor | None, config: SolverConfig
) -> _State:
    B = xi.shape[0]
    lam = xi.new_full((B,), config.initial_lambda)
    if config.algorithm == "gauss_newton":
        lam = torch.zeros_like(lam)
    elif config.algorithm == "gradient_descent":
        lam = torch.full_like(lam, config.step_size)
    lin = linearize(xi, X, data, factor, config.jacobian, config.linear_solver == "schur")
    cost = lin.cost
    status = torch.zeros(B, dtype=torch.long, device=xi.device)
    gradient_norm = _gradient_norm(lin).detach()
    status = torch.where(
        gradient_norm <= config.gradient_tolerance, int(Status.CONVERGED_GRADIENT), status
    )
    status = torch.where(torch.isfinite(cost.detach()), status, int(Status.NON_FINITE))
    return _State(
        xi=xi,
        X=X,
        lam=lam,
        nu=torch.full_like(lam, 2.0),
        status=status,
        iterations=torch.zeros(B, dtype=torch.long, device=xi.device),
        cost=cost,
        lin=lin,
        accepted=torch.zeros(B, dtype=torch.long, device=xi.device),
    )


def _select(mask: Tensor, new, old):
    """Per-problem choice between two linearizations (mask (B,) → new); None if forms differ.

    Recurses into nested dataclasses (the pose terms) and tuples of tensors."""
    if isinstance(new, Tensor) and isinstance(old, Tensor):
        return torch.where(mask.reshape(-1, *([1] * (new.dim() - 1))), new, old)
    if new is None or type(new) is not type(old):
        return None
    if isinstance(new, tuple):
        return tuple(_select(mask, a, b) for a, b in zip(new, old, strict=True))
    fields = {}
    for name in type(new).__dataclass_fields__:
        a, b = getattr(new, name), getattr(old, name)
        fields[name] = _select(mask, a, b)
    return type(new)(**fields)


def sparse_schur(data: PointMapData, config: SolverConfig) -> linear.SparseSchur | None:
    """The sparse reduced-system structure when ``config`` (and, for "auto", the problem's size
    and pattern) asks for the sparse factorization; None for the dense one."""
    if config.linear_solver != "schur" or config.algorithm == "gradient_descent":
        return None
    choice = linear.choose_reduced_solver(
        data, config.reduced_solver, config.dense_max_variables, config.ordering
    )
    if choice == "dense":
        return None
    return linear.SparseSchur.build(data, ordering=config.ordering)


def _iterate(
    state: _State,
    data: PointMapData,
    factor: Tensor | None,
    config: SolverConfig,
    on_step: Callable[[_State], None] | None,
) -> _State:
    """Iterations of :func:`torchslam.solve_tensors`, differentiable w.r.t. the iterate and the
    data: the same linearize → solve_step → retract → accept path, with every decision (λ, ν,
    accept, stop) taken on detached values. Stops when no problem is running (a problem
    stops by the solver's tests or at ``config.max_iterations``)."""
    algorithm = config.algorithm
    structured = config.linear_solver == "schur"
    structure = None
    sparse = sparse_schur(data, config)
    running = int(Status.RUNNING)
    xi, X, lam, nu = state.xi, state.X, state.lam, state.nu
    status, iterations, cost, lin = state.status, state.iterations, state.cost, state.lin
    accepted_total = state.accepted
    while True:
        active = (status == running) & (iterations < config.max_iterations)
        if not bool(active.any()):
            break
        iterations = iterations + active.long()
        if algorithm == "gradient_descent":
            dp = -lam[:, None, None] * lin.pose_gradient
            dl = -lam[:, None, None] * lin.point_gradient
            ok = torch.ones_like(active)
        else:
            if (
                structure is None
                and sparse is None
                and not isinstance(lin, StructuredLinearization)
            ):
                structure = linear.SchurStructure.build(data)
            dp, dl, ok = linear.solve_step(
                lin,
                data,
                structure,
                lam,
                config.damping,
                config.linear_solver,
                config.schur_chunk_size,
                sparse,
            )
        xi_new, X_new = retract(xi, X, dp, dl)
        lin_new = linearize(xi_new, X_new, data, factor, config.jacobian, structured)
        with torch.no_grad():
            # The decisions: constants of the graph.
            step_norm = torch.sqrt(dp.square().flatten(1).sum(-1) + dl.square().flatten(1).sum(-1))
            x_norm = torch.sqrt(xi.square().flatten(1).sum(-1) + X.square().flatten(1).sum(-1))
            old_cost, new_cost = cost.detach(), lin_new.cost.detach()
            finite = torch.isfinite(new_cost) & torch.isfinite(step_norm)
            if algorithm == "levenberg_marquardt":
                predicted = model_decrease(lin, data, dp, dl)
                gain = (old_cost - new_cost) / predicted
                accepted = active & ok & finite & (predicted > 0) & (gain > 0)
                factor_up = torch.clamp(1 - (2 * gain - 1) ** 3, min=1 / 3)
                lam = torch.where(accepted, (lam * factor_up).clamp_min(config.min_lambda), lam)
                rejected = active & ~accepted
                lam = torch.where(rejected, lam * nu, lam)
                nu = torch.where(accepted, 2.0, torch.where(rejected, nu * 2, nu))
            elif algorithm == "gauss_newton":
                accepted = active & ok & finite
            else:
                accepted = active & finite & (new_cost < old_cost)
                lam = torch.where(active & ~accepted, lam * 0.5, lam)
            decrease = old_cost - new_cost
            f_conv = accepted & (decrease.abs() <= config.function_tolerance * old_cost)
            if algorithm == "levenberg_marquardt":
                # As the solver: stop when even the model predicts a negligible decrease.
                f_conv = f_conv | (
                    active & ok & (predicted.abs() <= config.function_tolerance * old_cost)
                )
            p_conv = (
                active
                & ok
                & (step_norm <= config.parameter_tolerance * (x_norm + config.parameter_tolerance))
            )
        accepted_total = accepted_total + accepted.long()
        xi = torch.where(accepted[:, None, None], xi_new, xi)
        X = torch.where(accepted[:, None, None], X_new, X)
        cost = torch.where(accepted, lin_new.cost, cost)
        lin = _select(accepted, lin_new, lin)
        if lin is None:  # the two forms differ (rare): relinearize at the kept estimates
            lin = linearize(xi, X, data, factor, config.jacobian, structured)
        with torch.no_grad():
            g_conv = active & (_gradient_norm(lin) <= config.gradient_tolerance)
            status = torch.where(active & f_conv, int(Status.CONVERGED_FUNCTION), status)
            status = torch.where(
                (status == running) & g_conv, int(Status.CONVERGED_GRADIENT), status
            )
            status = torch.where(
                (status == running) & p_conv, int(Status.CONVERGED_PARAMETER), status
            )
            if algorithm == "gauss_newton":
                status = torch.where(
                    (status == running) & active & ~ok, int(Status.LINEAR_SOLVE_FAILED), status
                )
            if algorithm == "levenberg_marquardt":
                status = torch.where(
                    (status == running) & (lam > config.max_lambda),
                    int(Status.DAMPING_LIMIT),
                    status,
                )
            status = torch.where(
                (status == running) & active & ~torch.isfinite(cost.detach()),
                int(Status.NON_FINITE),
                status,
            )
        state = _State(
            xi, X, lam, nu, status, iterations, cost, lin, accepted_total, step_norm, accepted
        )
        if on_step is not None:
            on_step(state)
    return state


def _finish(state: _State, config: SolverConfig) -> _State:
    """Problems still running have used up ``max_iterations``."""
    stopped = (state.status == int(Status.RUNNING)) & (state.iterations >= config.max_iterations)
    status = torch.where(stopped, int(Status.MAX_ITERATIONS), state.status)
    return dataclasses.replace(state, status=status)


def _run(
    pose_tangent: Tensor,
    points: Tensor,
    data: PointMapData,
    config: SolverConfig,
    on_step: Callable[[_State], None] | None,
    report_initial: bool = True,
) -> tuple[_State, list[Tensor], list[Tensor]]:
    """The whole solve from the initial guess (with autograd as the caller has it).

    ``on_step`` sees the state after every iteration (and the initial one when
    ``report_initial``); returns the final state and the cost and λ histories."""
    factor = whitening_factors(data)
    state = _initial_state(pose_tangent, points, data, factor, config)
    costs, lambdas = [state.cost.detach().clone()], [state.lam.clone()]

    def record(s: _State) -> None:
        costs.append(s.cost.detach().clone())
        lambdas.append(s.lam.clone())
        if on_step is not None:
            on_step(s)

    if on_step is not None and report_initial:
        on_step(state)
    state = _iterate(state, data, factor, config, record)
    return _finish(state, config), costs, lambdas


def _result(state: _State, costs: list[Tensor], lambdas: list[Tensor], start: float) -> SolveResult:
    """The :class:`SolveResult` of a finished run (histories from :func:`_run`)."""
    return SolveResult(
        pose_tangent=state.xi,
        points=state.X,
        status=[Status(int(s)) for s in state.status.tolist()],
        iterations=state.iterations,
        initial_cost=costs[0],
        final_cost=state.cost,
        cost_history=torch.stack(costs, dim=1),
        lambda_history=torch.stack(lambdas, dim=1),
        gradient_norm=_gradient_norm(state.lin).detach(),
        time_seconds=time.perf_counter() - start,
    )


def solve_tensors(
    pose_tangent: Tensor,
    points: Tensor,
    data: PointMapData,
    config: SolverConfig | None = None,
    callback: Callable[[IterationInfo], None] | None = None,
) -> SolveResult:
    """Solve B problems given as tensors; returns new tensors (the inputs are not modified).

    Runs under ``torch.no_grad`` (:func:`torchslam.solve_differentiable` runs the same loop
    with gradients).

    Args:
        pose_tangent: initial ξ = (ω, v), (B, m, 6).
        points: initial world points, (B, n, 3).
        data: observations and structure (:class:`torchslam.problem.PointMapData`).
        config: solver options; default :class:`SolverConfig()`.
        callback: called after every iteration with an :data:`IterationInfo` dict.
    """
    config = check_solve_inputs("solve_tensors", pose_tangent, points, data, config)
    _check_callback("solve_tensors", callback)
    return _solve_tensors(pose_tangent, points, data, config, callback)


def _solve_tensors(
    pose_tangent: Tensor,
    points: Tensor,
    data: PointMapData,
    config: SolverConfig,
    callback: Callable[[IterationInfo], None] | None,
) -> SolveResult:
    """:func:`solve_tensors` after its argument checks."""
    start = time.perf_counter()
    count = [0]

    def report(state: _State) -> None:
        count[0] += 1
        if callback is None and not logger.isEnabledFor(logging.INFO):
            return
        info = {
            "iteration": count[0],
            "cost": state.cost.clone(),
            "lambda": state.lam.clone(),
            "step_norm": state.step_norm,
            "accepted": state.last_accepted,
            "active": state.status == int(Status.RUNNING),
            "seconds": time.perf_counter() - start,
        }
        if callback is not None:
            callback(info)
        logger.info(
            "iter %3d  cost %.6e  lambda %.2e  |step| %.2e  accepted %d",
            count[0],
            float(state.cost.sum()),
            float(state.lam.max()),
            float(state.step_norm.max()),
            int(state.last_accepted.sum()),
        )

    with torch.no_grad(), _checks.validation(False):
        state, costs, lambdas = _run(
            pose_tangent.detach().clone(), points.detach().clone(), data, config, report, False
        )
    return _result(state, costs, lambdas, start)


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
    fn = "solve"
    if isinstance(problem, PointMapData):
        raise TypeError(
            f"{fn}: argument 'problem' must be a torchslam.PointMapProblem, got a PointMapData; "
            "solve tensors with torchslam.solve_tensors(pose_tangent, points, data)"
        )
    if not isinstance(problem, PointMapProblem):
        raise TypeError(
            f"{fn}: argument 'problem' must be a torchslam.PointMapProblem, got "
            f"{_checks.describe(problem)}"
        )
    config = check_solve_inputs(fn, problem.pose_tangent, problem.points, problem.data, config)
    _check_callback(fn, callback)
    result = _solve_tensors(problem.pose_tangent, problem.points, problem.data, config, callback)
    with torch.no_grad():
        problem.pose_tangent.copy_(result.pose_tangent)
        problem.points.copy_(result.points)
    return result
