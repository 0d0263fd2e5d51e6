"""Marginal covariances of a solved problem, from the solve's own linear-solve plan.

At the solution x*, the Gauss-Newton approximation of the cost's Hessian is H = J̃ᵀJ̃: J̃ the
Jacobian of the whitened residuals, robustified by the kernel's corrector at x* as Ceres'
``Covariance`` evaluates it (√ρ'(s) and the curvature term, :func:`torchslam.losses.
triggs_correction`), with respect to the free variables in the solver's charts — the right
perturbation T·Exp(δ) of each pose, δ = (ω, v) rotation first, and δX of each point. When the
weights are the inverse noise covariances (Ω = Σ_noise⁻¹, scalar w = 1/σ²), H⁻¹ is the
covariance of the estimate (to first order); :func:`marginal_covariances` returns its blocks:

- per pose the 6 × 6 block Σ_ii = Cov(δ_i) in (ω, v) order (for a :class:`PointMapProblem`,
  whose poses are T_i0 (world → frame i), T_i0·Exp(δ) moves the frame by Exp(−δ) on the world
  side: δ is in world coordinates; :func:`position_covariance` gives the covariance of the
  frame's position, :func:`pose_uncertainty` 1-σ figures; for a pose graph, whose vertices
  are body → world, δ is in the body frame, as GTSAM's);
- per point the 3 × 3 block Σ_XjXj;
- for requested pose pairs (i, k) the 6 × 6 cross-covariance Σ_ik = Cov(δ_i, δ_k).

How. The problem is relinearized at the solution and factored with λ = 0 by the solve's
:class:`torchslam.solver.plan.LinearPlan` (the same method and reduced solver as the solve
with the same config). The pose blocks come from the reduced system S = U − W V⁻¹ Wᵀ:

- dense reduced solver (small m): S⁻¹ from its batched Cholesky factor (differentiable);
- sparse reduced solver: only the blocks of S⁻¹ on the pattern of its sparse factor, by the
  block Takahashi recursion on that factor (:func:`torchslam.solver.sparse.selected_inverse`);
  the pattern holds every diagonal block and every pair of poses that share a point or a
  term, so a cross block outside it costs 6 extra solves per distinct pose (never a dense
  inverse of the system); a parameter block's slots (one term touches them all) lie on it
  too;
- the "dense" method (``SolverConfig(linear_solver="dense")``, small problems): the blocks
  of H⁻¹ from the Cholesky factor of the full system.

Points by the back-substitution of the Schur complement: with V_j the point's block and W_e
the pose-point blocks of its edges e = (i_e, j),

    Σ_XjXj = V_j⁻¹ + V_j⁻¹ (Σ_(a,b) W_aᵀ Σ_(i_a i_b) W_b) V_j⁻¹,

whose pose blocks (i_a, i_b) share the point, hence lie on the factor's pattern.

Gauge and fixed variables. Covariances are relative to the fixed poses and points (pose 0 by
default): those have zero covariance and zero cross-covariance. A free gauge or any other
variable the data do not determine makes H singular: the problem is reported (``ok`` False,
``reason``) and its blocks are NaN, never round-off garbage. The test is the factorization's
pivots: a pivot D_k of the factor with D_k ≤ ``rank_tolerance`` · H_kk (the variable is a
combination of earlier ones to working precision) or a failed factorization.

Differentiable with respect to the weights (and the solution, as :func:`torchslam.
solve_differentiable` returns it) through the dense paths; the sparse path runs SciPy and
raises a ValueError when a gradient is asked for.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from torchslam import _checks
from torchslam.lie import so3
from torchslam.objective.data import PointMapData
from torchslam.objective.parameters import pack_values
from torchslam.problem import PointMapProblem
from torchslam.solver.config import SolverConfig
from torchslam.solver.linearize import StructuredLinearization, linearize, whitening_factors
from torchslam.solver.plan import LinearPlan
from torchslam.solver.result import SolveResult
from torchslam.solver.solve import check_solve_inputs
from torchslam.solver.sparse import SparseFactor

__all__ = [
    "RANK_TOLERANCE",
    "MarginalCovariances",
    "marginal_covariances",
    "marginal_covariances_tensors",
    "pose_uncertainty",
    "position_covariance",
]

# Default pivot ratio D_k / H_kk below which the Hessian counts as singular, by dtype: well
# above the round-off of a singular matrix's pivots (~1e-16 · growth in float64), well below
# the smallest ratio of real problems (parking-garage: 1.8e-6, a variance 5·10⁵ times its
# variable's own information alone).
RANK_TOLERANCE = {torch.float64: 1e-10, torch.float32: 1e-4}
# Entries of the (B, 6m, 3c) coupling buffer of one chunk of c points (dense reduced path).
_CHUNK_ENTRIES = 1 << 24


@dataclass
class MarginalCovariances:
    """Marginal covariance blocks of B solved problems (module doc for the conventions).

    Blocks of a problem that is not ``ok`` are NaN. Fixed poses and points have zero blocks.
    """

    # Σ_ii of the poses ``pose_index``, (B, P, 6, 6), (ω, v) order, right perturbation
    # T_i·Exp(δ) of the solver's poses (T_i0, world → frame i, for a PointMapProblem).
    poses: Tensor
    # Σ_XjXj of the points ``point_index``, (B, Q, 3, 3), world coordinates.
    points: Tensor
    # Σ_ik = Cov(δ_i, δ_k) of the pairs ``pair_index``, (B, R, 6, 6).
    pairs: Tensor
    # The poses (P,), points (Q,) and pose pairs (R, 2) the blocks belong to, long.
    pose_index: Tensor
    point_index: Tensor
    pair_index: Tensor
    # Whether each problem's Hessian was positive definite (its blocks are valid), bool (B,).
    ok: Tensor
    # A sentence per problem: "ok", or why its covariances could not be computed.
    reason: list[str]
    # How S⁻¹ (or H⁻¹) was formed: "dense" (batched Cholesky of the reduced system),
    # "sparse" (selected inverse of the sparse factor) or "full" (the whole system).
    method: str
    # Σ of every parameter block by group, {name: (B, q, d, d)} in the block's own entries
    # (x ← x + δ), zero for fixed blocks (empty without parameter blocks;
    # :mod:`torchslam.objective.parameters`).
    parameters: dict[str, Tensor] = field(default_factory=dict)

    def check(self) -> MarginalCovariances:
        """Self when every problem is ok; ValueError naming the first one that is not."""
        for b, ok in enumerate(self.ok.tolist()):
            if not ok:
                raise ValueError(f"marginal_covariances: problem {b}: {self.reason[b]}")
        return self


# ------------------------------------------------------------------------------------------
# Argument checks


def _selection(fn: str, name: str, value: object, count: int, device) -> Tensor:
    """True/None → all of ``count``; False → none; a sequence or 1-D integer tensor of
    indices in [0, count) → those."""
    if value is None or value is True:
        return torch.arange(count, device=device)
    if value is False:
        return torch.zeros(0, dtype=torch.long, device=device)
    if isinstance(value, Tensor):
        _checks.check_integer_tensor(fn, name, value, "hold integer indices")
        if value.dim() != 1:
            raise ValueError(
                f"{fn}: argument '{name}' must be a 1-D tensor of indices, got shape "
                f"{tuple(value.shape)}"
            )
        index = value.to(device=device, dtype=torch.long)
    elif isinstance(value, Sequence) and not isinstance(value, (str, bytes)):
        items = [_checks.check_int(fn, f"{name}[{k}]", v) for k, v in enumerate(value)]
        index = torch.tensor(items, dtype=torch.long, device=device)
    else:
        raise TypeError(
            f"{fn}: argument '{name}' must be True, False or a sequence of indices, got "
            f"{_checks.describe(value)}"
        )
    if index.numel() and (int(index.min()) < 0 or int(index.max()) >= count):
        raise ValueError(
            f"{fn}: argument '{name}' must hold indices in [0, {count}), got values in "
            f"[{int(index.min())}, {int(index.max())}]"
        )
    return index


def _pair_selection(fn: str, pairs: object, m: int, device) -> Tensor:
    """None → (0, 2); an (R, 2) integer tensor or a sequence of (i, k) pairs in [0, m)."""
    if pairs is None:
        return torch.zeros(0, 2, dtype=torch.long, device=device)
    if isinstance(pairs, Tensor):
        _checks.check_integer_tensor(fn, "pairs", pairs, "hold integer pose indices")
        if pairs.dim() != 2 or pairs.shape[1] != 2:
            raise ValueError(
                f"{fn}: argument 'pairs' must have shape (R, 2), got {tuple(pairs.shape)}"
            )
        index = pairs.to(device=device, dtype=torch.long)
    elif isinstance(pairs, Sequence) and not isinstance(pairs, (str, bytes)):
        rows = []
        for k, pair in enumerate(pairs):
            if isinstance(pair, (str, bytes)) or not isinstance(pair, Sequence) or len(pair) != 2:
                raise ValueError(
                    f"{fn}: argument 'pairs' must hold (i, k) pose pairs, got "
                    f"{_checks.describe(pair)} at position {k}"
                )
            rows.append([_checks.check_int(fn, f"pairs[{k}]", v) for v in pair])
        index = torch.tensor(rows, dtype=torch.long, device=device).reshape(-1, 2)
    else:
        raise TypeError(
            f"{fn}: argument 'pairs' must be None or a sequence of (i, k) pose pairs, got "
            f"{_checks.describe(pairs)}"
        )
    if index.numel() and (int(index.min()) < 0 or int(index.max()) >= m):
        raise ValueError(
            f"{fn}: argument 'pairs' must hold pose indices in [0, {m}), got values in "
            f"[{int(index.min())}, {int(index.max())}]"
        )
    return index


def _rank_tolerance(fn: str, value: object, dtype: torch.dtype) -> float:
    if value is None:
        return RANK_TOLERANCE.get(dtype, 1e-10)
    return _checks.check_real(fn, "rank_tolerance", value, low=0.0, high=1.0)


# ------------------------------------------------------------------------------------------
# Public entry points


def marginal_covariances(
    problem: PointMapProblem,
    result: SolveResult | None = None,
    *,
    poses: bool | Sequence[int] | Tensor = True,
    points: bool | Sequence[int] | Tensor = True,
    pairs: Sequence[Sequence[int]] | Tensor | None = None,
    config: SolverConfig | None = None,
    rank_tolerance: float | None = None,
) -> MarginalCovariances:
    """Marginal covariances of the solution of a :class:`PointMapProblem` (module doc).

    Use after :func:`torchslam.solve`: ``marginal_covariances(problem, result)``.

    Args:
        problem: the solved problem (its data; its parameters are the solution when
            ``result`` is None).
        result: the :class:`SolveResult` of the solve, whose ``pose_tangent`` and ``points``
            are the solution (with gradients, as :func:`torchslam.solve_differentiable`
            returns them); None: the problem's current parameters.
        poses: the poses whose 6 × 6 blocks to return: True (all, default), False (none) or
            indices (P,).
        points: the points whose 3 × 3 blocks to return: True (all), False or indices (Q,).
        pairs: pose pairs (i, k) whose cross-covariances Σ_ik to return, (R, 2); default none.
        config: the solve's :class:`SolverConfig` (its ``linear_solver``, ``reduced_solver``,
            ``dense_max_variables``, ``ordering`` and ``jacobian`` choose the plan); default
            ``SolverConfig()``.
        rank_tolerance: pivot ratio below which the Hessian counts as singular
            (:data:`RANK_TOLERANCE` by dtype when None).

    Returns:
        :class:`MarginalCovariances` ((B, P, 6, 6), (B, Q, 3, 3), (B, R, 6, 6), ``ok``,
        ``reason``); ``.check()`` raises for a problem whose Hessian is singular.

    Raises:
        TypeError, ValueError: bad arguments; a gradient asked for through the sparse path.
    """
    fn = "marginal_covariances"
    if not isinstance(problem, PointMapProblem):
        raise TypeError(
            f"{fn}: argument 'problem' must be a torchslam.PointMapProblem, got "
            f"{_checks.describe(problem)}"
        )
    if result is None:
        pose_tangent, point_values = problem.pose_tangent.detach(), problem.points.detach()
        blocks = {k: v.detach() for k, v in problem.parameter_blocks.items()}
    elif isinstance(result, SolveResult):
        pose_tangent, point_values = result.pose_tangent, result.points
        blocks = result.parameters
    else:
        raise TypeError(
            f"{fn}: argument 'result' must be the SolveResult of the solve or None, got "
            f"{_checks.describe(result)}"
        )
    return _marginals(
        fn,
        pose_tangent,
        point_values,
        problem.data,
        config,
        poses,
        points,
        pairs,
        rank_tolerance,
        blocks,
    )


def marginal_covariances_tensors(
    pose_tangent: Tensor,
    points: Tensor,
    data: PointMapData,
    config: SolverConfig | None = None,
    *,
    poses: bool | Sequence[int] | Tensor = True,
    point_selection: bool | Sequence[int] | Tensor = True,
    pairs: Sequence[Sequence[int]] | Tensor | None = None,
    rank_tolerance: float | None = None,
    parameters: dict[str, Tensor] | None = None,
) -> MarginalCovariances:
    """:func:`marginal_covariances` of B problems given as tensors (as
    :func:`torchslam.solve_tensors` takes them): the solution ``pose_tangent`` (B, m, 6) and
    ``points`` (B, n, 3), the ``data``; ``point_selection`` selects the points' blocks;
    ``parameters`` the solution's parameter blocks {group: (B, q, d)}, for data that has
    them (the ``parameters`` of the solve's result)."""
    return _marginals(
        "marginal_covariances_tensors",
        pose_tangent,
        points,
        data,
        config,
        poses,
        point_selection,
        pairs,
        rank_tolerance,
        parameters,
    )


def _marginals(*args: object) -> MarginalCovariances:
    """The work of the two entry points, under the solve's thread policy (torchslam._threads:
    one thread for small problems, never the cores other work keeps busy)."""
    from torchslam._threads import threads_for

    with threads_for(args[3]):  # data
        return _marginals_work(*args)  # type: ignore[arg-type]


def _marginals_work(
    fn: str,
    pose_tangent: Tensor,
    points: Tensor,
    data: PointMapData,
    config: object,
    pose_selection: object,
    point_selection: object,
    pairs: object,
    rank_tolerance: object,
    parameters: object = None,
) -> MarginalCovariances:
    # The solve's own checks of the solution and data (names the argument and the function).
    config = check_solve_inputs(fn, pose_tangent, points, data, config)
    slots = pack_values(fn, data.parameters, parameters, pose_tangent)
    B, m, n = data.valid.shape[0], data.num_poses, data.num_points
    device = pose_tangent.device
    pose_index = _selection(fn, "poses", pose_selection, m, device)
    point_index = _selection(
        fn,
        "points" if fn == "marginal_covariances" else "point_selection",
        point_selection,
        n,
        device,
    )
    pair_index = _pair_selection(fn, pairs, m, device)
    tolerance = _rank_tolerance(fn, rank_tolerance, pose_tangent.dtype)
    with _checks.validation(False):
        lin = linearize(
            pose_tangent,
            points,
            data,
            whitening_factors(data),
            config.jacobian,
            config.linear_solver == "schur",
            None,
            slots,
        )
        plan = LinearPlan.build(data, config)
        wants_grad = torch.is_grad_enabled() and any(
            isinstance(t, Tensor) and t.requires_grad
            for t in (lin.pose_blocks, lin.pose_gradient, getattr(lin, "coupling", None))
        )
        if plan.sparse and wants_grad:
            raise ValueError(
                f"{fn}: the sparse reduced solver (SciPy) is not differentiable, and the "
                "inputs require gradients; use SolverConfig(reduced_solver='dense') for "
                "covariances differentiable with respect to the weights, or call under "
                "torch.no_grad()"
            )
        factorization = plan.factorize(lin, pose_tangent.new_zeros(B))
        selection = (pose_index, point_index, pair_index)
        inverses: dict = {}  # the sparse path's selected inverses, by problem
        if plan.method == "dense":
            out = _full(factorization, data, selection, tolerance)
        elif plan.sparse:
            out = _sparse(plan, factorization, lin, data, selection, tolerance, inverses)
        else:
            out = _dense(plan, factorization, lin, data, selection, tolerance)
    poses_cov, points_cov, pairs_cov, ok, reason, method = out
    # Fixed variables: zero; problems whose Hessian is singular: NaN.
    fixed_pose = data.fixed_poses[:, pose_index]
    poses_cov = torch.where(fixed_pose[..., None, None], 0.0, poses_cov)
    fixed_point = data.fixed_points[:, point_index]
    points_cov = torch.where(fixed_point[..., None, None], 0.0, points_cov)
    fixed_pair = data.fixed_poses[:, pair_index[:, 0]] | data.fixed_poses[:, pair_index[:, 1]]
    pairs_cov = torch.where(fixed_pair[..., None, None], 0.0, pairs_cov)
    bad = ~ok
    blocks = {}
    if data.parameters is not None and plan.sparse:
        blocks = _sparse_parameter_blocks(factorization, data, inverses, lin.pose_blocks)
    elif data.parameters is not None:
        blocks = _parameter_blocks(plan, factorization, data)
    blocks = {k: torch.where(bad[:, None, None, None], math.nan, v) for k, v in blocks.items()}
    poses_cov = torch.where(bad[:, None, None, None], math.nan, poses_cov)
    points_cov = torch.where(bad[:, None, None, None], math.nan, points_cov)
    pairs_cov = torch.where(bad[:, None, None, None], math.nan, pairs_cov)
    return MarginalCovariances(
        poses=poses_cov,
        points=points_cov,
        pairs=pairs_cov,
        pose_index=pose_index,
        point_index=point_index,
        pair_index=pair_index,
        ok=ok,
        reason=reason,
        method=method,
        parameters=blocks,
    )


def _parameter_blocks(plan: LinearPlan, factorization, data: PointMapData) -> dict[str, Tensor]:
    """Σ of every parameter block, {group: (B, q, d, d)}, from the inverse of the factored
    reduced (or full) system: the rows and columns of each block's d entries in its slots
    (:class:`~torchslam.objective.parameters.ParameterLayout`); zero for fixed blocks."""
    layout = data.parameters
    sigma = factorization.factor.inverse()
    out = {}
    device = sigma.device
    for g, name in enumerate(layout.names):
        q, d = layout.counts[g], layout.dims[g]
        slots = layout.slot_index(name, torch.arange(q, device=device))  # (q, spb)
        entries = (6 * slots[..., None] + torch.arange(6, device=device)).reshape(q, -1)[:, :d]
        block = sigma[:, entries[:, :, None], entries[:, None, :]]
        out[name] = torch.where(layout.fixed[g][..., None, None], 0.0, block)
    return out


def _sparse_parameter_blocks(
    factorization, data: PointMapData, inverses: dict, like: Tensor
) -> dict[str, Tensor]:
    """:func:`_parameter_blocks` for the sparse reduced solver: each block's slots' 6 × 6
    blocks of S⁻¹ from the selected inverse (the slots of one block are touched by the same
    terms, so they lie on the factor's pattern; any that does not is solved for), then the
    block's d entries. Problems without a selected inverse (not ok) get zeros (NaN later)."""
    layout = data.parameters
    factor: SparseFactor = factorization.factor
    B = len(factor.factors)
    out = {}
    for g, name in enumerate(layout.names):
        q, d, per = layout.counts[g], layout.dims[g], layout.slots_per_block(g)
        slots = layout.slot_index(name, torch.arange(q)).cpu().numpy()  # (q, per), from 0
        rows = np.repeat(slots, per, axis=1).reshape(-1)  # (q·per·per,) slot i of (i, j)
        cols = np.tile(slots, (1, per)).reshape(-1)
        values = np.zeros((B, q, 6 * per, 6 * per))
        for b, inverse in inverses.items():
            order = factor.block_order(b)
            blocks, found = inverse.lookup(order[rows], order[cols])
            missing = np.flatnonzero(~found)
            if missing.size:  # off the pattern: block columns of S⁻¹ by solves
                columns = np.unique(cols[missing])
                size = 6 * len(order)
                rhs = np.zeros((size, 6 * columns.size))
                for c, k in enumerate(columns):
                    rhs[6 * k : 6 * k + 6, 6 * c : 6 * c + 6] = np.eye(6)
                X = factor.solve_columns(b, rhs).reshape(len(order), 6, columns.size, 6)
                where = np.searchsorted(columns, cols[missing])
                blocks[missing] = X[rows[missing], :, where, :]
            full = blocks.reshape(q, per, per, 6, 6).transpose(0, 1, 3, 2, 4)
            values[b] = full.reshape(q, 6 * per, 6 * per)
        block = torch.from_numpy(values[:, :, :d, :d]).to(like)
        out[name] = torch.where(layout.fixed[g][..., None, None], 0.0, block)
    return out


# ------------------------------------------------------------------------------------------
# Rank checks


def _describe_unknown(k: int, m: int) -> str:
    """The variable of unknown k of the (poses, points) ordering."""
    if k < 6 * m:
        return f"pose {k // 6}"
    return f"point {(k - 6 * m) // 3}"


def _singular_reason(where: str, ratio: float, tolerance: float) -> str:
    return (
        f"rank deficient: the Gauss-Newton Hessian is singular to working precision at {where} "
        f"(pivot ratio {ratio:.1e} ≤ rank_tolerance {tolerance:g}): the data do not determine "
        "every free variable (a free gauge: fix a pose; or a variable without enough "
        "observations)"
    )


_FAILED = (
    "rank deficient: the Gauss-Newton Hessian is not positive definite (its factorization "
    "failed): the data do not determine every free variable (a free gauge: fix a pose; or a "
    "variable without enough observations)"
)


def _cholesky_ratios(L: Tensor) -> Tensor:
    """Pivot ratios L_kk² / A_kk of a Cholesky factor L (B, N, N) of A, (B, N)."""
    d = torch.diagonal(L, dim1=-2, dim2=-1).square()
    return d / L.square().sum(-1)


def _dense_status(
    factor_ok: Tensor, ratios: Tensor, tolerance: float, describe
) -> tuple[Tensor, list[str]]:
    """(ok (B,), reasons) from a factorization's ok flags and pivot ratios (B, N)."""
    ratios = ratios.detach()
    good = factor_ok & (ratios > tolerance).all(-1)  # NaN ratios fail
    reasons = []
    for b in range(ratios.shape[0]):
        if bool(good[b]):
            reasons.append("ok")
        elif not bool(factor_ok[b]):
            reasons.append(_FAILED)
        else:
            r = torch.nan_to_num(ratios[b], nan=-1.0)
            k = int(torch.argmin(r))
            reasons.append(_singular_reason(describe(k), float(ratios[b, k]), tolerance))
    return good, reasons


def _point_status(lin, data: PointMapData, tolerance: float) -> tuple[Tensor, list[str | None]]:
    """Free points whose block V_j is singular: (ok (B,), reason or None per problem)."""
    B, n = data.fixed_points.shape
    if n == 0:
        return data.fixed_points.new_ones(B), [None] * B
    if isinstance(lin, StructuredLinearization):
        # V_j = v_j I: its pivot ratios are 1 when v_j > 0 (0 when unobserved).
        v = lin.point_weight.detach()
        ratio = torch.where(v > 0, torch.ones_like(v), torch.zeros_like(v))
    else:
        V = lin.point_blocks.detach()
        L, info = torch.linalg.cholesky_ex(V)
        ratio = torch.where(
            (info == 0)[..., None], _cholesky_ratios(L), torch.zeros_like(V[..., 0])
        ).amin(-1)
    ratio = torch.where(data.fixed_points, torch.ones_like(ratio), ratio)
    good = (ratio > tolerance).all(-1)
    reasons: list[str | None] = []
    for b in range(ratio.shape[0]):
        if bool(good[b]):
            reasons.append(None)
        else:
            j = int(torch.argmin(torch.nan_to_num(ratio[b], nan=-1.0)))
            reasons.append(_singular_reason(f"point {j}", float(ratio[b, j]), tolerance))
    return good, reasons


def _combine(
    ok: Tensor, reasons: list[str], point_ok: Tensor, point_reasons: list[str | None]
) -> tuple[Tensor, list[str]]:
    merged = [p if p is not None else r for r, p in zip(reasons, point_reasons, strict=True)]
    return ok & point_ok, merged


# ------------------------------------------------------------------------------------------
# The elimination's blocks per edge


def _local_index(index: Tensor, count: int) -> Tensor:
    """Position of each of ``count`` items in the selection ``index``, −1 if not in it."""
    local = torch.full((count,), -1, dtype=torch.long, device=index.device)
    return local.index_put((index,), torch.arange(index.numel(), device=index.device))


# ------------------------------------------------------------------------------------------
# The three paths


def _describe_slot(k: int, data: PointMapData) -> str:
    """The variable of entry k of the reduced system: a pose, or a parameter block."""
    slot = k // 6
    if slot < data.num_poses or data.parameters is None:
        return f"pose {slot}"
    layout = data.parameters
    for g, name in enumerate(layout.names):
        per = layout.slots_per_block(g)
        start = data.num_poses + layout.offsets[g]
        if slot < start + layout.counts[g] * per:
            return f"parameter block {name}[{(slot - start) // per}]"
    return f"slot {slot}"


def _full(factorization, data: PointMapData, selection, tolerance: float):
    """The "dense" method: blocks of H⁻¹ from the Cholesky factor of the whole system."""
    pose_index, point_index, pair_index = selection
    B, m, n = factorization.shape
    L = factorization.factor.L
    ok, reasons = _dense_status(
        factorization.factor.ok, _cholesky_ratios(L), tolerance, lambda k: _describe_unknown(k, m)
    )
    inverse = torch.cholesky_inverse(L)
    pose_part = inverse[:, : 6 * m, : 6 * m].reshape(B, m, 6, m, 6).transpose(2, 3)
    point_part = inverse[:, 6 * m :, 6 * m :].reshape(B, n, 3, n, 3).transpose(2, 3)
    poses = pose_part[:, pose_index, pose_index]
    points = point_part[:, point_index, point_index]
    pairs = pose_part[:, pair_index[:, 0], pair_index[:, 1]]
    return poses, points, pairs, ok, reasons, "full"


def _dense(plan: LinearPlan, factorization, lin, data: PointMapData, selection, tolerance):
    """Dense reduced solver: S⁻¹ from its batched Cholesky factor; the points' blocks by
    Σ_XX = V⁻¹ + V⁻¹ (Wᵀ S⁻¹ W) V⁻¹ with W (6m × 3c) per chunk of c selected points."""
    pose_index, point_index, pair_index = selection
    B, m, n = factorization.shape
    factor = factorization.factor
    ok, reasons = _dense_status(
        factor.ok, factor.pivot_ratios(), tolerance, lambda k: _describe_slot(k, data)
    )
    point_ok, point_reasons = _point_status(lin, data, tolerance)
    ok, reasons = _combine(ok, reasons, point_ok, point_reasons)
    sigma = factor.inverse()  # (B, 6m, 6m)
    blocks = sigma.reshape(B, m, 6, m, 6).transpose(2, 3)
    poses = blocks[:, pose_index, pose_index]
    pairs = blocks[:, pair_index[:, 0], pair_index[:, 1]]
    Q = point_index.numel()
    points = sigma.new_zeros(B, Q, 3, 3)
    if Q:
        W, V_inv = factorization.elimination.blocks()
        elim = factorization.elimination
        local = _local_index(point_index, n)
        edge_local = local[elim.point_slot % n] if n else elim.point_slot
        chunk = max(1, min(Q, _CHUNK_ENTRIES // max(1, B * 18 * m)))
        parts = []
        for start in range(0, Q, chunk):
            c = min(chunk, Q - start)
            inside = (edge_local >= start) & (edge_local < start + c)
            slot = elim.pose_slot * c + (edge_local - start).clamp(0, c - 1)
            W_c = torch.where(inside[:, None, None], W, torch.zeros_like(W))
            buffer = W.new_zeros(B * m * c, 6, 3).index_add(0, slot, W_c)
            W_full = buffer.reshape(B, m, c, 6, 3).permute(0, 1, 3, 2, 4).reshape(B, 6 * m, 3 * c)
            # (S⁻¹ W)_(i, j) at each edge's own block: Σ_e∈j W_eᵀ (S⁻¹ W)_(i_e, j).
            Y = (sigma @ W_full).reshape(B, m, 6, c, 3).permute(0, 1, 3, 2, 4)
            C = W_c.transpose(-1, -2) @ Y.reshape(B * m * c, 6, 3)[slot]
            local_slot = elim.point_slot // n * c + (edge_local - start).clamp(0, c - 1)
            parts.append(W.new_zeros(B * c, 3, 3).index_add(0, local_slot, C).reshape(B, c, 3, 3))
        coupled = torch.cat(parts, dim=1)
        V_sel = V_inv[:, point_index]
        points = V_sel + V_sel @ coupled @ V_sel
    return poses, points, pairs, ok, reasons, "dense"


def _sparse(
    plan: LinearPlan, factorization, lin, data: PointMapData, selection, tolerance, inverses
):
    """Sparse reduced solver: the blocks of S⁻¹ on its factor's pattern (selected inverse),
    cross blocks outside it by block-column solves; points through the edge pairs that share
    them (their pose blocks are on the pattern). ``inverses`` (a dict) receives each ok
    problem's selected inverse (the parameter blocks read theirs from it)."""
    pose_index, point_index, pair_index = selection
    B, m, n = factorization.shape
    factor: SparseFactor = factorization.factor
    dtype, device = lin.pose_blocks.dtype, lin.pose_blocks.device
    point_ok, point_reasons = _point_status(lin, data, tolerance)
    pose_np = pose_index.cpu().numpy()
    pair_np = pair_index.cpu().numpy()
    P, R = pose_np.size, pair_np.shape[0]
    poses = np.zeros((B, P, 6, 6))
    pairs = np.zeros((B, R, 6, 6))
    Q = point_index.numel()
    need_points = Q > 0 and plan._pairs().num_pairs > 0
    if need_points:
        structure = plan._pairs()
        selected = torch.zeros(B * n, dtype=torch.bool, device=device)
        selected = selected.reshape(B, n).index_fill(1, point_index, True).reshape(-1)
        keep = selected[structure.point].nonzero().squeeze(1)
        key = structure.key[keep].cpu().numpy()
        pair_blocks = np.zeros((key.size, 6, 6))
        key_batch = key // (m * m)
    ok, reasons = [], []
    for b in range(B):
        if factor.factors[b] is None:
            ok.append(False)
            reasons.append(_FAILED)
            continue
        inverse, ratios = factor.selected_inverse(b)
        free = ~np.repeat(data.fixed_poses[b].cpu().numpy(), 6)
        if data.parameters is not None:  # the parameter slots: free blocks' own entries
            layout = data.parameters
            slot_free = ~layout.fixed_slots()[b].cpu().numpy()[:, None] & layout.active.numpy()
            free = np.concatenate((free, slot_free.reshape(-1)))
        r = np.where(free, ratios, 1.0)
        if not bool((r > tolerance).all()):  # NaN ratios fail
            k = int(np.argmin(np.nan_to_num(r, nan=-1.0)))
            ok.append(False)
            reasons.append(_singular_reason(_describe_slot(k, data), float(r[k]), tolerance))
            continue
        inverses[b] = inverse
        ok.append(True)
        reasons.append("ok")
        order = factor.block_order(b)
        poses[b] = inverse.lookup(order[pose_np], order[pose_np])[0]
        if R:
            blocks, found = inverse.lookup(order[pair_np[:, 0]], order[pair_np[:, 1]])
            missing = np.flatnonzero(~found)
            if missing.size:  # outside the pattern: block columns of S⁻¹ by solves
                columns = np.unique(pair_np[missing, 1])
                rhs = np.zeros((6 * m, 6 * columns.size))
                for c, k in enumerate(columns):
                    rhs[6 * k : 6 * k + 6, 6 * c : 6 * c + 6] = np.eye(6)
                X = factor.solve_columns(b, rhs).reshape(m, 6, columns.size, 6)
                where = np.searchsorted(columns, pair_np[missing, 1])
                blocks[missing] = X[pair_np[missing, 0], :, where, :]
            pairs[b] = blocks
        if need_points:
            mine = np.flatnonzero(key_batch == b)
            local = key[mine] % (m * m)
            pair_blocks[mine] = inverse.lookup(order[local // m], order[local % m])[0]
    ok_t = torch.tensor(ok, dtype=torch.bool, device=device)
    ok_t, reasons = _combine(ok_t, reasons, point_ok, point_reasons)
    as_tensor = lambda x: torch.from_numpy(x).to(device=device, dtype=dtype)  # noqa: E731
    points = torch.zeros(B, Q, 3, 3, dtype=dtype, device=device)
    if Q:
        W, V_inv = factorization.elimination.blocks()
        coupled = torch.zeros(B * n, 3, 3, dtype=dtype, device=device)
        if need_points:
            S = as_tensor(pair_blocks)
            first, second = structure.first[keep], structure.second[keep]
            C = W[first].transpose(-1, -2) @ S @ W[second]
            mirror = ~structure.self_pair[keep]
            C = torch.where(mirror[:, None, None], C + C.transpose(-1, -2), C)
            coupled = coupled.index_add(0, structure.point[keep], C)
        V_sel = V_inv[:, point_index]
        coupled = coupled.reshape(B, n, 3, 3)[:, point_index]
        points = V_sel + V_sel @ coupled @ V_sel
    return as_tensor(poses), points, as_tensor(pairs), ok_t, reasons, "sparse"


# ------------------------------------------------------------------------------------------
# From blocks to what a user reads


def _check_convention(fn: str, convention: object) -> str:
    if convention not in ("world_to_frame", "frame_to_world"):
        raise ValueError(
            f"{fn}: argument 'convention' must be 'world_to_frame' (T_i0 of a "
            "PointMapProblem) or 'frame_to_world' (pose-graph vertices), got "
            f"{_checks.describe(convention)}"
        )
    return convention


def position_covariance(
    covariance: Tensor, poses: Tensor, convention: str = "world_to_frame"
) -> Tensor:
    """The covariance of each frame's position in the world, (..., 3, 3), from its 6 × 6
    block (..., 6, 6) ((ω, v), right perturbation T·Exp(δ)) and its pose (..., 4, 4).

    - ``"world_to_frame"`` (T = T_i0, a :class:`PointMapProblem`'s poses): the frame's
      position c = −Rᵀt moves by δc = [c]× ω − v (T·Exp(δ) moves T⁻¹ by Exp(−δ) on the world
      side), so Σ_c = J Σ Jᵀ with J = [[c]×, −I];
    - ``"frame_to_world"`` (T = T_i, body → world, pose-graph vertices): δt = R v, so
      Σ_t = R Σ_vv Rᵀ.
    """
    fn = "position_covariance"
    _checks.check_tensor(fn, "covariance", covariance, (6, 6))
    _checks.check_tensor(fn, "poses", poses, (4, 4))
    _checks.check_same_kind(fn, covariance=covariance, poses=poses)
    convention = _check_convention(fn, convention)
    R, t = poses[..., :3, :3], poses[..., :3, 3]
    if convention == "frame_to_world":
        return R @ covariance[..., 3:, 3:] @ R.transpose(-1, -2)
    c = -(R.transpose(-1, -2) @ t[..., None])[..., 0]
    eye = torch.eye(3, dtype=poses.dtype, device=poses.device).expand(*c.shape[:-1], 3, 3)
    J = torch.cat((so3.hat(c), -eye), dim=-1)
    return J @ covariance @ J.transpose(-1, -2)


def pose_uncertainty(
    covariance: Tensor, poses: Tensor, convention: str = "world_to_frame"
) -> tuple[Tensor, Tensor]:
    """Per pose the 1-σ rotation uncertainty in degrees and the 1-σ uncertainty of the frame's
    position in the world (units of the poses), along the least certain axis: the square roots
    of the largest eigenvalues of the rotation block Σ_ωω and of
    :func:`position_covariance`. Shapes (..., 6, 6) and (..., 4, 4) → (...,), (...,).

    The rotation part needs no pose: T·Exp(δ) rotates the frame by |ω| either way.
    """
    position = position_covariance(covariance, poses, convention)
    rotation = covariance[..., :3, :3]
    sym = lambda A: 0.5 * (A + A.transpose(-1, -2))  # noqa: E731
    rot = torch.linalg.eigvalsh(sym(rotation))[..., -1].clamp_min(0).sqrt()
    trans = torch.linalg.eigvalsh(sym(position))[..., -1].clamp_min(0).sqrt()
    return torch.rad2deg(rot), trans
