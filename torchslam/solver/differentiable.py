"""Gradients through the solver: unrolled, truncated and implicit backward modes (issue 5).

:func:`solve_differentiable` solves the same problem as :func:`torchslam.solve_tensors` and
returns a :class:`SolveResult` whose ``pose_tangent``, ``points`` (and ``final_cost``) carry
an autograd graph back to everything the solution depends on: the observations, the scalar
weights or information matrices (and whatever produced them), tensor parameters of the robust
loss (e.g. ``HuberLoss(scale)`` with a tensor scale), and the initial guess. Four modes:

- ``"unrolled"``: the Levenberg-Marquardt (or Gauss-Newton, gradient-descent) iterations run
  with autograd on: linearize → Schur solve (:mod:`.plan`) → retract, every iteration
  recorded. The damping λ, ν and the accept/reject and stopping decisions are taken on
  detached values, so they are constants of the graph. Memory grows with the iterations.
- ``"truncated"``: the same, but the graph covers only the last k = ``truncate_steps``
  accepted iterations of each problem: the solve first runs under ``torch.no_grad`` (keeping a
  snapshot of the iterate after each iteration), then each problem is re-run with autograd on
  from the snapshot before its last k accepted steps (rejected steps, which leave the iterate
  unchanged, are re-run too but do not count). The iterate at the start of that window is a
  constant, so the initial guess receives a gradient only where k covers every accepted step
  (then the result equals ``"unrolled"``). k = 1 differentiates one damped Gauss-Newton step
  near the solution, roughly the ``hessian="gauss_newton"`` implicit gradient; the gradient
  approaches the implicit one as k grows.
- ``"implicit"``: the solve runs under ``torch.no_grad`` (:func:`torchslam.solve_tensors`);
  the solution x* = (ξ*, X*) then enters a ``torch.autograd.Function`` whose backward applies
  the implicit function theorem to the optimality condition

      g(δ; θ) = ∇_δ F(x* ⊞ δ; θ) = 0   at δ = 0,

  with x ⊞ δ = (Log(Exp(ξ)·Exp(δ_p)), X + δ_l) (right perturbation, seed eq. L1) and θ the
  data. Then dδ*/dθ = −H⁻¹ ∂g/∂θ with H = ∂g/∂δ (the Hessian of F in the chart) and
  dξ*/dδ = jr_inv(ξ*), so for an incoming gradient (ḡ_ξ, ḡ_X) the backward solves

      H w = (jr_inv(ξ*)ᵀ ḡ_ξ, ḡ_X)      and returns      θ̄ = −(∂g/∂θ)ᵀ w,

  one linear solve per backward, whatever the number of iterations (memory O(E + m² + n)).
  ``H`` is solved with the forward pass's Schur machinery, factored once (λ = 0; dense
  Cholesky or the sparse factorization, as the forward solve, by the forward's
  :class:`torchslam.solver.plan.LinearPlan`). With ``ImplicitConfig(hessian="exact")``
  (default) H is the exact Hessian, which the unrolled gradient converges to, assembled
  in the forward's block structure by :func:`torchslam.solver.hessian.exact_hessian`: the
  robust-corrected Gauss-Newton part Jᵀ(ρ'Ω + 2ρ''(Ωr)(Ωr)ᵀ)J plus the second-order part
  Σ ρ'(Ωr)ₖ∇²rₖ (analytic for the point observations, ``torch.func`` for the terms). Where
  it does not factor (not positive definite: a singular or indefinite problem), that problem
  falls back to conjugate gradients on the exact Hessian (Hessian-vector products by double
  backward) preconditioned by the Gauss-Newton solve. ``hessian="gauss_newton"`` solves with
  JᵀJ alone: cheaper, but it drops the Σ r∇²r and ρ'' terms, an O(residual) error.
  Parameter blocks (:mod:`torchslam.objective.parameters`) join the chart as the forward's
  reduced system has them (δ_p over the m poses and then the S slots, x ← x + δ, a slot's
  entries past its block's size inert); their exact Hessian is not assembled in blocks, so
  such problems always take the conjugate gradients (exact Hessian-vector products).
  Fixed variables keep their given values: the initial guess
  receives the identity there, plus the effect of moving a fixed variable (e.g. the gauge
  pose) on the free solution; elsewhere the solution does not depend on the initial guess.
  The theorem needs a converged, non-degenerate minimum: see *Unconverged problems* below.
  First derivatives only: a backward with ``create_graph=True`` (``torch.autograd.grad(...,
  create_graph=True)``, ``.backward(create_graph=True)``, Hessian-vector products) raises a
  ``RuntimeError``; use ``"unrolled"`` for second derivatives.
- ``"none"``: :func:`torchslam.solve_tensors` (``torch.no_grad``), detached results.

Unconverged problems (``on_unconverged``, implicit mode). A problem whose status is not
converged (:attr:`SolveResult.converged`: stopped at ``max_iterations``, at the damping limit,
by a failed linear solve or a non-finite cost) did not reach a minimum, so the implicit
gradient is not the derivative of what was computed (1% off after a few iterations short of
convergence, wrong by any factor after one). The policy decides, per problem:

- ``"warn"`` (default): the unconverged problems are re-run from the initial guess with
  autograd on (as ``"unrolled"``, the same iterations: ``max_iterations`` capped at the most
  any unconverged problem used, ``reduced_solver="dense"``), and their ``pose_tangent``,
  ``points`` and ``final_cost`` are those of the re-run, whose gradient is the exact
  derivative of the iterations actually run; converged problems keep the implicit gradient. A
  ``UserWarning`` names the unconverged problems and their status.
- ``"unroll"``: the same, without the warning (e.g. a deliberately short forward solve).
- ``"raise"``: a ``RuntimeError`` naming the unconverged problems.
- ``"implicit"``: the implicit gradient for every problem anyway (the opt-out: approximate
  where a problem stopped short of its minimum, NaN where its iterate is not finite).

The policy applies only when a gradient is attached (grad mode on and something requires
grad). ``"unrolled"`` already differentiates what was computed; ``"truncated"`` is an
approximation chosen explicitly.

Reusing data across training steps. The observations, weights etc. of ``data`` are the graph's
inputs: a tensor built once (``weights=torch.sigmoid(logits)`` in a problem built before the
training loop) has its graph freed by the first ``backward()``, and a second solve on it could
not reach ``logits`` again. :func:`solve_differentiable` detects such a tensor (when
validation is on) and raises a ``ValueError``; build the tensor inside the loop instead, e.g.
``dataclasses.replace(problem.data, weights=torch.sigmoid(logits))`` (cheap: no copies, no
checks) or a new :class:`torchslam.PointMapProblem`.

With a :class:`torchslam.PointMapProblem` (weights produced by a model ``net``)::

    problem = PointMapProblem(poses0, points0, pose_index, point_index, observations,
                              weights=net(features), loss=HuberLoss(scale))
    result = solve_differentiable(problem.pose_tangent, problem.points, problem.data)
    pose_loss(result.poses, poses_gt).backward()   # reaches net's parameters (and scale)
"""

