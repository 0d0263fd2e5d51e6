"""Gradients through the solver: unrolled, truncated and implicit backward modes (issue 5).

:func:`solve_differentiable` solves the same problem as :func:`torchslam.solve_tensors` and
returns a :class:`SolveResult` whose ``pose_tangent``, ``points`` (and ``final_cost``) carry
an autograd graph back to everything the solution depends on: the observations, the scalar
weights or information matrices (and whatever produced them), tensor parameters of the robust
loss (e.g. ``HuberLoss(scale)`` with a tensor scale), and the initial guess. Four modes:

- ``"unrolled"``: the Levenberg-Marquardt (or Gauss-Newton, gradient-descent) iterations run
  with autograd on: linearize → Schur solve (:mod:`.linear`) → retract, every iteration
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
  ``H`` is solved with the forward pass's Schur machinery: the Gauss-Newton matrix JᵀJ at x*
  is factored once by :func:`torchslam.solver.linear.factorize` (λ = 0; dense Cholesky or
  the sparse factorization, as the forward solve) and solved for the right-hand side; with
  ``ImplicitConfig(hessian="exact")`` (default) that solve
  preconditions conjugate gradients on the exact Hessian (Hessian-vector products by double
  backward), which the unrolled gradient converges to — JᵀJ alone drops the Σ r ∇²r and ρ''
  terms, an O(residual) error. Fixed variables keep their given values: the initial guess
  receives the identity there, plus the effect of moving a fixed variable (e.g. the gauge
  pose) on the free solution; elsewhere the solution does not depend on the initial guess.
  The theorem needs a converged, non-degenerate minimum (check ``result.converged``).
- ``"none"``: :func:`torchslam.solve_tensors` (``torch.no_grad``), detached results.

With a :class:`torchslam.PointMapProblem` (weights produced by a model ``net``)::

    problem = PointMapProblem(poses0, points0, pose_index, point_index, observations,
                              weights=net(features), loss=HuberLoss(scale))
    result = solve_differentiable(problem.pose_tangent, problem.points, problem.data)
    pose_loss(result.poses, poses_gt).backward()   # reaches net's parameters (and scale)
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from torchslam import _checks, losses
from torchslam.lie import se3
from torchslam.problem import PointMapData, cost, cost_from_poses
from torchslam.solver import linear
from torchslam.solver.config import SolverConfig, check_implicit_config
from torchslam.solver.linearize import (
    StructuredLinearization,
    linearize,
    whitening_factors,
)
from torchslam.solver.result import SolveResult
from torchslam.solver.solve import (
    _finish,
    _iterate,
    _result,
    _run,
    _State,
    check_solve_inputs,
    solve_tensors,
    sparse_schur,
)

__all__ = ["Backward", "ImplicitConfig", "solve_differentiable"]

Backward = Literal["implicit", "unrolled", "truncated", "none"]
_BACKWARDS = ("implicit", "unrolled", "truncated", "none")
_HESSIANS = ("exact", "gauss_newton")


@dataclass(frozen=True)
class ImplicitConfig:
    """Options of the implicit backward of :func:`solve_differentiable`."""

    # H in H w = v: "exact" (conjugate gradients on the exact Hessian, Hessian-vector products
    # by double backward, preconditioned by the Gauss-Newton Schur solve) or "gauss_newton"
    # (the Schur solve with JᵀJ alone: cheaper, exact only for zero-residual problems).
    hessian: Literal["exact", "gauss_newton"] = "exact"
    # Conjugate gradients stop when ‖H w − v‖ ≤ tolerance · ‖v‖ in every problem.
    tolerance: float = 1e-10
    # At most this many conjugate-gradient iterations (each one Hessian-vector product).
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

    Returns:
        A :class:`SolveResult`; ``pose_tangent`` (B, m, 6), ``points`` (B, n, 3) and
        ``final_cost`` (B,) are differentiable (detached for "none"), the histories are not.
    """
    fn = "solve_differentiable"
    config = check_solve_inputs(fn, pose_tangent, points, data, config)
    _checks.check_tensor(fn, "pose_tangent", pose_tangent, (6,), min_batch_dims=2)
    _checks.check_tensor(fn, "points", points, (3,), min_batch_dims=2)
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
    implicit = implicit or ImplicitConfig()

    if backward == "none":
        return solve_tensors(pose_tangent, points, data, config)
    if backward == "implicit":
        return _solve_implicit(pose_tangent, points, data, config, implicit)
    start = time.perf_counter()
    with _checks.validation(False):
        if backward == "unrolled":
            state, costs, lambdas = _run(pose_tangent, points, data, config, None)
        else:
            state, costs, lambdas = _run_truncated(
                pose_tangent, points, data, config, truncate_steps
            )
    return _result(state, costs, lambdas, start)


