"""The one damped Gauss-Newton / Levenberg-Marquardt / gradient-descent loop, batched.

One straight path per iteration: linearize (:mod:`.linearize`) → factorize the damped system
with the solve's plan (:class:`.plan.LinearPlan`, built once) and solve for the step → retract
(:func:`retract`: T ← T·Exp(δ) for the poses, X ← X + δX for the points) → accept or reject →
stopping rules (:func:`update_status`). The loop iterates on the pose matrices T = Exp(ξ) and
takes ξ = Log(T) once, when it is read (:attr:`State.xi`): the same twists, bit for bit, as
Log(Exp(ξ)·Exp(δ)) after every step (:meth:`torchslam.manifold.SE3Tangent.retract`), without a
Log per iteration. Each of the B problems has its own
damping λ, its own accept/reject decisions and its own convergence; a problem that stopped
keeps its values while the others go on. Every decision is taken on detached values, so the
same loop runs under ``torch.no_grad`` (:func:`torchslam.solve_tensors`) or with autograd
(the unrolled and truncated backward of :mod:`.differentiable`).

Levenberg-Marquardt uses the gain ratio ϱ = (F(x) − F(x ⊞ δ)) / (L(0) − L(δ)), with the
model decrease L(0) − L(δ) = −(r̃ᵀJ̃δ + ½‖J̃δ‖²) evaluated exactly from the blocks, and
Nielsen's update: accepted (ϱ > 0): λ ← λ·max(⅓, 1 − (2ϱ − 1)³), ν ← 2; rejected: λ ← λ·ν,
ν ← 2ν. Gauss-Newton is the undamped step, always taken. Gradient descent is the seed's
δ = −α Jᵀr with α halved after a step that does not decrease the cost.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from torchslam._batched import matmul
from torchslam._threads import threads_for
from torchslam.lie import _series, se3
from torchslam.objective.data import PointMapData
from torchslam.solver.config import SolverConfig
from torchslam.solver.linearize import linearize, model_decrease, whitening_factors
from torchslam.solver.plan import LinearPlan
from torchslam.solver.result import IterationInfo, SolveResult, Status

__all__ = ["State", "retract", "run", "update_status"]


def retract(
    poses: Tensor, points: Tensor, dp: Tensor, dl: Tensor, parameters: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """x ⊞ δ on the iterate, each variable type by its own retraction
    (:mod:`torchslam.objective.parameters`): T ← T·Exp(δp) (seed eq. L1, right perturbation;
    poses (B, m, 4, 4), dp (B, m [+ S], 6)), X ← X + δl (points (B, n, 3)), and for the
    parameter blocks' slots (B, S, 6) x ← x + δ (the last S rows of dp). Returns
    (T, X, moves, parameters), ``moves`` (B, m) the poses whose step is not zero.

    A pose whose step is exactly zero (a fixed pose) keeps T bit for bit; its twist is then
    the one the solve started from (:attr:`State.xi`). The θ-power form of Exp
    (``se3.exp(..., form="fast")``, the same bits for |δω| ≤ 2²⁰).
    """
    if parameters is not None:
        m = poses.shape[1]
        parameters = parameters + dp[:, m:]
        dp = dp[:, :m]
    moves = (dp != 0).any(dim=-1)
    moved = torch.where(moves[..., None, None], matmul(poses, se3._exp(dp)), poses)
    return moved, points + dl, moves, parameters


def _norm_bound(
    start_square: Tensor, poses: Tensor, moved: Tensor, X: Tensor, P: Tensor | None = None
) -> Tensor:
    """An upper bound of ‖(ξ, X)‖ per problem (B,) without the Log: a pose that moved has
    ‖ξ‖² = θ² + ‖J_l(ω)⁻¹ t‖² ≤ π² + (π/2)²‖t‖² (θ ≤ π, and ‖J_l⁻¹‖ = (θ/2)/sin(θ/2) ≤ π/2),
    bounded here by 10 + 2.5‖t‖² (a margin over round-off); one that did not keeps its ‖ξ₀‖²
    (``start_square`` (B, m)). The total is raised by 10⁻⁵ relative: summed in another order
    than the exact norm, it could otherwise fall an ulp below it. Parameter blocks' slots
    ``P`` (B, S, 6) add their squares."""
    t_square = poses[..., :3, 3].square().sum(-1)
    per_pose = torch.where(moved, 10.0 + 2.5 * t_square, start_square)
    total = per_pose.sum(-1) + X.square().flatten(1).sum(-1)
    if P is not None:
        total = total + P.detach().square().flatten(1).sum(-1)
    return torch.sqrt(total) * (1.0 + 1e-5)


@dataclass
class State:
    """The iterate of B problems and the loop's bookkeeping.

    The poses are held as matrices T (``poses``, (B, m, 4, 4)); :attr:`xi` is their twist
    ξ = Log(T), computed when read, except on the poses no step ever moved (``moved`` False),
    which keep the twist the loop started from (``start``) bit for bit."""

    start: Tensor
    poses: Tensor
    moved: Tensor
    X: Tensor
    lam: Tensor
    nu: Tensor
    status: Tensor
    iterations: Tensor
    cost: Tensor
    lin: object
    # Accepted iterations so far per problem, long (B,).
    accepted: Tensor
    # Step norm and acceptance of the last iteration, (B,) (None before the first).
    step_norm: Tensor | None = None
    last_accepted: Tensor | None = None
    # Wall-clock seconds spent in linearize and in the linear solves so far.
    linearize_seconds: float = 0.0
    linear_solve_seconds: float = 0.0
    # The parameter blocks' slot values (B, S, 6), or None for a problem without them.
    parameters: Tensor | None = None
    # Linearizations (Jacobian evaluations) so far per problem, long (B,): the start and
    # every evaluated candidate.
    evaluations: Tensor | None = None

    @functools.cached_property
    def xi(self) -> Tensor:
        """The twists ξ (B, m, 6) of the iterate."""
        return _twists(self.start, self.poses, self.moved)


def _twists(start: Tensor, poses: Tensor, moved: Tensor) -> Tensor:
    """ξ = Log(T) of the poses (B, m, 4, 4) that moved (``moved`` (B, m)), ``start`` (B, m, 6)
    bit for bit on the others."""
    if not bool(moved.any()):
        return start
    return torch.where(moved[..., None], se3._log(poses), start)


def _finite(x: Tensor) -> Tensor:
    """``torch.isfinite(x)`` of a float tensor in two operations (isfinite takes seven)."""
    return x.abs() < math.inf


def gradient_norm(lin) -> Tensor:
    """max |g| over poses, parameter blocks and points, (B,)."""
    # One cat, so that a problem without points (pose terms only) works too.
    g = torch.cat((lin.pose_gradient.flatten(1), lin.point_gradient.flatten(1)), dim=1)
    return g.abs().amax(-1)


def initial_state(
    xi: Tensor,
    X: Tensor,
    data: PointMapData,
    factor: Tensor | None,
    config: SolverConfig,
    parameters: Tensor | None = None,
) -> State:
    """The state before the first iteration: λ₀ (0 for Gauss-Newton, α for descent), the
    linearization at (ξ, X, parameter slots), and the status of problems that start
    converged or non-finite."""
    B = xi.shape[0]
    lam = xi.new_full((B,), config.initial_lambda)
    if config.algorithm == "gauss_newton":
        lam = torch.zeros_like(lam)
    elif config.algorithm == "gradient_descent":
        lam = torch.full_like(lam, config.step_size)
    tick = time.perf_counter()
    lin = linearize(
        xi, X, data, factor, config.jacobian, config.linear_solver == "schur", None, parameters
    )
    seconds = time.perf_counter() - tick
    status = torch.zeros(B, dtype=torch.long, device=xi.device)
    status = torch.where(
        gradient_norm(lin).detach() <= config.gradient_tolerance,
        int(Status.CONVERGED_GRADIENT),
        status,
    )
    status = torch.where(_finite(lin.cost.detach()), status, int(Status.NON_FINITE))
    return State(
        start=xi,
        poses=lin.poses,
        moved=torch.zeros(xi.shape[:2], dtype=torch.bool, device=xi.device),
        X=X,
        lam=lam,
        nu=torch.full_like(lam, 2.0),
        status=status,
        iterations=torch.zeros(B, dtype=torch.long, device=xi.device),
        cost=lin.cost,
        lin=lin,
        accepted=torch.zeros(B, dtype=torch.long, device=xi.device),
        linearize_seconds=seconds,
        parameters=parameters,
        evaluations=torch.ones(B, dtype=torch.long, device=xi.device),
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
        fields[name] = _select(mask, getattr(new, name), getattr(old, name))
    return type(new)(**fields)


def update_status(
    status: Tensor,
    config: SolverConfig,
    *,
    active: Tensor,
    accepted: Tensor,
    ok: Tensor,
    old_cost: Tensor,
    new_cost: Tensor,
    predicted: Tensor | None,
    step_norm: Tensor,
    x_norm: Tensor,
    gradient: Tensor,
    lam: Tensor,
) -> Tensor:
    """The stopping rules, applied after an iteration to the problems still running, (B,).

    In this order (the first that holds names the status):

    1. ``CONVERGED_FUNCTION``: an accepted step decreased the cost by at most
       ``function_tolerance``·F, or (Levenberg-Marquardt) the model predicts a decrease in
       [0, ``function_tolerance``·F]: nothing is left to gain.
    2. ``CONVERGED_GRADIENT``: max |g| ≤ ``gradient_tolerance`` at the kept estimate.
    3. ``CONVERGED_PARAMETER``: ‖δ‖ ≤ ``parameter_tolerance``·(‖x‖ + ``parameter_tolerance``),
       ‖x‖ the norm of (ξ, X) of the problem.
    4. ``LINEAR_SOLVE_FAILED`` (Gauss-Newton only): the normal equations were not positive
       definite, and there is no damping to fall back on.
    5. ``DAMPING_LIMIT`` (Levenberg-Marquardt only): λ > ``max_lambda``.

    The rules apply to the active problems (running, below ``max_iterations``); the others keep
    their status. ``MAX_ITERATIONS`` is set by :func:`run` when the loop ends; ``NON_FINITE``
    by :func:`initial_state` for a problem whose starting cost is not finite (the loop keeps
    only finite costs: a step to a non-finite one is rejected).
    """
    limit = config.function_tolerance * old_cost
    f_conv = accepted & ((old_cost - new_cost).abs() <= limit)
    if predicted is not None:
        # A negative prediction is an indefinite model (round-off in a damped factor whose
        # sign check was skipped), never "nothing left to gain".
        f_conv = f_conv | (ok & (predicted >= 0) & (predicted <= limit))
    # One stacked (R, B) tensor and the first rule that holds per problem (a few whole-tensor
    # operations, however many rules).
    rules = [
        f_conv,
        gradient <= config.gradient_tolerance,
        ok & (step_norm <= config.parameter_tolerance * (x_norm + config.parameter_tolerance)),
    ]
    outcomes = [Status.CONVERGED_FUNCTION, Status.CONVERGED_GRADIENT, Status.CONVERGED_PARAMETER]
    if config.algorithm == "gauss_newton":
        rules.append(~ok)
        outcomes.append(Status.LINEAR_SOLVE_FAILED)
    if config.algorithm == "levenberg_marquardt":
        rules.append(lam > config.max_lambda)
        outcomes.append(Status.DAMPING_LIMIT)
    holds = torch.stack(rules) & active
    codes = _series.constant(
        ("status codes", *outcomes), [int(o) for o in outcomes], torch.long, status.device
    )
    first = codes.index_select(0, holds.to(torch.uint8).argmax(0))  # the first that holds
    return torch.where(holds.any(0), first, status)


def iterate(
    state: State,
    data: PointMapData,
    factor: Tensor | None,
    config: SolverConfig,
    on_step: Callable[[State], None] | None,
    plan: LinearPlan | None = None,
) -> State:
    """Iterations from ``state`` until no problem is running (a problem stops by the rules of
    :func:`update_status` or at ``config.max_iterations``); differentiable w.r.t. the iterate
    and the data when autograd is on. ``plan`` defaults to :meth:`LinearPlan.build`."""
    algorithm = config.algorithm
    structured = config.linear_solver == "schur"
    if plan is None and algorithm != "gradient_descent":
        plan = LinearPlan.build(data, config)
    running = int(Status.RUNNING)
    s = state
    T, moved, X, lam, nu, status, lin = s.poses, s.moved, s.X, s.lam, s.nu, s.status, s.lin
    P = s.parameters
    iterations, cost, accepted_total = s.iterations, s.cost, s.accepted
    evaluations = s.evaluations if s.evaluations is not None else torch.ones_like(iterations)
    # ‖ξ₀‖² per pose, for the poses that have not moved (:func:`_norm_bound`).
    start_square = s.start.detach().square().sum(-1)
    linearize_seconds, solve_seconds = s.linearize_seconds, s.linear_solve_seconds
    while True:
        active = (status == running) & (iterations < config.max_iterations)
        if not bool(active.any()):
            break
        iterations = iterations + active  # long + bool: long
        tick = time.perf_counter()
        if algorithm == "gradient_descent":
            dp = -lam[:, None, None] * lin.pose_gradient
            dl = -lam[:, None, None] * lin.point_gradient
            ok = torch.ones_like(active)
        else:
            factorization = plan.factorize(lin, lam)
            dp, dl = factorization.solve(lin.pose_gradient, lin.point_gradient)
            ok = factorization.ok
        tock = time.perf_counter()
        solve_seconds += tock - tick
        predicted = None
        done = torch.zeros_like(active)
        if algorithm == "levenberg_marquardt":
            with torch.no_grad():
                predicted = model_decrease(lin, data, dp, dl)
                if not config.take_negligible_steps:
                    # The model promises at most function_tolerance·F: the step is neither
                    # evaluated nor taken (SolverConfig.take_negligible_steps).
                    done = active & ok & (predicted >= 0)
                    done = done & (predicted <= config.function_tolerance * cost.detach())
            if not config.take_negligible_steps and bool(done[active].all()):
                status = torch.where(done, int(Status.CONVERGED_FUNCTION), status)
                zero = torch.zeros_like(active)
                step_norm = torch.sqrt(
                    dp.square().flatten(1).sum(-1) + dl.square().flatten(1).sum(-1)
                ).detach()
                s = dataclasses.replace(
                    s,
                    status=status,
                    iterations=iterations,
                    step_norm=step_norm,
                    last_accepted=zero,
                    linear_solve_seconds=solve_seconds,
                )
                if on_step is not None:
                    on_step(s)
                continue
        evaluations = evaluations + (active & ~done)
        T_new, X_new, moves, P_new = retract(T, X, dp, dl, P)
        lin_new = linearize(None, X_new, data, factor, config.jacobian, structured, T_new, P_new)
        linearize_seconds += time.perf_counter() - tock
        with torch.no_grad():
            # The decisions: constants of the graph.
            step_norm = torch.sqrt(dp.square().flatten(1).sum(-1) + dl.square().flatten(1).sum(-1))
            # ‖x‖ of the parameter rule needs ξ = Log(T) only where a step is small enough for
            # the rule to hold with the upper bound of ‖x‖ (in a solve's last iterations if
            # ever): elsewhere the bound decides the same.
            x_norm = _norm_bound(start_square, T.detach(), moved, X.detach(), P)
            tolerance = config.parameter_tolerance
            if bool((step_norm <= tolerance * (x_norm + tolerance)).any()):
                xi = _twists(s.start.detach(), T.detach(), moved)
                x_square = xi.square().flatten(1).sum(-1) + X.square().flatten(1).sum(-1)
                if P is not None:
                    x_square = x_square + P.detach().square().flatten(1).sum(-1)
                x_norm = torch.sqrt(x_square)
            old_cost, new_cost = cost.detach(), lin_new.cost.detach()
            finite = _finite(new_cost) & _finite(step_norm)
            if algorithm == "levenberg_marquardt":
                gain = (old_cost - new_cost) / predicted
                accepted = active & ~done & ok & finite & (predicted > 0) & (gain > 0)
                factor_up = torch.clamp(1 - (2 * gain - 1) ** 3, min=1 / 3)
                lam = torch.where(accepted, (lam * factor_up).clamp_min(config.min_lambda), lam)
                rejected = active & ~done & ~accepted
                lam = torch.where(rejected, lam * nu, lam)
                nu = torch.where(accepted, 2.0, torch.where(rejected, nu * 2, nu))
            elif algorithm == "gauss_newton":
                accepted = active & ok & finite
            else:
                accepted = active & finite & (new_cost < old_cost)
                lam = torch.where(active & ~accepted, lam * 0.5, lam)
        accepted_total = accepted_total + accepted
        # Whole-batch outcomes (every solve of one problem) keep one of the two as it is.
        taken = int(accepted.sum())
        if taken == accepted.numel():
            T, X, P, cost, lin = T_new, X_new, P_new, lin_new.cost, lin_new
            moved = moved | moves
        elif taken > 0:
            take = accepted[:, None, None]
            T = torch.where(take[..., None], T_new, T)
            X = torch.where(take, X_new, X)
            if P is not None:
                P = torch.where(take, P_new, P)
            cost = torch.where(accepted, lin_new.cost, cost)
            moved = moved | (accepted[:, None] & moves)
            lin = _select(accepted, lin_new, lin)
        if lin is None:  # the two forms differ (rare): relinearize at the kept estimates
            lin = linearize(None, X, data, factor, config.jacobian, structured, T, P)
        with torch.no_grad():
            status = update_status(
                status,
                config,
                active=active,
                accepted=accepted,
                ok=ok,
                old_cost=old_cost,
                new_cost=new_cost,
                predicted=predicted,
                step_norm=step_norm,
                x_norm=x_norm,
                gradient=gradient_norm(lin),
                lam=lam,
            )
        s = State(
            s.start,
            T,
            moved,
            X,
            lam,
            nu,
            status,
            iterations,
            cost,
            lin,
            accepted_total,
            step_norm,
            accepted,
            linearize_seconds,
            solve_seconds,
            P,
            evaluations,
        )
        if on_step is not None:
            on_step(s)
    return s


def iteration_info(state: State, iteration: int, start: float) -> IterationInfo:
    """The :class:`IterationInfo` a callback receives after iteration ``iteration`` of a solve
    that started at ``time.perf_counter()`` = ``start``."""
    return IterationInfo(
        iteration=iteration,
        cost=state.cost.detach().clone(),
        damping=state.lam.clone(),
        step_norm=state.step_norm,
        accepted=state.last_accepted,
        active=state.status == int(Status.RUNNING),
        gradient_norm=gradient_norm(state.lin).detach(),
        seconds=time.perf_counter() - start,
    )


def finish(state: State, config: SolverConfig) -> State:
    """Problems still running have used up ``max_iterations``."""
    stopped = (state.status == int(Status.RUNNING)) & (state.iterations >= config.max_iterations)
    status = torch.where(stopped, int(Status.MAX_ITERATIONS), state.status)
    return dataclasses.replace(state, status=status)


@dataclass
class Histories:
    """Per-iteration records of a run: cost, λ and step norm, each a list of (B,) tensors."""

    costs: list[Tensor]
    lambdas: list[Tensor]
    steps: list[Tensor]


def run(
    pose_tangent: Tensor,
    points: Tensor,
    data: PointMapData,
    config: SolverConfig,
    on_step: Callable[[State], None] | None,
    report_initial: bool = True,
    plan: LinearPlan | None = None,
    parameters: Tensor | None = None,
) -> tuple[State, Histories]:
    """The whole solve from the initial guess (with autograd as the caller has it).

    ``on_step`` sees the state after every iteration (and the initial one when
    ``report_initial``); ``plan`` defaults to :meth:`LinearPlan.build`. Returns the final
    state and the histories. ``parameters``: the parameter blocks' starting slot values
    (B, S, 6) (:mod:`torchslam.objective.parameters`), for a problem that has them. Small
    problems run on one intra-op thread (:mod:`torchslam._threads`)."""
    with threads_for(data):
        return _run(pose_tangent, points, data, config, on_step, report_initial, plan, parameters)


def _run(pose_tangent, points, data, config, on_step, report_initial, plan, parameters=None):
    factor = whitening_factors(data)
    state = initial_state(pose_tangent, points, data, factor, config, parameters)
    history = Histories([state.cost.detach().clone()], [state.lam.clone()], [])

    def record(s: State) -> None:
        # No copies: the loop makes new tensors every iteration and never writes to them,
        # and :func:`result` stacks the histories.
        history.costs.append(s.cost.detach())
        history.lambdas.append(s.lam)
        history.steps.append(s.step_norm)
        if on_step is not None:
            on_step(s)

    if on_step is not None and report_initial:
        on_step(state)
    state = iterate(state, data, factor, config, record, plan)
    return finish(state, config), history


def _parameter_values(state: State, layout) -> dict[str, Tensor]:
    """The parameter blocks of the iterate by group, {name: (B, q, d)} (empty without)."""
    if state.parameters is None or layout is None:
        return {}
    return layout.unpack(state.parameters)


def result(state: State, history: Histories, start: float, layout=None) -> SolveResult:
    """The :class:`SolveResult` of a finished run (``layout``: the problem's
    :class:`~torchslam.objective.parameters.ParameterLayout`, for its parameter blocks)."""
    steps = (
        torch.stack(history.steps, dim=1)
        if history.steps
        else state.cost.detach().new_zeros(state.cost.shape[0], 0)
    )
    return SolveResult(
        pose_tangent=state.xi,
        points=state.X,
        parameters=_parameter_values(state, layout),
        status=[Status(int(s)) for s in state.status.tolist()],
        iterations=state.iterations,
        initial_cost=history.costs[0],
        final_cost=state.cost,
        cost_history=torch.stack(history.costs, dim=1),
        lambda_history=torch.stack(history.lambdas, dim=1),
        gradient_norm=gradient_norm(state.lin).detach(),
        time_seconds=time.perf_counter() - start,
        step_norm_history=steps,
        linearize_seconds=state.linearize_seconds,
        linear_solve_seconds=state.linear_solve_seconds,
        linearizations=state.evaluations,
    )