from __future__ import annotations

import collections
import dataclasses
import time
import warnings
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from torchslam import _checks, _inference, losses
from torchslam._threads import threads_for
from torchslam.lie import se3
from torchslam.manifold import SE3Matrix
from torchslam.objective.data import PointMapData, cost, cost_from_poses
from torchslam.objective.parameters import pack_values
from torchslam.solver import loop
from torchslam.solver.config import SolverConfig, check_implicit_config
from torchslam.solver.hessian import exact_hessian
from torchslam.solver.linearize import linearize, whitening_factors
from torchslam.solver.plan import LinearPlan
from torchslam.solver.result import SolveResult
from torchslam.solver.solve import check_solve_inputs, solve_tensors

__all__ = ["Backward", "ImplicitConfig", "OnUnconverged", "solve_differentiable"]

Backward = Literal["implicit", "unrolled", "truncated", "none"]
_BACKWARDS = ("implicit", "unrolled", "truncated", "none")
OnUnconverged = Literal["warn", "unroll", "raise", "implicit"]
_ON_UNCONVERGED = ("warn", "unroll", "raise", "implicit")
_HESSIANS = ("exact", "gauss_newton")
# The chart x* ⊞ δ of the implicit backward on the pose matrices: T·Exp(δ).
_MATRIX = SE3Matrix()


@dataclass(frozen=True)
class ImplicitConfig:
    """Options of the implicit backward of :func:`solve_differentiable`."""

    # H in H w = v: "exact" (the exact Hessian assembled in the forward's block structure and
    # factored once by its Schur solve; conjugate gradients with Hessian-vector products by
    # double backward, preconditioned by the Gauss-Newton solve, for a problem whose exact
    # Hessian is not positive definite) or "gauss_newton" (the Schur solve with JᵀJ alone:
    # cheaper, exact only for zero-residual problems).
    hessian: Literal["exact", "gauss_newton"] = "exact"
    # The conjugate-gradient fallback stops in a problem when ‖H w − v‖ ≤ tolerance · ‖v‖.
    tolerance: float = 1e-10
    # At most this many fallback iterations (each one Hessian-vector product).
    max_iterations: int = 100

    def __post_init__(self) -> None:
        check_implicit_config(self)
        if self.hessian not in _HESSIANS:
            raise ValueError(
                f"ImplicitConfig: 'hessian' must be one of {_HESSIANS}, got {self.hessian!r}"
            )
        if not isinstance(self.tolerance, (int, float)) or not self.tolerance >= 0:
            raise ValueError(
                f"ImplicitConfig: 'tolerance' must be a number ≥ 0, got {self.tolerance!r}"
            )
        if not isinstance(self.max_iterations, int) or self.max_iterations < 1:
            raise ValueError(
                f"ImplicitConfig: 'max_iterations' must be an int ≥ 1, got {self.max_iterations!r}"
            )


