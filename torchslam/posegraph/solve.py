"""Levenberg-Marquardt for pose graphs: between terms, pose priors, a fixed gauge, sparse solves.

Problem. Over the free vertex poses T_i (body i → world), minimize the standard cost

    F(T) = ½ Σ_(i,j) r_ijᵀ Ω_ij r_ij + ½ Σ_p r_pᵀ Ω_p r_p,
    r_ij = Log(Z_ij⁻¹ T_i⁻¹ T_j)   (between, :mod:`torchslam.posegraph.between`),
    r_p  = Log(Z_p⁻¹ T_(k_p))        (optional pose priors, :class:`PosePriors`),

with right perturbations T_i ← T_i·Exp(δ_i), ξ = (ω, v) rotation first, Ω in (ω, v) order.
The gauge: the vertices in ``fixed`` keep their poses (default: the file's ``FIX`` vertices,
or vertex 0 when it fixes none).

Normal equations. With the whitened blocks A = U J (UᵀU = Ω, :func:`between.sqrt_information`)
an edge adds A_iᵀA_i to the diagonal block (i, i), A_jᵀA_j to (j, j), A_iᵀA_j to (i, j) and its
transpose to (j, i), and A_iᵀ(U r), A_jᵀ(U r) to the gradient g; a prior adds to one diagonal
block. H (6n × 6n for n free vertices) thus has n diagonal blocks and one off-diagonal pair per
distinct pair of free vertices joined by an edge. All products are computed for every term at
once (stacked 6 × 6 matmuls); g is accumulated with ``index_add``.

Linear solve of (H + λD) δ = −g, D = diag(H) clamped to [1e-6, 1e32] (Marquardt, like Ceres and
:mod:`torchslam.solver`) or D = I (Levenberg):

- ``"sparse"``: once per solve, a fill-reducing ordering of the n × n vertex graph (multiple
  minimum degree on Aᵀ + A, from SuperLU) is expanded to the 6 × 6 blocks, the CSC layout of
  the permuted symmetric matrix P H Pᵀ is computed, and a sparse 0/1 "assembly" matrix that
  maps every entry of every product (and its mirror) to its place in the CSC data array. Each
  iteration is then one sparse mat-vec to fill the data array, λD on its diagonal entries and a
  SuperLU factorization (``scipy.sparse.linalg.splu``) in symmetric mode with diagonal pivots
  in that precomputed order: SuperLU exposes no reusable symbolic factorization, so the
  ordering is what is reused. No new dependency: SciPy has no sparse Cholesky, and LU with
  diagonal pivots of an SPD matrix is its LDLᵀ factorization (twice the flops of Cholesky).
- ``"dense"``: the 6n × 6n matrix (blocks accumulated with ``index_put_``) and
  ``torch.linalg.cholesky_ex``: small graphs, any device, and the reference for the tests.
- ``"auto"``: dense when 6n ≤ ``dense_max_variables``, sparse otherwise.

Levenberg-Marquardt as :mod:`torchslam.solver.solve`: gain ratio ϱ = (F(T) − F(T ⊞ δ)) /
(L(0) − L(δ)) with the exact model decrease L(0) − L(δ) = −(gᵀδ + ½ Σ_terms ‖A δ‖²); Nielsen's
update (accepted, ϱ > 0: λ ← λ·max(⅓, 1 − (2ϱ − 1)³), ν ← 2; rejected: λ ← λν, ν ← 2ν);
Ceres-like stopping with the statuses of :class:`torchslam.solver.result.Status`.

Performance (sphere2500, 2500 poses, 4949 edges, float64, one CPU thread): ~35 ms per
linearization (mostly :func:`between.between_jacobians`) and ~100 ms per SuperLU factorization;
7 iterations from the odometry guess. On a CPU shared with other processes keep torch at one
thread (``torch.set_num_threads(1)``): the per-edge tensors are too small to gain from more,
and a busy-waiting second OpenMP thread made the linearization up to 25× slower in our runs.

The solve is not differentiable (it runs under ``torch.no_grad`` and the sparse path goes
through SciPy on the CPU); the dense path keeps the tensors' device.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch
from torch import Tensor

from torchslam import _checks
from torchslam.lie import se3
from torchslam.posegraph import between
from torchslam.posegraph.graph import PoseGraph, check_information, check_vertex_indices
from torchslam.solver.config import check_int, check_number
from torchslam.solver.result import REASONS, Status
from torchslam.solver.sparse import fill_reducing_order

__all__ = [
    "IterationInfo",
    "PoseGraphSolveResult",
    "PoseGraphSolverConfig",
    "PosePriors",
    "solve_pose_graph",
]

logger = logging.getLogger("torchslam.posegraph")

IterationInfo = dict
"""Per-iteration progress passed to ``callback`` (the keys of :data:`torchslam.solver.solve.
IterationInfo`, as Python scalars): iteration (int), cost (float, after the iteration),
lambda (float), step_norm (float, ‖δ‖ of the tried step), accepted (bool), gradient_norm
(float, max |g| at the current estimate), seconds (float since the start)."""

_DAMPINGS = ("marquardt", "levenberg")
_JACOBIANS = ("analytic", "jacrev")
_LINEAR_SOLVERS = ("auto", "sparse", "dense")
_ORDERINGS = ("mmd", "colamd", "natural")


@dataclass(frozen=True)
class PoseGraphSolverConfig:
    """Options of :func:`solve_pose_graph`. Defaults suit float64 pose graphs.

    Tolerances follow Ceres: the solve stops when an accepted step decreases the cost by less
    than ``function_tolerance`` relative to the cost (or the model predicts less than that),
    when the largest gradient entry falls below ``gradient_tolerance``, or when the step is
    shorter than ``parameter_tolerance`` · (‖x‖ + ``parameter_tolerance``), ‖x‖ the Frobenius
    norm of the free poses' top 3 × 4 rows.
    """

    # Maximum number of iterations (linear solves, accepted or not).
    max_iterations: int = 100
    # Stop when |ΔF| ≤ function_tolerance · F after an accepted step.
    function_tolerance: float = 1e-10
    # Stop when max |∇F| ≤ gradient_tolerance.
    gradient_tolerance: float = 1e-10
    # Stop when ‖δ‖ ≤ parameter_tolerance · (‖x‖ + parameter_tolerance).
    parameter_tolerance: float = 1e-12
    # Initial damping λ₀. Tiny: pose graphs (gauge fixed) are well posed, so Gauss-Newton
    # steps are taken from the start and rejections raise λ; with Nielsen's update λ falls at
    # most 3× per iteration, so Ceres' 1e-4 costs sphere2500/garage 2-9 extra iterations.
    initial_lambda: float = 1e-9
    # λ above which the solve gives up (no step decreases the cost): DAMPING_LIMIT.
    max_lambda: float = 1e16
    # λ never goes below this.
    min_lambda: float = 1e-16
    # Damping matrix: "marquardt" λ·diag(H) (scale invariant) or "levenberg" λ·I.
    damping: Literal["marquardt", "levenberg"] = "marquardt"
    # Jacobian blocks: "analytic" (between.between_jacobians) or "jacrev" (torch.func).
    jacobian: Literal["analytic", "jacrev"] = "analytic"
    # Linear solver: "auto" (dense up to dense_max_variables), "sparse" or "dense".
    linear_solver: Literal["auto", "sparse", "dense"] = "auto"
    # Largest system size 6n solved densely by "auto".
    dense_max_variables: int = 1200
    # Fill-reducing ordering of the vertex graph for "sparse": "mmd", "colamd" or "natural".
    ordering: Literal["mmd", "colamd", "natural"] = "mmd"

    def __post_init__(self) -> None:
        fn = "PoseGraphSolverConfig"
        for name, allowed in (
            ("damping", _DAMPINGS),
            ("jacobian", _JACOBIANS),
            ("linear_solver", _LINEAR_SOLVERS),
            ("ordering", _ORDERINGS),
        ):
            value = getattr(self, name)
            if not isinstance(value, str) or value not in allowed:
                raise ValueError(
                    f"{fn}: '{name}' must be one of {allowed}, got {_checks.describe(value)}"
                )
        for name in ("max_iterations", "dense_max_variables"):
            object.__setattr__(self, name, check_int(fn, name, getattr(self, name), 0))
        # Every real option is a finite number ≥ 0 (an infinite λ or tolerance stops nothing
        # or everything at once).
        for name in (
            "function_tolerance",
            "gradient_tolerance",
            "parameter_tolerance",
            "initial_lambda",
            "max_lambda",
            "min_lambda",
        ):
            object.__setattr__(self, name, check_number(fn, name, getattr(self, name), 0.0, True))
        if self.min_lambda > self.max_lambda:
            raise ValueError(
                f"{fn}: 'min_lambda' ({self.min_lambda!r}) must not exceed 'max_lambda' "
                f"({self.max_lambda!r})"
            )
        if self.initial_lambda > self.max_lambda:
            raise ValueError(
                f"{fn}: 'initial_lambda' ({self.initial_lambda!r}) must not exceed 'max_lambda' "
                f"({self.max_lambda!r})"
            )


@dataclass(frozen=True)
class PosePriors:
    """Pose priors r_p = Log(Z_p⁻¹ T_(k_p)) with information Ω_p, ξ = (ω, v) order."""

    # Vertex indices k_p (into graph.poses, not ids), shape (P,), int64.
    indices: Tensor
    # Prior poses Z_p (body → world), shape (P, 4, 4).
    poses: Tensor
    # Information matrices Ω_p in (ω, v) order, symmetric positive definite, shape (P, 6, 6).
    information: Tensor

    def __post_init__(self) -> None:
        fn = "PosePriors"
        _checks.check_tensor(fn, "poses", self.poses, (4, 4), min_batch_dims=1, dims="K")
        _checks.check_tensor(
            fn, "information", self.information, (6, 6), min_batch_dims=1, dims="K"
        )
        _checks.check_tensor(fn, "indices", self.indices, floating=False)
        _checks.check_same_kind(fn, poses=self.poses, information=self.information)
        if self.indices.dtype != torch.int64:
            raise TypeError(f"{fn}: argument 'indices' must be int64, got {self.indices.dtype}")
        count = self.indices.shape[0] if self.indices.dim() == 1 else -1
        if (
            self.poses.dim() != 3
            or self.information.dim() != 3
            or count < 0
            or self.poses.shape[0] != count
            or self.information.shape[0] != count
        ):
            raise ValueError(
                f"{fn}: 'indices', 'poses' and 'information' must have shapes (P,), "
                f"(P, 4, 4), (P, 6, 6); got {tuple(self.indices.shape)}, "
                f"{tuple(self.poses.shape)}, {tuple(self.information.shape)}"
            )
        check_information(fn, "information", self.information, "prior")
        _checks.check_pose_matrix(fn, "poses", self.poses)
        if _checks.value_checks_active() and self.indices.numel():
            negative = self.indices < 0
            if bool(negative.any()):
                p = int(negative.nonzero()[0, 0])
                raise ValueError(
                    f"{fn}: argument 'indices' must hold vertex indices ≥ 0 (positions in the "
                    f"graph's poses), got indices[{p}] = {int(self.indices[p])}"
                )

    @property
    def num_priors(self) -> int:
        """Number of priors P."""
        return self.indices.shape[0]


@dataclass
class PoseGraphSolveResult:
    """Outcome of :func:`solve_pose_graph` (one graph)."""

    # Optimized poses T_i (body i → world), (N, 4, 4); fixed vertices unchanged.
    poses: Tensor
    # Why the solve stopped (the statuses of torchslam.solver).
    status: Status
    # Iterations (linear solves, accepted or rejected).
    iterations: int
    # Cost ½ Σ rᵀΩr at the start and at the end.
    initial_cost: float
    final_cost: float
    # Cost after each iteration, (K + 1,), float64 on the CPU; entry 0 is the initial cost.
    cost_history: Tensor
    # Damping λ after each iteration, (K + 1,); entry 0 is the initial λ.
    lambda_history: Tensor
    # Norm ‖δ‖ of the step tried in each iteration, (K,).
    step_norm_history: Tensor
    # Max |gradient| at the final estimate.
    gradient_norm: float
    # The linear solver used: "sparse" or "dense".
    linear_solver: str
    # Wall-clock seconds of the whole solve, and of its parts: linearization (residuals,
    # Jacobians, block products, assembly) and linear solves (factorization and solve).
    time_seconds: float
    linearize_seconds: float
    linear_solve_seconds: float

    @property
    def reason(self) -> str:
        """A sentence saying why the solve stopped."""
        return REASONS[self.status]

    @property
    def converged(self) -> bool:
        return self.status.converged

    def summary(self) -> str:
        return (
            f"{self.status.name} after {self.iterations} iterations, cost "
            f"{self.initial_cost:.6g} -> {self.final_cost:.6g} in {self.time_seconds:.3f} s "
            f"({self.linear_solver} solver; {self.reason})"
        )


# --------------------------------------------------------------------------------------------
# Structure: which variable each term touches (built once per solve).


def _matmul(a: Tensor, b: Tensor) -> Tensor:
    """a @ b for stacks of small matrices (..., k, l) @ (..., l, m).

    On the CPU this goes through NumPy's stacked matmul, several times faster than torch's
    batched matmul for 6 × 6 blocks (torch 2.13: ~0.7 ms vs ~4.5 ms for 6,000 products);
    elsewhere it is ``a @ b``. Used only on detached tensors (the solve is not differentiable).
    """
    if a.device.type == "cpu" and b.device.type == "cpu":
        return torch.from_numpy(np.matmul(a.numpy(), b.numpy()))
    return a @ b


@dataclass
class _Structure:
    """Index maps of one solve (int64 tensors on the graph's device unless noted)."""

    num_free: int
    # Vertex index of each free variable, (n,).
    free: Tensor
    # Variables of the edges' endpoints (E,) and of the priors (P,), −1 where fixed.
    first: Tensor
    second: Tensor
    prior: Tensor
    # Gradient rows: sources in cat(A_iᵀUr (E), A_jᵀUr (E), A_pᵀUr (P)) → target variables.
    gradient_source: Tensor
    gradient_target: Tensor


def _build_structure(
    edges: Tensor, prior_indices: Tensor, fixed: Tensor, num_vertices: int
) -> _Structure:
    device = edges.device
    is_free = torch.ones(num_vertices, dtype=torch.bool, device=device)
    is_free[fixed] = False
    free = is_free.nonzero().squeeze(1)
    n = free.numel()
    variable = torch.full((num_vertices,), -1, dtype=torch.int64, device=device)
    variable[free] = torch.arange(n, device=device)
    first, second, prior = variable[edges[:, 0]], variable[edges[:, 1]], variable[prior_indices]
    targets = torch.cat((first, second, prior))
    keep = targets >= 0
    return _Structure(
        num_free=n,
        free=free,
        first=first,
        second=second,
        prior=prior,
        gradient_source=keep.nonzero().squeeze(1),
        gradient_target=targets[keep],
    )


# --------------------------------------------------------------------------------------------
# Linearization: residuals, whitened Jacobian blocks, gradient and Hessian products.


@dataclass
class _Linearization:
    # Cost ½ Σ ‖U r‖².
    cost: float
    # Whitened Jacobian blocks A = U J of the first endpoint of the edges and of the priors
    # (E + P, 6, 6), and of the second endpoint of the edges (E, 6, 6).
    first: Tensor
    second: Tensor
    # Gradient g = Jᵀ Ω r per free variable, (n, 6).
    gradient: Tensor
    # Hessian products cat(A_iᵀA_i (E), A_jᵀA_j (E), A_iᵀA_j (E), A_pᵀA_p (P)), (3E + P, 6, 6).
    products: Tensor


def _residuals_and_jacobians(
    T: Tensor, graph: PoseGraph, priors: PosePriors | None, jacobian: str
) -> tuple[Tensor, Tensor, Tensor]:
    """Residuals (E + P, 6), J of the first pose (E + P, 6, 6) and of the second (E, 6, 6)."""
    T_i, T_j = T[graph.edges[:, 0]], T[graph.edges[:, 1]]
    if jacobian == "analytic":
        r, J_i, J_j = between.between_jacobians(T_i, T_j, graph.measurements)
    else:
        r = between.between_residual(T_i, T_j, graph.measurements)
        J_i, J_j = between.between_jacobians_jacrev(T_i, T_j, graph.measurements)
    if priors is not None:
        T_p = T[priors.indices]
        if jacobian == "analytic":
            r_p, J_p = between.prior_jacobian(T_p, priors.poses)
        else:
            r_p = between.prior_residual(T_p, priors.poses)
            J_p = between.prior_jacobian_jacrev(T_p, priors.poses)
        r, J_i = torch.cat((r, r_p)), torch.cat((J_i, J_p))
    return r, J_i, J_j


def _linearize(
    T: Tensor,
    graph: PoseGraph,
    priors: PosePriors | None,
    U: Tensor,
    structure: _Structure,
    jacobian: str,
) -> _Linearization:
    E = graph.num_edges
    r, J_first, J_second = _residuals_and_jacobians(T, graph, priors, jacobian)
    wr = _matmul(U, r[..., None])  # (E + P, 6, 1)
    A_first = _matmul(U, J_first)
    A_second = _matmul(U[:E], J_second)
    A_first_t, A_second_t = A_first.transpose(-1, -2), A_second.transpose(-1, -2)
    g_terms = torch.cat((_matmul(A_first_t[:E], wr[:E]), _matmul(A_second_t, wr[:E])))
    if priors is not None:
        g_terms = torch.cat((g_terms, _matmul(A_first_t[E:], wr[E:])))
    gradient = wr.new_zeros(structure.num_free, 6).index_add_(
        0, structure.gradient_target, g_terms.squeeze(-1)[structure.gradient_source]
    )
    products = torch.cat(
        (
            _matmul(A_first_t[:E], A_first[:E]),
            _matmul(A_second_t, A_second),
            _matmul(A_first_t[:E], A_second),
            _matmul(A_first_t[E:], A_first[E:]),
        )
    )
    cost = 0.5 * float(wr.square().sum())
    return _Linearization(cost, A_first, A_second, gradient, products)


def _model_decrease(
    lin: _Linearization,
    delta: Tensor,
    delta_vertex: Tensor,
    graph: PoseGraph,
    priors: PosePriors | None,
) -> float:
    """L(0) − L(δ) = −(gᵀδ + ½ Σ ‖A δ‖²): δ per variable (n, 6) and per vertex (N, 6)."""
    E = graph.num_edges
    d_first = delta_vertex[graph.edges[:, 0]]
    if priors is not None:
        d_first = torch.cat((d_first, delta_vertex[priors.indices]))
    Ad = _matmul(lin.first, d_first[..., None])
    Ad[:E] += _matmul(lin.second, delta_vertex[graph.edges[:, 1]][..., None])
    return -(float((lin.gradient * delta).sum()) + 0.5 * float(Ad.square().sum()))


# --------------------------------------------------------------------------------------------
# Linear solves.


def _damping_diagonal(diagonal: np.ndarray | Tensor, damping: str) -> np.ndarray | Tensor:
    """D of the damped system: diag(H) clamped to [1e-6, 1e32] (as torchslam.solver.linear)
    for Marquardt, ones for Levenberg; NumPy or torch like ``diagonal``."""
    if damping == "levenberg":
        ones = torch.ones_like if isinstance(diagonal, Tensor) else np.ones_like
        return ones(diagonal)
    return diagonal.clip(1e-6, 1e32)


@dataclass
class _SparseLayout:
    """CSC layout of the permuted symmetric matrix P H Pᵀ, built once per solve."""

    # CSC arrays of the permuted 6n × 6n matrix.
    indices: np.ndarray
    indptr: np.ndarray
    # data = assembly @ products.ravel(): sums (and mirrors) the Hessian products into the
    # CSC data array in one sparse product, (nnz, 36 (3E + P)).
    assembly: scipy.sparse.csc_matrix
    # Positions in data of the diagonal entries.
    diagonal: np.ndarray
    # New (permuted) index of each original unknown 6·v + a, (6n,).
    position: np.ndarray


def _build_sparse_layout(structure: _Structure, ordering: str) -> _SparseLayout:
    """CSC layout of P H Pᵀ and the assembly map, in O(E) vectorized steps (no big sorts).

    The matrix is block sparse: block column c (in permuted numbering) holds the blocks of the
    sorted block rows R_c, so its scalar column 6c + b lists rows 6r + a for r ∈ R_c, a = 0..5.
    Entry (a, b) of the q-th block (block-CSC order, column c) is therefore at data position
    36·ptr[c] + 6·|R_c|·b + 6·(q − ptr[c]) + a.
    """
    n = structure.num_free
    first = structure.first.cpu().numpy()
    second = structure.second.cpu().numpy()
    prior = structure.prior.cpu().numpy()
    E, P = first.shape[0], prior.shape[0]
    position = fill_reducing_order(n, first, second, ordering)
    a = np.arange(6)

    # Block pattern (diagonal + both orientations of every edge between free vertices).
    both = (first >= 0) & (second >= 0)
    p_first, p_second = position[first[both]], position[second[both]]
    block_rows = np.concatenate((position, p_first, p_second))
    block_cols = np.concatenate((position, p_second, p_first))
    keys = np.unique(block_cols * n + block_rows)  # sorted by column, then row
    block_col, block_row = keys // n, keys % n
    ptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(block_col, minlength=n), out=ptr[1:])
    count = np.diff(ptr)

    def entry_positions(q: np.ndarray) -> np.ndarray:
        """Data positions (M, 6, 6) of entries (a, b) of the blocks q (M,)."""
        c = block_col[q]
        base = 36 * ptr[c] + 6 * (q - ptr[c])
        return (base[:, None, None] + 6 * count[c][:, None, None] * a[None, None, :]) + a[
            None, :, None
        ]

    def block_of(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        return np.searchsorted(keys, position[cols] * n + position[rows])

    nnz = 36 * keys.shape[0]
    all_blocks = np.arange(keys.shape[0])
    indices = np.empty(nnz, dtype=np.int64)
    indices[entry_positions(all_blocks).ravel()] = np.broadcast_to(
        (6 * block_row[:, None, None] + a[None, :, None]), (keys.shape[0], 6, 6)
    ).ravel()
    indptr = np.append((36 * ptr[:-1, None] + 6 * count[:, None] * a[None, :]).ravel(), nnz)
    diagonal_blocks = block_of(np.arange(n), np.arange(n))
    diagonal = entry_positions(diagonal_blocks)[:, a, a].ravel()

    # Assembly: source entry 36·k + 6a + b of the products (3E + P, 6, 6) goes to a "direct"
    # data position, and the A_iᵀA_j entries also to the mirrored one (entry (b, a) of (j, i)).
    direct = np.full((3 * E + P, 6, 6), -1, dtype=np.int64)
    mirror = np.full((E, 6, 6), -1, dtype=np.int64)
    edge = np.arange(E)
    for offset, rows, cols, valid in (
        (0, first, first, first >= 0),
        (E, second, second, second >= 0),
        (2 * E, first, second, both),
    ):
        direct[offset + edge[valid]] = entry_positions(block_of(rows[valid], cols[valid]))
    mirror[both] = entry_positions(block_of(second[both], first[both])).transpose(0, 2, 1)
    valid = prior >= 0
    direct[3 * E + np.arange(P)[valid]] = entry_positions(block_of(prior[valid], prior[valid]))
    targets = np.stack(
        (
            direct.reshape(-1),
            np.concatenate(
                (-np.ones(72 * E, np.int64), mirror.reshape(-1), -np.ones(36 * P, np.int64))
            ),
        ),
        axis=1,
    )
    counts = (targets >= 0).sum(1)
    targets = targets[targets >= 0]
    assembly = scipy.sparse.csc_matrix(
        (np.ones(targets.shape[0]), targets, np.append(0, np.cumsum(counts))),
        shape=(nnz, direct.size),
    )
    return _SparseLayout(
        indices=indices.astype(np.int32),
        indptr=indptr.astype(np.int32),
        assembly=assembly,
        diagonal=diagonal,
        position=(6 * position[:, None] + a).ravel(),
    )


def _solve_sparse(
    lin: _Linearization, layout: _SparseLayout, lam: float, damping: str
) -> Tensor | None:
    """δ (n, 6) from SuperLU, or None when the factorization fails."""
    data = layout.assembly @ lin.products.cpu().numpy().reshape(-1)
    diagonal = data[layout.diagonal]
    data[layout.diagonal] = diagonal + lam * _damping_diagonal(diagonal, damping)
    size = layout.indptr.shape[0] - 1
    matrix = scipy.sparse.csc_matrix((data, layout.indices, layout.indptr), shape=(size, size))
    rhs = np.empty(size, dtype=data.dtype)
    rhs[layout.position] = -lin.gradient.cpu().numpy().reshape(-1)
    try:
        lu = scipy.sparse.linalg.splu(
            matrix,
            permc_spec="NATURAL",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )
        x = lu.solve(rhs)
    except RuntimeError:  # SuperLU: "Factor is exactly singular"
        return None
    if not np.isfinite(x).all():
        return None
    return torch.from_numpy(x[layout.position]).to(lin.gradient).reshape(-1, 6)


def _dense_matrix(lin: _Linearization, structure: _Structure, num_edges: int) -> Tensor:
    """H (6n, 6n) from the products, accumulated block by block."""
    n, E = structure.num_free, num_edges
    H = lin.products.new_zeros(n, n, 6, 6)
    H_ii, H_jj, H_ij, H_pp = lin.products.split((E, E, E, lin.products.shape[0] - 3 * E))
    i, j, p = structure.first, structure.second, structure.prior
    for rows, cols, blocks in (
        (i, i, H_ii),
        (j, j, H_jj),
        (i, j, H_ij),
        (j, i, H_ij.transpose(-1, -2)),
        (p, p, H_pp),
    ):
        keep = (rows >= 0) & (cols >= 0)
        H.index_put_((rows[keep], cols[keep]), blocks[keep], accumulate=True)
    return H.transpose(1, 2).reshape(6 * n, 6 * n)


def _solve_dense(
    lin: _Linearization, structure: _Structure, num_edges: int, lam: float, damping: str
) -> Tensor | None:
    """δ (n, 6) from a dense Cholesky factorization, or None when it fails."""
    H = _dense_matrix(lin, structure, num_edges)
    H = H + torch.diag(lam * _damping_diagonal(H.diagonal(), damping))
    L, info = torch.linalg.cholesky_ex(H)
    if int(info) != 0:
        return None
    x = torch.cholesky_solve(-lin.gradient.reshape(-1, 1), L).squeeze(-1)
    if not bool(torch.isfinite(x).all()):
        return None
    return x.reshape(-1, 6)


# --------------------------------------------------------------------------------------------
# The Levenberg-Marquardt loop.


def _nielsen(
    lam: float, nu: float, gain: float, accepted: bool, config: PoseGraphSolverConfig
) -> tuple[float, float]:
    """Nielsen's damping update (same rule as :mod:`torchslam.solver.solve`)."""
    if accepted:
        factor = max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
        return max(lam * factor, config.min_lambda), 2.0
    return lam * nu, 2.0 * nu


def _check_inputs(
    graph: PoseGraph,
    poses: Tensor,
    priors: PosePriors | None,
    fixed: Tensor,
    config: PoseGraphSolverConfig,
    callback: object,
) -> None:
    fn = "solve_pose_graph"
    if not isinstance(config, PoseGraphSolverConfig):
        raise TypeError(
            f"{fn}: argument 'config' must be a PoseGraphSolverConfig or None, got "
            f"{_checks.describe(config)}"
        )
    if callback is not None and not callable(callback):
        raise TypeError(
            f"{fn}: argument 'callback' must be callable (called with an IterationInfo dict "
            f"after every iteration) or None, got {_checks.describe(callback)}"
        )
    N = graph.num_vertices
    _checks.check_tensor(fn, "poses", poses, (N, 4, 4), min_batch_dims=0)
    if poses.dim() != 3:
        raise ValueError(
            f"{fn}: argument 'poses' must have shape ({N}, 4, 4), got {tuple(poses.shape)}"
        )
    _checks.check_same_kind(fn, poses=poses, measurements=graph.measurements)
    _checks.check_pose_matrix(fn, "poses", poses)
    _checks.check_tensor(fn, "fixed", fixed, floating=False)
    if fixed.dtype != torch.int64:
        raise TypeError(f"{fn}: argument 'fixed' must be an int64 tensor, got {fixed.dtype}")
    if fixed.dim() != 1:
        raise ValueError(f"{fn}: argument 'fixed' must have shape (F,), got {tuple(fixed.shape)}")
    # The graph checked its edges when it was built, unless validation was off then.
    check_vertex_indices(fn, "graph.edges", graph.edges, N)
    indices = [("fixed", fixed)]
    if priors is not None:
        if not isinstance(priors, PosePriors):
            raise TypeError(
                f"{fn}: argument 'priors' must be PosePriors or None, got {type(priors).__name__}"
            )
        _checks.check_same_kind(fn, poses=poses, priors=priors.poses)
        _checks.check_pose_matrix(fn, "priors.poses", priors.poses)
        indices.append(("priors.indices", priors.indices))
    for name, index in indices:
        if index.numel() and (int(index.min()) < 0 or int(index.max()) >= N):
            raise ValueError(
                f"{fn}: '{name}' must hold vertex indices in [0, {N}), got values in "
                f"[{int(index.min())}, {int(index.max())}]"
            )
    if fixed.numel() == 0 and (priors is None or priors.num_priors == 0):
        raise ValueError(
            f"{fn}: the gauge is free: no vertex is fixed and there are no priors; fix a "
            "vertex (argument 'fixed') or add a PosePriors"
        )


def _sqrt_information(graph: PoseGraph, priors: PosePriors | None) -> Tensor:
    """U with UᵀU = Ω for the edges and then the priors, (E + P, 6, 6); ValueError naming the
    first edge or prior whose information is not positive definite (when validation is on)."""
    information = graph.information.detach()
    if priors is not None:
        information = torch.cat((information, priors.information.detach()))
    L, info = torch.linalg.cholesky_ex(information)
    if _checks.value_checks_active() and information.numel() > 0 and bool((info > 0).any()):
        k = int((info > 0).nonzero()[0, 0])
        where = (
            f"'graph.information' of edge {k}"
            if k < graph.num_edges
            else f"'priors.information' of prior {k - graph.num_edges}"
        )
        raise ValueError(
            f"solve_pose_graph: the information matrices must be symmetric positive definite "
            f"(Cholesky factorization); {where} is not (a singular or indefinite matrix)"
        )
    return L.transpose(-1, -2)


def solve_pose_graph(
    graph: PoseGraph,
    poses: Tensor | None = None,
    *,
    config: PoseGraphSolverConfig | None = None,
    priors: PosePriors | None = None,
    fixed: Tensor | None = None,
    callback: Callable[[IterationInfo], None] | None = None,
) -> PoseGraphSolveResult:
    """Minimize ½ Σ rᵀΩr over the free vertex poses by Levenberg-Marquardt (module docstring).

    Conventions: T_i maps body-i points into the world; r_ij = Log(Z_ij⁻¹ T_i⁻¹ T_j) and
    r_p = Log(Z_p⁻¹ T_k), ξ = (ω, v) rotation first, Ω in (ω, v) order; the retraction is
    T ← T·Exp(δ).

    Args:
        graph: the pose graph (edges, measurements Z_ij ≈ T_i⁻¹ T_j, information (E, 6, 6)).
        poses: initial poses, shape (N, 4, 4); ``graph.poses`` (the file's vertices) when None.
        config: solver options; default :class:`PoseGraphSolverConfig()`.
        priors: optional pose priors (:class:`PosePriors`).
        fixed: indices (F,) int64 of vertices held at their initial poses (the gauge); when
            None, ``graph.fixed`` if the graph has any, else vertex 0. An empty tensor fixes
            nothing (then the priors must fix the gauge).
        callback: called after every iteration with an :data:`IterationInfo` dict.

    Returns:
        A :class:`PoseGraphSolveResult` (poses, status and reason, costs, histories, times).

    Raises:
        ValueError, TypeError: for inconsistent shapes, dtypes, indices, non-positive-definite
            information, or a free gauge. Non-convergence is reported by ``status``.
    """
    if not isinstance(graph, PoseGraph):
        raise TypeError(
            f"solve_pose_graph: argument 'graph' must be a PoseGraph, got {_checks.describe(graph)}"
        )
    config = PoseGraphSolverConfig() if config is None else config
    poses = graph.poses if poses is None else poses
    if fixed is None:
        fixed = graph.fixed if graph.fixed.numel() else graph.edges.new_zeros(1)
    _check_inputs(graph, poses, priors, fixed, config, callback)
    start = time.perf_counter()
    linearize_seconds = solve_seconds = 0.0
    with torch.no_grad():
        U = _sqrt_information(graph, priors)  # raises on a non-SPD matrix
    with torch.no_grad(), _checks.validation(False):
        T = poses.detach().clone()
        N = graph.num_vertices
        prior_indices = priors.indices if priors is not None else graph.edges.new_zeros(0)
        structure = _build_structure(graph.edges, prior_indices, fixed, N)
        n = structure.num_free
        linear_solver = config.linear_solver
        if linear_solver == "auto":
            linear_solver = "dense" if 6 * n <= config.dense_max_variables else "sparse"
        layout = None
        if linear_solver == "sparse" and n > 0:
            layout = _build_sparse_layout(structure, config.ordering)

        tick = time.perf_counter()
        lin = _linearize(T, graph, priors, U, structure, config.jacobian)
        cost = lin.cost
        linearize_seconds += time.perf_counter() - tick
        initial_cost = cost
        lam, nu = config.initial_lambda, 2.0
        costs, lambdas, steps = [cost], [lam], []

        def gradient_norm_of(lin: _Linearization) -> float:
            return float(lin.gradient.abs().max()) if n > 0 else 0.0

        gradient_norm = gradient_norm_of(lin)
        status = Status.RUNNING
        if not np.isfinite(cost):
            status = Status.NON_FINITE
        elif gradient_norm <= config.gradient_tolerance:
            status = Status.CONVERGED_GRADIENT
        iterations = 0
        for it in range(config.max_iterations):
            if status != Status.RUNNING:
                break
            iterations += 1
            tick = time.perf_counter()
            if linear_solver == "sparse":
                delta = _solve_sparse(lin, layout, lam, config.damping)
            else:
                delta = _solve_dense(lin, structure, graph.num_edges, lam, config.damping)
            solve_seconds += time.perf_counter() - tick
            accepted, f_conv, p_conv = False, False, False
            step_norm = float("nan")
            if delta is not None:
                step_norm = float(torch.linalg.vector_norm(delta))
                x_norm = float(torch.linalg.vector_norm(T[structure.free, :3, :]))
                delta_vertex = T.new_zeros(N, 6)
                delta_vertex[structure.free] = delta
                predicted = _model_decrease(lin, delta, delta_vertex, graph, priors)
                T_new = T.clone()
                T_new[structure.free] = T[structure.free] @ se3._exp(delta)
                # Linearize at the candidate right away: its cost decides acceptance, and an
                # accepted step then needs no second pass over the edges.
                tick = time.perf_counter()
                lin_new = _linearize(T_new, graph, priors, U, structure, config.jacobian)
                new_cost = lin_new.cost
                linearize_seconds += time.perf_counter() - tick
                gain = (cost - new_cost) / predicted if predicted > 0 else -1.0
                accepted = bool(np.isfinite(new_cost)) and predicted > 0 and gain > 0
                if accepted:
                    f_conv = abs(cost - new_cost) <= config.function_tolerance * cost
                # Nothing left to gain: even the model predicts a negligible decrease.
                f_conv = f_conv or abs(predicted) <= config.function_tolerance * cost
                p_conv = step_norm <= config.parameter_tolerance * (
                    x_norm + config.parameter_tolerance
                )
                lam, nu = _nielsen(lam, nu, gain, accepted, config)
                if accepted:
                    T, lin, cost = T_new, lin_new, new_cost
                    gradient_norm = gradient_norm_of(lin)
            else:
                lam, nu = _nielsen(lam, nu, 0.0, False, config)
            if f_conv:
                status = Status.CONVERGED_FUNCTION
            elif gradient_norm <= config.gradient_tolerance:
                status = Status.CONVERGED_GRADIENT
            elif p_conv:
                status = Status.CONVERGED_PARAMETER
            elif lam > config.max_lambda:
                status = Status.DAMPING_LIMIT
            costs.append(cost)
            lambdas.append(lam)
            steps.append(step_norm)
            if callback is not None or logger.isEnabledFor(logging.INFO):
                info = {
                    "iteration": it + 1,
                    "cost": cost,
                    "lambda": lam,
                    "step_norm": step_norm,
                    "accepted": accepted,
                    "gradient_norm": gradient_norm,
                    "seconds": time.perf_counter() - start,
                }
                if callback is not None:
                    callback(info)
                logger.info(
                    "iter %3d  cost %.6e  lambda %.2e  |step| %.2e  %s",
                    it + 1,
                    cost,
                    lam,
                    step_norm,
                    "accepted" if accepted else "rejected",
                )
        if status == Status.RUNNING:
            status = Status.MAX_ITERATIONS

    def history(values: list[float]) -> Tensor:
        return torch.tensor(values, dtype=torch.float64)

    return PoseGraphSolveResult(
        poses=T,
        status=status,
        iterations=iterations,
        initial_cost=initial_cost,
        final_cost=cost,
        cost_history=history(costs),
        lambda_history=history(lambdas),
        step_norm_history=history(steps),
        gradient_norm=gradient_norm,
        linear_solver=linear_solver,
        time_seconds=time.perf_counter() - start,
        linearize_seconds=linearize_seconds,
        linear_solve_seconds=solve_seconds,
    )