# ------------------------------------------------------------------------------------------
# Unrolled and truncated: the solver loop with autograd on


def _run_truncated(
    pose_tangent: Tensor, points: Tensor, data: PointMapData, config: SolverConfig, k: int
) -> tuple[_State, list[Tensor], list[Tensor]]:
    """Solve under no_grad keeping a snapshot per iteration, then re-run each problem with
    autograd on from the snapshot before its last k accepted iterations."""
    snapshots: list[_State] = []

    def snapshot(s: _State) -> None:
        snapshots.append(dataclasses.replace(s, lin=None))

    with torch.no_grad():
        final, costs, lambdas = _run(pose_tangent, points, data, config, snapshot)
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
    factor = whitening_factors(data)
    lin = linearize(xi, X, data, factor, config.jacobian, config.linear_solver == "schur")
    state = _State(
        xi=xi,
        X=X,
        lam=pick("lam"),
        nu=pick("nu"),
        status=pick("status"),
        iterations=pick("iterations"),
        cost=lin.cost,
        lin=lin,
        accepted=pick("accepted"),
    )
    state = _iterate(state, data, factor, config, None)
    return _finish(state, config), costs, lambdas


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
    """Identity on the solution (ξ*, X*) in forward; implicit-function VJP in backward."""

    @staticmethod
    def forward(ctx, xi_star, X_star, xi0, X0, spec, *theta):
        ctx.spec = spec
        ctx.save_for_backward(xi_star, X_star, xi0, X0, *theta)
        return xi_star.clone(), X_star.clone()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_xi, grad_X):
        spec: _ImplicitSpec = ctx.spec
        xi_star, X_star, xi0, X0, *theta = ctx.saved_tensors
        need = ctx.needs_input_grad
        need_theta = list(need[5:])
        data0 = spec.data.data
        free_pose = ~data0.fixed_poses[..., None]
        free_point = ~data0.fixed_points[..., None]
        with torch.enable_grad(), _checks.validation(False):
            leaves = [t.detach().requires_grad_(n) for t, n in zip(theta, need_theta, strict=True)]
            xi0_leaf = xi0.detach().requires_grad_(need[2])
            X0_leaf = X0.detach().requires_grad_(need[3])
            data = spec.data.rebuild(leaves)
            # The chart x* ⊞ δ; fixed variables read the initial guess (their gradient path).
            dp = torch.zeros_like(xi_star, requires_grad=True)
            dl = torch.zeros_like(X_star, requires_grad=True)
            T = torch.where(
                data0.fixed_poses[..., None, None],
                se3._exp(xi0_leaf),
                se3._exp(xi_star) @ se3._exp(dp),
            )
            X = torch.where(data0.fixed_points[..., None], X0_leaf, X_star + dl)
            F = cost_from_poses(T, X, data).sum()
            g = torch.autograd.grad(F, (dp, dl), create_graph=True)

            # v = (dξ*/dδ)ᵀ ḡ with dξ*/dδ = jr_inv(ξ*) = jl_inv(−ξ*) (SE3Tangent.plus_jacobian).
            jr_inv = se3._jl_inv(-xi_star)
            v = (
                (grad_xi[..., None, :] @ jr_inv)[..., 0, :] * free_pose,
                grad_X * free_point,
            )
            w = _solve_hessian(spec, data0, xi_star, X_star, g, (dp, dl), v)

            wanted = [leaf for leaf in leaves if leaf.requires_grad]
            wanted += [x for x in (xi0_leaf, X0_leaf) if x.requires_grad]
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
        xi0_grad, X0_grad = take(xi0_leaf), take(X0_leaf)
        # The fixed variables of the output are the initial guess itself.
        if xi0_grad is not None:
            xi0_grad = xi0_grad + grad_xi * ~free_pose
        if X0_grad is not None:
            X0_grad = X0_grad + grad_X * ~free_point
        return (None, None, xi0_grad, X0_grad, None, *theta_grads)