def solve_differentiable(
    pose_tangent: Tensor,
    points: Tensor,
    data: PointMapData,
    config: SolverConfig | None = None,
    *,
    backward: Backward = "implicit",
    truncate_steps: int = 1,
    implicit: ImplicitConfig | None = None,
    on_unconverged: OnUnconverged = "warn",
    parameters: dict[str, Tensor] | None = None,
) -> SolveResult:
    """Solve B problems like :func:`torchslam.solve_tensors`, differentiably (module doc).

    Args:
        pose_tangent: initial ξ = (ω, v), rotation first, (B, m, 6); may require grad.
        points: initial world points, (B, n, 3); may require grad.
        data: observations and structure; ``observations`` (B, E, 3), ``weights`` (B, E) or
            ``information`` (B, E, 3, 3) and floating-point tensor attributes of ``loss``
            (e.g. a ``HuberLoss`` tensor scale) may require grad.
        config: solver options; default :class:`SolverConfig()`.
        backward: "implicit" (default), "unrolled", "truncated" or "none".
        truncate_steps: k ≥ 1, accepted iterations of each problem that "truncated"
            differentiates.
        implicit: options of the "implicit" backward; default :class:`ImplicitConfig()`.
        on_unconverged: what the "implicit" backward does for problems that did not converge
            (module doc): "warn" (default: unrolled gradient of the iterations actually run
            for those problems, with a ``UserWarning``), "unroll" (the same, silently),
            "raise" (``RuntimeError``) or "implicit" (the implicit gradient anyway).
        parameters: initial parameter blocks {group: (B, q, d)} of data that has them
            (:mod:`torchslam.objective.parameters`); may require grad. Backward "unrolled",
            any backward (the implicit one solves with conjugate gradients on the exact
            Hessian, module doc); the result's ``parameters`` are differentiable like its
            poses.

    Returns:
        A :class:`SolveResult`; ``pose_tangent`` (B, m, 6), ``points`` (B, n, 3) and
        ``final_cost`` (B,) are differentiable (detached for "none"), the histories are not.

    Raises:
        ValueError: a tensor of ``data`` (or the initial guess) whose autograd graph was
            already freed by a backward (module doc, *Reusing data across training steps*).
        RuntimeError: ``on_unconverged="raise"`` and a problem did not converge; a second
            derivative (``create_graph=True``) through the "implicit" backward.
    """
    fn = "solve_differentiable"
    config = check_solve_inputs(fn, pose_tangent, points, data, config)
    slots = pack_values(fn, data.parameters, parameters, pose_tangent, detach=False)
    _checks.check_tensor(fn, "pose_tangent", pose_tangent, (6,), min_batch_dims=2, dims="Bm")
    _checks.check_tensor(fn, "points", points, (3,), min_batch_dims=2, dims="Bn")
    _checks.check_same_kind(
        fn, pose_tangent=pose_tangent, points=points, observations=data.observations
    )
    B = data.pose_index.shape[0]
    if tuple(pose_tangent.shape) != (B, data.num_poses, 6) or tuple(points.shape) != (
        B,
        data.num_points,
        3,
    ):
        raise ValueError(
            f"{fn}: expected pose_tangent {(B, data.num_poses, 6)} and points "
            f"{(B, data.num_points, 3)} to match 'data', got {tuple(pose_tangent.shape)} and "
            f"{tuple(points.shape)}"
        )
    if backward not in _BACKWARDS:
        raise ValueError(f"{fn}: 'backward' must be one of {_BACKWARDS}, got {backward!r}")
    if isinstance(truncate_steps, bool) or not isinstance(truncate_steps, int):
        raise TypeError(f"{fn}: 'truncate_steps' must be an int, got {truncate_steps!r}")
    if truncate_steps < 1:
        raise ValueError(f"{fn}: 'truncate_steps' must be ≥ 1, got {truncate_steps}")
    if on_unconverged not in _ON_UNCONVERGED:
        raise ValueError(
            f"{fn}: 'on_unconverged' must be one of {_ON_UNCONVERGED}, got {on_unconverged!r}"
        )
    config = config or SolverConfig()
    if backward in ("unrolled", "truncated"):
        if config.reduced_solver == "sparse":
            # SciPy's factorization is outside autograd; the batched Cholesky is not.
            raise ValueError(
                f"{fn}: backward={backward!r} needs reduced_solver='dense' or 'auto', got "
                "'sparse' (the sparse factorization is not differentiable; use "
                "backward='implicit', which works with it)"
            )
        config = dataclasses.replace(config, reduced_solver="dense")
        _check_zero_weights_unrolled(fn, data, config, backward)
    if implicit is not None and not isinstance(implicit, ImplicitConfig):
        raise TypeError(
            f"{fn}: argument 'implicit' must be an ImplicitConfig or None, got "
            f"{type(implicit).__name__}"
        )
    implicit = implicit or ImplicitConfig()

    if backward == "none":
        return solve_tensors(pose_tangent, points, data, config, parameters=parameters)
    if _checks.value_checks_active():
        _check_graphs_alive(fn, pose_tangent, points, data)
    if backward == "implicit":
        return _solve_implicit(pose_tangent, points, data, config, implicit, on_unconverged, slots)
    start = time.perf_counter()
    with _checks.validation(False):
        if backward == "unrolled":
            state, history = loop.run(pose_tangent, points, data, config, None, parameters=slots)
        else:
            state, history = _run_truncated(
                pose_tangent, points, data, config, truncate_steps, slots
            )
    result = loop.result(state, history, start, data.parameters)
    return _connected(result, pose_tangent, points, data)


def _connected(result: SolveResult, *inputs: object) -> SolveResult:
    """Outputs that did not move (no iteration ran, every variable fixed) are constants of
    the inputs, whose gradient is zero: attach them to the graph with an exact zero (the sum
    of an empty slice of each input that requires grad), so that ``backward()`` gives zeros
    as the implicit mode does, not torch's "does not require grad" error. Empty slices never
    read a value: NaN padding stays inert."""
    if not torch.is_grad_enabled():
        return result
    leaves = [t for t in _grad_inputs(*inputs) if t.requires_grad]
    if not leaves:
        return result
    changes = {}
    for name in ("pose_tangent", "points", "final_cost"):
        value = getattr(result, name)
        if not value.requires_grad:
            zero = sum(t.reshape(-1)[:0].sum() for t in leaves)
            changes[name] = value + zero.to(value.dtype)
    return dataclasses.replace(result, **changes) if changes else result


def _grad_inputs(pose_tangent: Tensor, points: Tensor, data: PointMapData) -> list[Tensor]:
    """The floating tensors a differentiable solve carries gradients to."""
    tensors = [pose_tangent, points]
    for field in dataclasses.fields(data):
        value = getattr(data, field.name)
        if isinstance(value, Tensor) and value.is_floating_point():
            tensors.append(value)
    tensors.extend(losses.tensor_attributes(data.loss).values())
    for term in data.terms:
        tensors.extend(v for v in term.constants.values() if v.is_floating_point())
        for value in (term.weight, term.information):
            if isinstance(value, Tensor):
                tensors.append(value)
        tensors.extend(losses.tensor_attributes(term.loss).values())
    return tensors


# ------------------------------------------------------------------------------------------
# Unrolled and truncated: the solver loop with autograd on


def _check_zero_weights_unrolled(
    fn: str, data: PointMapData, config: SolverConfig, backward: str
) -> None:
    """Refuse what would give a NaN gradient instead of returning it.

    The general block linearization (``jacobian="jacrev"`` or ``linear_solver="dense"``)
    whitens scalar weights by √w, whose derivative is infinite at w = 0: unrolling through it
    gives NaN for the gradient of a valid observation's weight of exactly 0 (its true value
    is finite). The structured path and the implicit backward use w itself and are exact.
    """
    weights = data.weights
    if weights is None or not weights.requires_grad or not _checks.value_checks_active():
        return
    if config.jacobian == "analytic" and config.linear_solver == "schur":
        return
    zero = data.valid & (weights.detach() == 0)
    if bool(zero.any()):
        b, e = (int(i) for i in zero.nonzero()[0])
        raise ValueError(
            f"{fn}: backward={backward!r} with jacobian={config.jacobian!r} and "
            f"linear_solver={config.linear_solver!r} cannot differentiate a weight of exactly 0 "
            f"on a valid observation (problem {b}, observation {e}): the block path whitens by "
            "√w. Use backward='implicit', or jacobian='analytic' with linear_solver='schur', "
            "or mark the observation valid=False"
        )


def _run_truncated(
    pose_tangent: Tensor,
    points: Tensor,
    data: PointMapData,
    config: SolverConfig,
    k: int,
    slots: Tensor | None = None,
) -> tuple[loop.State, loop.Histories]:
    """Solve under no_grad keeping a snapshot per iteration, then re-run each problem with
    autograd on from the snapshot before its last k accepted iterations."""
    snapshots: list[loop.State] = []

    def snapshot(s: loop.State) -> None:
        snapshots.append(dataclasses.replace(s, lin=None))

    with torch.no_grad():
        final, history = loop.run(pose_tangent, points, data, config, snapshot, parameters=slots)
    # Snapshot s holds every problem after s global iterations (a problem is active in every
    # global iteration before it stops). Problem b's window starts at the last snapshot that
    # still has k accepted iterations of b ahead, or at 0 when b accepted fewer than k.
    accepted = torch.stack([s.accepted for s in snapshots])  # (S, B)
    ahead = accepted <= (final.accepted - k)[None, :]
    index = torch.arange(accepted.shape[0], device=accepted.device)[:, None]
    begin = torch.where(ahead, index, 0).amax(0)
    b = torch.arange(begin.numel(), device=begin.device)

    def pick(name: str) -> Tensor:
        return torch.stack([getattr(s, name) for s in snapshots])[begin, b]

    at_start = begin == 0
    xi = torch.where(at_start[:, None, None], pose_tangent, pick("xi"))
    X = torch.where(at_start[:, None, None], points, pick("X"))
    P = None
    if slots is not None:
        P = torch.where(at_start[:, None, None], slots, pick("parameters"))
    factor = whitening_factors(data)
    structured = config.linear_solver == "schur"
    lin = linearize(xi, X, data, factor, config.jacobian, structured, None, P)
    state = loop.State(
        start=xi,
        poses=lin.poses,
        moved=torch.zeros(xi.shape[:2], dtype=torch.bool, device=xi.device),
        X=X,
        lam=pick("lam"),
        nu=pick("nu"),
        status=pick("status"),
        iterations=pick("iterations"),
        cost=lin.cost,
        lin=lin,
        accepted=pick("accepted"),
        parameters=P,
    )
    state = loop.iterate(state, data, factor, config, None)
    return loop.finish(state, config), history


# ------------------------------------------------------------------------------------------
# Implicit: the implicit function theorem at the solution