def _solve_hessian(
    spec: _ImplicitSpec,
    data: PointMapData,
    xi_star: Tensor,
    X_star: Tensor,
    g: tuple[Tensor, Tensor],
    delta: tuple[Tensor, Tensor],
    v: tuple[Tensor, Tensor],
) -> tuple[Tensor, Tensor]:
    """w = H⁻¹ v per problem; H the Hessian of F in the chart at δ = 0 (module doc).

    The Gauss-Newton matrix JᵀJ at x* is solved with the forward pass's Schur machinery
    (:func:`torchslam.solver.linear.factorize` with λ = 0, factored once, then solved with −v
    in place of the gradient, so its step −(JᵀJ)⁻¹(−v) is the solution). For the exact
    Hessian that solve preconditions conjugate gradients, batched with per-problem step sizes.
    """
    config, options = spec.config, spec.implicit
    with torch.no_grad():
        # Factor JᵀJ at x* once (dense or sparse, as the forward solve); every conjugate-
        # gradient iteration then reuses the factorization (two triangular solves).
        factor = whitening_factors(data)
        structured = config.linear_solver == "schur"
        lin = linearize(xi_star, X_star, data, factor, config.jacobian, structured)
        sparse = sparse_schur(data, config)
        structure = None
        if not isinstance(lin, StructuredLinearization) and structured and sparse is None:
            structure = linear.SchurStructure.build(data)
        lam = xi_star.new_zeros(xi_star.shape[0])
        gauss_newton = linear.factorize(
            lin,
            data,
            structure,
            lam,
            config.damping,
            config.linear_solver,
            config.schur_chunk_size,
            sparse,
        )

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

    # Preconditioned conjugate gradients (Hestenes-Stiefel), batched over problems.
    w = (torch.zeros_like(v[0]), torch.zeros_like(v[1]))
    r = v
    z = precondition(r)
    p = z
    rz = _dot(r, z)
    limit = options.tolerance * torch.sqrt(_dot(v, v))
    for _ in range(options.max_iterations):
        if bool((torch.sqrt(_dot(r, r)) <= limit).all()):
            break
        Hp = hessian_product(p)
        alpha = safe_ratio(rz, _dot(p, Hp))
        w = axpy(alpha, p, w)
        r = axpy(-alpha, Hp, r)
        z = precondition(r)
        rz_new = _dot(r, z)
        p = axpy(safe_ratio(rz_new, rz), p, z)
        rz = rz_new
    return w


def _solve_implicit(
    pose_tangent: Tensor,
    points: Tensor,
    data: PointMapData,
    config: SolverConfig,
    implicit: ImplicitConfig,
) -> SolveResult:
    result = solve_tensors(pose_tangent, points, data, config)
    data_spec = _DataSpec.of(data)
    theta = data_spec.tensors()
    if not torch.is_grad_enabled() or not any(
        t.requires_grad for t in (pose_tangent, points, *theta)
    ):
        return result
    spec = _ImplicitSpec(data_spec, config, implicit)
    xi, X = _ImplicitSolution.apply(
        result.pose_tangent, result.points, pose_tangent, points, spec, *theta
    )
    with _checks.validation(False):
        final_cost = cost(xi, X, data)
    return dataclasses.replace(result, pose_tangent=xi, points=X, final_cost=final_cost)