@dataclass(frozen=True)
class _DataSpec:
    """How to rebuild a PointMapData from its differentiable tensors θ (a flat list): the
    observation fields, the loss's tensor attributes and the pose terms' tensors."""

    data: PointMapData
    fields: tuple[str, ...]
    loss_attributes: tuple[str, ...]
    term_tensors: tuple[tuple[str, ...], ...]

    @staticmethod
    def of(data: PointMapData) -> _DataSpec:
        fields = tuple(
            f for f in ("observations", "weights", "information") if getattr(data, f) is not None
        )
        terms = tuple(tuple(term.tensors()) for term in data.terms)
        return _DataSpec(data, fields, tuple(losses.tensor_attributes(data.loss)), terms)

    def tensors(self) -> list[Tensor]:
        out = [getattr(self.data, f) for f in self.fields]
        out += [getattr(self.data.loss, a) for a in self.loss_attributes]
        for term, names in zip(self.data.terms, self.term_tensors, strict=True):
            values = term.tensors()
            out += [values[name] for name in names]
        return out

    def rebuild(self, theta: list[Tensor]) -> PointMapData:
        it = iter(theta)
        values = {f: next(it) for f in self.fields}
        loss = losses.with_tensor_attributes(
            self.data.loss, {name: next(it) for name in self.loss_attributes}
        )
        terms = tuple(
            term.replace_tensors({name: next(it) for name in names})
            for term, names in zip(self.data.terms, self.term_tensors, strict=True)
        )
        return dataclasses.replace(self.data, loss=loss, terms=terms, **values)


@dataclass(frozen=True)
class _ImplicitSpec:
    data: _DataSpec
    config: SolverConfig
    implicit: ImplicitConfig


def _dot(a: tuple[Tensor, Tensor], b: tuple[Tensor, Tensor]) -> Tensor:
    """Per-problem inner product of (pose (B, m, 6), point (B, n, 3)) pairs, (B,)."""
    return (a[0] * b[0]).flatten(1).sum(-1) + (a[1] * b[1]).flatten(1).sum(-1)


class _ImplicitSolution(torch.autograd.Function):
    """Identity on the solution (ξ*, X*, P*) in forward; implicit-function VJP in backward.

    P* and P0 are the parameter blocks' slot values (B, S, 6) at the solution and at the
    start, for a problem that has them; else two empty (B, 0, 6) tensors."""

    @staticmethod
    def forward(ctx, xi_star, X_star, P_star, xi0, X0, P0, spec, *theta):
        ctx.spec = spec
        ctx.save_for_backward(xi_star, X_star, P_star, xi0, X0, P0, *theta)
        return xi_star.clone(), X_star.clone(), P_star.clone()

    @staticmethod
    def backward(ctx, grad_xi, grad_X, grad_P):
        with threads_for(ctx.spec.data.data):  # small problems on one thread (._threads)
            return _ImplicitSolution._backward(ctx, grad_xi, grad_X, grad_P)

    @staticmethod
    def _backward(ctx, grad_xi, grad_X, grad_P):
        # The engine runs a backward in grad mode exactly when it records a graph of the
        # gradient (create_graph=True). That graph would have to differentiate the solution
        # map twice (third derivatives of the cost); rather than return a gradient that
        # silently treats w = H⁻¹v as a constant, refuse.
        if torch.is_grad_enabled():
            raise RuntimeError(
                "solve_differentiable: backward='implicit' provides first derivatives only; "
                "a second derivative (torch.autograd.grad(..., create_graph=True), "
                ".backward(create_graph=True), Hessian-vector products) through it is not "
                "implemented. Use solve_differentiable(..., backward='unrolled') to "
                "differentiate twice."
            )
        spec: _ImplicitSpec = ctx.spec
        xi_star, X_star, P_star, xi0, X0, P0, *theta = ctx.saved_tensors
        need = ctx.needs_input_grad
        need_theta = list(need[7:])
        data0 = spec.data.data
        m = xi_star.shape[1]
        free_pose = ~data0.fixed_poses[..., None]
        free_point = ~data0.fixed_points[..., None]
        layout = data0.parameters
        if layout is None:
            fixed_slot = torch.zeros(P_star.shape[:2], dtype=torch.bool, device=P_star.device)
            active = fixed_slot[0, :, None].expand(-1, 6)
        else:
            # clones: the layout caches its masks, perhaps first made in inference mode
            fixed_slot = layout.fixed_slots().to(P_star.device).clone()
            active = layout.active.to(P_star.device).clone()
        # the slots' tangent entries that are variables: free blocks, entries of a block
        free_slot = ~fixed_slot[..., None] & active
        with torch.enable_grad(), _checks.validation(False):
            leaves = [t.detach().requires_grad_(n) for t, n in zip(theta, need_theta, strict=True)]
            xi0_leaf = xi0.detach().requires_grad_(need[3])
            X0_leaf = X0.detach().requires_grad_(need[4])
            P0_leaf = P0.detach().requires_grad_(need[5])
            data = spec.data.rebuild(leaves)
            # The chart x* ⊞ δ (δ_p over the poses and then the parameter slots, as in the
            # forward's reduced system); fixed variables read the initial guess (their
            # gradient path); a slot's entries past its block's size are inert.
            dp = xi_star.new_zeros(xi_star.shape[0], m + P_star.shape[1], 6).requires_grad_()
            dl = torch.zeros_like(X_star, requires_grad=True)
            with _checks.validation(False):
                T = torch.where(
                    data0.fixed_poses[..., None, None],
                    se3.exp(xi0_leaf, form="fast"),
                    _MATRIX.plus(se3.exp(xi_star, form="fast"), dp[:, :m]),
                )
            X = torch.where(data0.fixed_points[..., None], X0_leaf, X_star + dl)
            P = None
            if layout is not None:
                P = torch.where(fixed_slot[..., None], P0_leaf, P_star + dp[:, m:] * active)
            F = cost_from_poses(T, X, data, P).sum()
            g = torch.autograd.grad(F, (dp, dl), create_graph=True)

            # v = (dξ*/dδ)ᵀ ḡ with dξ*/dδ = jr_inv(ξ*) = jl_inv(−ξ*) (SE3Tangent.plus_jacobian);
            # the parameter slots' chart is the identity.
            with _checks.validation(False):
                jr_inv = se3.jr_inv(xi_star, form="fast")
            v_pose = (grad_xi[..., None, :] @ jr_inv)[..., 0, :] * free_pose
            v = (torch.cat((v_pose, grad_P * free_slot), dim=1), grad_X * free_point)
            w = _solve_hessian(spec, data0, xi_star, X_star, g, (dp, dl), v, P_star)

            wanted = [leaf for leaf in leaves if leaf.requires_grad]
            wanted += [x for x in (xi0_leaf, X0_leaf, P0_leaf) if x.requires_grad]
            grads = iter(())
            if wanted:
                inner = _dot(g, w).sum()
                grads = iter(torch.autograd.grad(inner, wanted, allow_unused=True))

        def take(leaf: Tensor) -> Tensor | None:
            if not leaf.requires_grad:
                return None
            d = next(grads)
            return torch.zeros_like(leaf) if d is None else -d

        theta_grads = [take(leaf) for leaf in leaves]
        xi0_grad, X0_grad, P0_grad = take(xi0_leaf), take(X0_leaf), take(P0_leaf)
        # The fixed variables of the output are the initial guess itself.
        if xi0_grad is not None:
            xi0_grad = xi0_grad + grad_xi * ~free_pose
        if X0_grad is not None:
            X0_grad = X0_grad + grad_X * ~free_point
        if P0_grad is not None:
            P0_grad = P0_grad + grad_P * fixed_slot[..., None]
        return (None, None, None, xi0_grad, X0_grad, P0_grad, None, *theta_grads)


def _solve_hessian(
    spec: _ImplicitSpec,
    data: PointMapData,
    xi_star: Tensor,
    X_star: Tensor,
    g: tuple[Tensor, Tensor],
    delta: tuple[Tensor, Tensor],
    v: tuple[Tensor, Tensor],
    slots: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """w = H⁻¹ v per problem; H the Hessian of F in the chart at δ = 0 (module doc).

    With parameter blocks (``slots`` (B, S, 6) at the solution; the pose parts of g, δ, v
    then cover m + S rows, as the forward's reduced system does) the exact H is not
    assembled: every problem runs the conjugate gradients below.

    Exact (default): H assembled in the forward's block structure (:mod:`.hessian`) and
    factored once by the forward pass's plan (:meth:`torchslam.solver.plan.LinearPlan.
    factorize` with λ = 0, or its GEMM variant for dense co-visibility), then solved with −v
    in place of the gradient (its step −H⁻¹(−v) is the solution). Problems whose H does not
    factor (not positive definite) fall back to conjugate gradients on the exact Hessian
    (Hessian-vector products by double backward), preconditioned by the Gauss-Newton solve,
    batched with per-problem step sizes. Gauss-Newton: that preconditioner alone (JᵀJ at x*
    factored once the same way).
    """
    config, options = spec.config, spec.implicit
    plan = LinearPlan.build(data, config)
    lam = xi_star.new_zeros(xi_star.shape[0])
    fallback = None
    if options.hessian == "exact" and data.parameters is None:
        w_exact, ok = _exact_solve(plan, data, xi_star, X_star, v, config)
        if bool(ok.all()):
            return w_exact
        # H is not positive definite for some problem (singular: a point whose residuals all
        # lie beyond a redescending kernel's reach; indefinite: not a strict minimum, e.g. an
        # unconverged iterate under on_unconverged="implicit"): those problems run the
        # conjugate gradients below; the others start converged (v = 0 there) and keep the
        # direct solution.
        fallback = ~ok
        v = tuple(torch.where(fallback[:, None, None], x, 0.0) for x in v)
    with torch.no_grad():
        # Factor JᵀJ at x* once (dense or sparse, as the forward solve); every conjugate-
        # gradient iteration then reuses the factorization (two triangular solves).
        factor = whitening_factors(data)
        structured = config.linear_solver == "schur"
        params = None if data.parameters is None else slots
        lin = linearize(xi_star, X_star, data, factor, config.jacobian, structured, None, params)
        gauss_newton = plan.factorize(lin, lam)

    def precondition(r: tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor]:
        with torch.no_grad():
            # The step −(JᵀJ)⁻¹ g for g = −r is (JᵀJ)⁻¹ r.
            zp, zl = gauss_newton.solve(-r[0], -r[1])
            ok = gauss_newton.ok
            # A singular JᵀJ (e.g. a point whose weights are all 0): no preconditioning there.
            return (
                torch.where(ok[:, None, None], zp, r[0]),
                torch.where(ok[:, None, None], zl, r[1]),
            )

    if options.hessian == "gauss_newton":
        return precondition(v)

    def hessian_product(p: tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor]:
        Hp = torch.autograd.grad(_dot(g, p).sum(), delta, retain_graph=True, allow_unused=True)
        return tuple(
            torch.zeros_like(d) if h is None else h.detach() for h, d in zip(Hp, delta, strict=True)
        )

    def axpy(a: Tensor, x: tuple[Tensor, Tensor], y: tuple[Tensor, Tensor]):
        return (y[0] + a[:, None, None] * x[0], y[1] + a[:, None, None] * x[1])

    def safe_ratio(num: Tensor, den: Tensor) -> Tensor:
        nonzero = den != 0
        return torch.where(nonzero, num / torch.where(nonzero, den, 1.0), 0.0)

    # Preconditioned conjugate gradients (Hestenes-Stiefel), batched over problems. A problem
    # whose residual meets the tolerance takes no further step (α = 0), so its w does not
    # depend on the other problems of the batch: the same gradient alone or in any shard.
    w = (torch.zeros_like(v[0]), torch.zeros_like(v[1]))
    r = v
    z = precondition(r)
    p = z
    rz = _dot(r, z)
    limit = options.tolerance * torch.sqrt(_dot(v, v))
    for _ in range(options.max_iterations):
        active = torch.sqrt(_dot(r, r)) > limit
        if not bool(active.any()):
            break
        Hp = hessian_product(p)
        alpha = torch.where(active, safe_ratio(rz, _dot(p, Hp)), 0.0)
        w = axpy(alpha, p, w)
        r = axpy(-alpha, Hp, r)
        z = precondition(r)
        rz_new = _dot(r, z)
        p = axpy(safe_ratio(rz_new, rz), p, z)
        rz = rz_new
    if fallback is not None:
        w = tuple(
            torch.where(fallback[:, None, None], a, b) for a, b in zip(w, w_exact, strict=True)
        )
    return w


def _exact_solve(
    plan: LinearPlan,
    data: PointMapData,
    xi_star: Tensor,
    X_star: Tensor,
    v: tuple[Tensor, Tensor],
    config: SolverConfig,
) -> tuple[tuple[Tensor, Tensor], Tensor]:
    """(w = H⁻¹v, ok (B,)) with the exact Hessian H (:mod:`.hessian`) factored once by the
    forward's plan (λ = 0); w is zero where ``ok`` is False (H not positive definite, or a
    non-finite solution)."""
    with torch.no_grad():
        hessian = exact_hessian(xi_star, X_star, data, config.jacobian)
        lam = xi_star.new_zeros(xi_star.shape[0])
        if plan.coupling_gemm_pays():
            factorization = plan.factorize_coupling_gemm(hessian, lam)
        else:
            factorization = plan.factorize(hessian, lam)
        # The step for the gradient −v is H⁻¹v.
        wp, wl = factorization.solve(-v[0], -v[1])
        ok = factorization.ok & torch.isfinite(wp).flatten(1).all(-1)
        ok = ok & torch.isfinite(wl).flatten(1).all(-1)
        w = (torch.where(ok[:, None, None], wp, 0.0), torch.where(ok[:, None, None], wl, 0.0))
    return w, ok


def _solve_implicit(
    pose_tangent: Tensor,
    points: Tensor,
    data: PointMapData,
    config: SolverConfig,
    implicit: ImplicitConfig,
    on_unconverged: str,
    slots: Tensor | None = None,
) -> SolveResult:
    layout = data.parameters
    initial = None if slots is None else layout.unpack(slots.detach())
    result = solve_tensors(pose_tangent, points, data, config, parameters=initial)
    data_spec = _DataSpec.of(data)
    theta = data_spec.tensors()
    start_values = (pose_tangent, points) + (() if slots is None else (slots,))
    if not _inference.tracked(*start_values, *theta):
        return result
    unconverged = [b for b, ok in enumerate(result.converged) if not ok]
    if unconverged and on_unconverged == "raise":
        raise RuntimeError(
            f"solve_differentiable: {_describe(result, unconverged)} did not converge, so the "
            "implicit gradient (which assumes a minimum) would not be the derivative of the "
            "solution returned (on_unconverged='raise'). Raise max_iterations or loosen the "
            "tolerances, or pass on_unconverged='unroll' to differentiate the iterations "
            "actually run."
        )
    unroll = bool(unconverged) and on_unconverged in ("warn", "unroll")
    if unroll and on_unconverged == "warn":
        warnings.warn(
            f"solve_differentiable: {_describe(result, unconverged)} did not converge; their "
            "gradients are those of the iterations actually run (an unrolled re-run), not the "
            "implicit gradient at a minimum. Pass on_unconverged='unroll' to silence this, "
            "'raise' to refuse, or 'implicit' for the implicit gradient anyway.",
            UserWarning,
            stacklevel=3,
        )
    xi_star, X_star = result.pose_tangent, result.points
    if unroll:
        # The implicit backward still runs on the whole batch; the unrolled problems send it
        # a zero gradient. Their slots get the (finite) initial guess, so that a non-finite
        # iterate cannot turn that zero into NaN (0 · NaN) in the Hessian solve.
        rerun = torch.tensor([b in unconverged for b in range(len(result.status))])
        rerun = rerun.to(xi_star.device)
    # the parameter slots (B, S, 6), empty (S = 0) without parameter blocks
    P0 = pose_tangent.new_zeros(pose_tangent.shape[0], 0, 6) if slots is None else slots
    P_star = P0.detach() if slots is None else layout.pack(result.parameters)
    if unroll:
        xi_star = torch.where(rerun[:, None, None], pose_tangent.detach(), xi_star)
        X_star = torch.where(rerun[:, None, None], points.detach(), X_star)
        P_star = torch.where(rerun[:, None, None], P0.detach(), P_star)
    xi, X, P = xi_star, X_star, P_star
    if len(unconverged) < len(result.status) or not unroll:
        spec = _ImplicitSpec(data_spec, config, implicit)
        xi, X, P = _ImplicitSolution.apply(
            xi_star, X_star, P_star, pose_tangent, points, P0, spec, *theta
        )
    if unroll:
        # Unrolled: the same iterations with autograd on (problems are independent in the
        # batch, so the others do not change them); no problem needs more than the most any
        # unconverged problem used.
        cap = int(result.iterations[unconverged].max())
        rerun_config = dataclasses.replace(config, reduced_solver="dense", max_iterations=cap)
        with _checks.validation(False):
            state, _ = loop.run(pose_tangent, points, data, rerun_config, None, parameters=slots)
        xi = torch.where(rerun[:, None, None], state.xi, xi)
        X = torch.where(rerun[:, None, None], state.X, X)
        if slots is not None:
            P = torch.where(rerun[:, None, None], state.parameters, P)
    with _checks.validation(False):
        final_cost = cost(xi, X, data, None if slots is None else P)
    parameters = {} if slots is None else layout.unpack(P)
    return dataclasses.replace(
        result, pose_tangent=xi, points=X, final_cost=final_cost, parameters=parameters
    )


def _describe(result: SolveResult, problems: list[int], limit: int = 10) -> str:
    """'problem 1 (MAX_ITERATIONS)' / 'problems 0 (…), 3 (…) and 5 more' for a message."""
    shown = ", ".join(f"{b} ({result.status[b].name})" for b in problems[:limit])
    more = f" and {len(problems) - limit} more" if len(problems) > limit else ""
    return f"problem{'s' if len(problems) > 1 else ''} {shown}{more} of {len(result.status)}"


# ------------------------------------------------------------------------------------------
# Inputs whose autograd graph a previous backward already freed

# At most this many autograd nodes are visited per solve, breadth first from the inputs (the
# nodes nearest to them, which a previous backward through them freed first): a host-side
# walk of a few milliseconds at most, no device work.
_GRAPH_CHECK_NODES = 1000
# Per autograd node class, the attributes holding its raw saved tensors.
_SAVED_ATTRIBUTES: dict[type, tuple[str, ...]] = {}


def _freed(node: object) -> bool:
    """True if ``node`` is an autograd node whose saved tensors a backward has released.

    Reads the raw saved tensors (``_raw_saved_*``, ``.data`` is None once freed), never
    unpacks a live one: unpacking would run saved-tensor hooks (``save_on_cpu`` copies,
    checkpointing's recomputation). A custom Function's node raises on its raw tensors once
    they are freed."""
    names = _SAVED_ATTRIBUTES.get(type(node))
    if names is None:
        names = tuple(a for a in dir(node) if a.startswith("_raw_saved_"))
        _SAVED_ATTRIBUTES[type(node)] = names
    for name in names:
        try:
            raw = getattr(node, name)
        except RuntimeError as error:
            if "freed" in str(error):
                return True
            continue
        for saved in raw if isinstance(raw, (list, tuple)) else (raw,):
            if getattr(saved, "data", True) is not None:
                continue
            # Freed, or an optional saved tensor that was never defined: only a freed one
            # raises when unpacked (and a freed one has no hook left to run).
            try:
                getattr(node, "_saved_" + name[len("_raw_saved_") :], None)
            except RuntimeError as error:
                if "freed" in str(error):
                    return True
    return False


def _check_graphs_alive(fn: str, pose_tangent: Tensor, points: Tensor, data: PointMapData) -> None:
    """Raise a ValueError naming the input whose graph a previous backward freed (module
    doc): torch's own error would come only at the next backward, without the remedy."""
    spec = _DataSpec.of(data)
    names = [f"data.{f}" for f in spec.fields]
    names += [f"data.loss.{a}" for a in spec.loss_attributes]
    names += [f"data.terms[{i}] {n!r}" for i, ns in enumerate(spec.term_tensors) for n in ns]
    inputs = [("pose_tangent", pose_tangent), ("points", points)]
    inputs += list(zip(names, spec.tensors(), strict=True))
    seen: set = set()
    budget = _GRAPH_CHECK_NODES
    for name, tensor in inputs:
        queue = collections.deque([tensor.grad_fn])
        while queue and budget > 0:
            node = queue.popleft()
            if node is None or node in seen:
                continue
            seen.add(node)
            budget -= 1
            if _freed(node):
                raise ValueError(
                    f"{fn}: '{name}' was computed by an autograd graph that a previous "
                    f"backward() already freed (its node {type(node).__name__}), so no gradient "
                    "can reach what it was computed from. A tensor computed once (e.g. "
                    "weights=torch.sigmoid(logits) in a PointMapProblem built before the "
                    "training loop) serves one backward only: recompute it for every solve, "
                    "e.g. data = dataclasses.replace(problem.data, "
                    "weights=torch.sigmoid(logits)), or build the problem inside the loop."
                )
            queue.extend(next_node for next_node, _ in node.next_functions)
