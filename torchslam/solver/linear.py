"""Linear solve of the damped normal equations, by Schur complement on the points or densely.

Every path first *factors* the damped system (:func:`factorize` → :class:`Factorization`)
and then solves it for a gradient; the solver calls both once per iteration
(:func:`solve_step`), the implicit backward of :mod:`.differentiable` factors once and solves
for many right-hand sides. The reduced pose system S is factored densely (batched Cholesky)
or, for large sparse ones, by :mod:`.sparse` (SuperLU with a fill-reducing ordering); the
pose terms of :mod:`torchslam.terms` add their off-diagonal blocks to it.

The system of one problem, with poses p and points l,

    [ U + λD_U    W       ] [δp]     [g_p]
    [ Wᵀ          V + λD_V] [δl] = − [g_l]

is reduced on the points (the classic bundle-adjustment elimination; V is block-diagonal
3×3 because each observation touches one point):

    S = (U + λD_U) − Σ_j W_j (V_j + λD_Vj)⁻¹ W_jᵀ,   S δp = −g_p + Σ_j W_j V_j⁻¹ g_lj,
    δl_j = −V_j⁻¹ (g_lj + W_jᵀ δp).

S is assembled from pairs of observations of the same point: the pair (a, b) with poses
(i_a, i_b) adds Y_a W_bᵀ, Y_a = W_a V_j⁻¹, to block (i_a, i_b). Only pairs with
(i_a, a) < (i_b, b) plus the self-pairs a = b are formed; the rest follows by symmetry.
Memory is O(E + P + m²) with P = Σ_j (observations of j)², processed in chunks; the dense
(6m+3n)² matrix is never formed. The 6m × 6m system is factored by batched Cholesky
(``torch.linalg.cholesky_ex``) or sparsely (:mod:`.sparse`, with the pose terms' blocks in
its pattern): a problem whose matrix is not positive definite is reported, never crashes the
batch.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse
import torch
from torch import Tensor

from torchslam.problem import PointMapData, gather_points, per_observation
from torchslam.solver.linearize import (
    BlockLinearization,
    StructuredLinearization,
    blocks_from_monomials,
    coupling_edges,
    monomials,
    term_pair_keys,
)
from torchslam.solver.sparse import BlockPattern, SparseFactor, factorization_work

__all__ = [
    "Factorization",
    "SchurStructure",
    "SparseSchur",
    "choose_reduced_solver",
    "damp",
    "factorize",
    "solve_dense",
    "solve_schur",
    "solve_schur_structured",
    "solve_step",
]


@dataclass
class SchurStructure:
    """Observation pairs that share a point, computed once per solve (the sparsity is fixed)."""

    # First / second observation of each pair, flat indices into B·E.
    first: Tensor
    second: Tensor
    # Flat index b·m·m + i_first·m + i_second of the 6×6 block each pair adds to.
    block: Tensor
    # 1 for a self-pair (a = b), 2 otherwise is not stored: self-pairs get weight ½ so that
    # A + Aᵀ counts them once.
    self_pair: Tensor
    # Both observations in the same pose (a diagonal block), bool.
    same_pose: Tensor
    # Flat index b·n + j of the shared point.
    point: Tensor

    @staticmethod
    def build(data: PointMapData) -> SchurStructure:
        edges = coupling_edges(data)
        B, E = edges.pose_index.shape
        m, n = data.num_poses, data.num_points
        device = edges.pose_index.device
        batch = torch.arange(B, device=device)[:, None].expand(B, E)
        # Edges that couple a free pose with a free point.
        active = edges.active.reshape(-1)
        obs = active.nonzero().squeeze(1)
        point_key = (batch * n + edges.point_index).reshape(-1)[obs]
        order = torch.argsort(point_key, stable=True)
        obs, point_key = obs[order], point_key[order]
        _, counts = torch.unique_consecutive(point_key, return_counts=True)
        group_start = torch.cumsum(counts, 0) - counts
        per_obs_count = torch.repeat_interleave(counts, counts)
        per_obs_start = torch.repeat_interleave(group_start, counts)
        # All ordered pairs (a, b) inside each point's group.
        first_pos = torch.repeat_interleave(torch.arange(obs.numel(), device=device), per_obs_count)
        offset = torch.arange(first_pos.numel(), device=device) - torch.repeat_interleave(
            torch.cumsum(per_obs_count, 0) - per_obs_count, per_obs_count
        )
        second_pos = per_obs_start[first_pos] + offset
        first, second = obs[first_pos], obs[second_pos]
        pose_flat = edges.pose_index.reshape(-1)
        i_a, i_b = pose_flat[first], pose_flat[second]
        keep = (i_a < i_b) | ((i_a == i_b) & (first <= second))
        first, second, i_a, i_b = first[keep], second[keep], i_a[keep], i_b[keep]
        b = first // E
        return SchurStructure(
            first=first,
            second=second,
            block=(b * m + i_a) * m + i_b,
            self_pair=first == second,
            same_pose=i_a == i_b,
            point=(batch * n + edges.point_index).reshape(-1)[first],
        )

    @property
    def num_pairs(self) -> int:
        return self.first.numel()


def damp(blocks: Tensor, lam: Tensor, damping: str) -> Tensor:
    """Add λD to square diagonal blocks (B, k, d, d); D = diag(block) clamped (Marquardt,
    as Ceres: [1e-6, 1e32]) or I (Levenberg). ``lam`` has shape (B,)."""
    eye = torch.eye(blocks.shape[-1], dtype=blocks.dtype, device=blocks.device)
    if damping == "levenberg":
        D = eye
    else:
        D = torch.diagonal(blocks, dim1=-2, dim2=-1).clamp(1e-6, 1e32)[..., None] * eye
    return blocks + lam[:, None, None, None] * D


@dataclass
class Factorization:
    """A damped system factored once: :meth:`solve` gives the step −H⁻¹g for any gradient."""

    # The factored (reduced or full) system: has ``ok`` (B,) and ``solve``.
    factor: _DenseCholesky | SparseFactor
    # (pose_gradient (B, m, 6), point_gradient (B, n, 3)) → (δp, δl).
    solve_fn: Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]
    # Problems whose other parts (e.g. the 3 × 3 point blocks) factored, bool (B,) or None.
    other_ok: Tensor | None = None

    @property
    def ok(self) -> Tensor:
        """False where a factorization failed or gave a non-finite step (then zero), (B,)."""
        ok = self.factor.ok
        return ok if self.other_ok is None else ok & self.other_ok

    def solve(self, pose_gradient: Tensor, point_gradient: Tensor) -> tuple[Tensor, Tensor]:
        """The step (δp (B, m, 6), δl (B, n, 3)) = −H⁻¹ g for the gradient g."""
        return self.solve_fn(pose_gradient, point_gradient)


@dataclass
class _DenseCholesky:
    """Batched Cholesky of (B, N, N) SPD matrices; never raises on an indefinite one."""

    L: Tensor
    ok: Tensor

    @staticmethod
    def of(A: Tensor) -> _DenseCholesky:
        L, info = torch.linalg.cholesky_ex(A)
        ok = info == 0
        if not bool(ok.all()):  # rare: swap in I so the batched solve stays finite
            eye = torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)
            L = torch.where(ok[..., None, None], L, eye)
        return _DenseCholesky(L, ok)

    def solve(self, b: Tensor) -> Tensor:
        x = torch.cholesky_solve(b[..., None], self.L)[..., 0]
        return torch.where(self.ok[..., None], x, torch.zeros_like(x))


def _batched_cholesky_solve(A: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """Solve A x = b for SPD A (..., k, k); returns (x, ok) with ok False where Cholesky failed
    (x is then zero). Never raises on an indefinite matrix."""
    factor = _DenseCholesky.of(A)
    return factor.solve(b), factor.ok


def term_pair_matrix(lin, data: PointMapData) -> Tensor | None:
    """The pose terms' off-diagonal blocks as a dense (B, 6m, 6m) matrix, or None."""
    if lin.terms is None or lin.terms.pair_blocks.shape[1] == 0:
        return None
    B, m = data.pose_index.shape[0], data.num_poses
    P = lin.terms.pair_blocks
    dense = P.new_zeros(B * m * m, 6, 6).index_add_(
        0, term_pair_keys(data).reshape(-1), P.reshape(-1, 6, 6)
    )
    return dense.reshape(B, m, m, 6, 6).transpose(2, 3).reshape(B, 6 * m, 6 * m)


@dataclass
class SparseSchur:
    """What the sparse reduced solve needs once per solve: the observation pairs, the block
    pattern of S and where each contribution goes in it (built by :meth:`build`)."""

    structure: SchurStructure
    pattern: BlockPattern
    # Unique block of each observation pair (P,), and of each kept term pair (T,).
    pair_slot: Tensor
    term_slot: Tensor
    # The term pairs (indices into lin.terms.pair_blocks flattened over B) that are upper
    # (i ≤ k) blocks, (T,).
    term_keep: Tensor

    @staticmethod
    def build(
        data: PointMapData, structure: SchurStructure | None = None, ordering: str = "mmd"
    ) -> SparseSchur:
        structure = structure if structure is not None else SchurStructure.build(data)
        m = data.num_poses
        B = data.pose_index.shape[0]
        term_keys = term_pair_keys(data).reshape(-1)
        i, k = (term_keys % (m * m)) // m, term_keys % m
        term_keep = (i <= k).nonzero().squeeze(1)
        keys = torch.cat((structure.block, term_keys[term_keep]))
        pattern, slot = BlockPattern.build(keys, B, m, ordering)
        P = structure.num_pairs
        return SparseSchur(structure, pattern, slot[:P], slot[P:], term_keep)

    def reduced_factor(self, lin, data: PointMapData, U: Tensor, pair_values: Tensor):
        """Factor S from the damped diagonal blocks U (B, m, 6, 6), the summed observation-pair
        blocks of the pattern (Q, 6, 6) (already negated) and the pose terms' pairs."""
        B, m = U.shape[:2]
        values = pair_values
        values.index_add_(0, self._diagonal_slots(B, m, U.device), U.reshape(-1, 6, 6))
        if lin.terms is not None and self.term_keep.numel() > 0:
            blocks = lin.terms.pair_blocks.reshape(-1, 6, 6)[self.term_keep]
            values.index_add_(0, self.term_slot, blocks)
        return self.pattern.factor(values)

    def _diagonal_slots(self, B: int, m: int, device) -> Tensor:
        diag = (torch.arange(B * m, device=device) * m) + torch.arange(m, device=device).repeat(B)
        return torch.searchsorted(self.pattern.keys, diag)


# The sparse factorization (SuperLU, scalar entries) runs ~10× below the dense batched
# Cholesky's flop rate, and assembly adds to it: sparse wins when its work is well below.
SPARSE_WORK_FACTOR = 30.0


def choose_reduced_solver(
    data: PointMapData,
    reduced_solver: str,
    dense_max_variables: int,
    ordering: str = "mmd",
    max_pairs: int = 10_000_000,
) -> str:
    """ "dense" or "sparse" for ``reduced_solver`` "auto" (explicit choices are returned).

    Dense when 6m ≤ ``dense_max_variables``. Otherwise the block pattern of each problem's S
    (pose pairs sharing a point, from the sparse product A Aᵀ of its m × n co-visibility,
    and the terms' pose pairs) is ordered like the sparse path would and its symbolic
    factorization gives the work W = Σ_j c_j² (c_j entries in block column j of the factor):
    sparse when ``SPARSE_WORK_FACTOR``·W < m³ (the dense Cholesky's (6m)³/3 in the same
    units, 216 W vs 72 m³) for every problem. Band-like patterns (trajectories, pose graphs)
    go sparse; random or wide co-visibility, whose factor fills in, stays dense. When the
    observation pairs sharing a point exceed ``max_pairs`` (forming them would be the sparse
    path's cost too), dense.
    """
    if reduced_solver != "auto":
        return reduced_solver
    m, n = data.num_poses, data.num_points
    if 6 * m <= dense_max_variables:
        return "dense"
    B = data.pose_index.shape[0]
    edges = coupling_edges(data)
    batch = torch.arange(B, device=edges.point_index.device)[:, None]
    flat_point = (batch * n + edges.point_index)[edges.active]
    counts = torch.bincount(flat_point, minlength=B * n).reshape(B, -1)
    if int((counts * (counts + 1) // 2).sum()) > max_pairs:
        return "dense"
    keys = term_pair_keys(data).cpu()
    pose, point, valid = (
        t.cpu().numpy() for t in (edges.pose_index, edges.point_index, edges.active)
    )
    for b in range(B):
        A = scipy.sparse.csr_matrix(
            (np.ones(int(valid[b].sum())), (pose[b][valid[b]], point[b][valid[b]])), shape=(m, n)
        )
        covisible = scipy.sparse.triu(A @ A.T, k=1).tocoo()
        local = keys[b] % (m * m)
        first = np.concatenate((covisible.row, (local // m).numpy()))
        second = np.concatenate((covisible.col, (local % m).numpy()))
        work = factorization_work(m, first, second, ordering)
        if SPARSE_WORK_FACTOR * work >= float(m) ** 3:
            return "dense"
    return "sparse"


def factorize(
    lin: BlockLinearization | StructuredLinearization,
    data: PointMapData,
    structure: SchurStructure | None,
    lam: Tensor,
    damping: str,
    linear_solver: str = "schur",
    chunk_size: int = 1 << 20,
    sparse: SparseSchur | None = None,
) -> Factorization:
    """Factor the damped system of either linearization form.

    ``linear_solver`` is "schur" or "dense" (block form only); with "schur", a given
    ``sparse`` (:class:`SparseSchur`) factors the reduced system sparsely, else densely.
    """
    if linear_solver == "dense":
        if isinstance(lin, StructuredLinearization):
            raise ValueError("factorize: linear_solver='dense' needs the block linearization")
        return _factorize_dense(lin, data, lam, damping)
    if isinstance(lin, StructuredLinearization):
        return _factorize_structured(lin, data, lam, damping, sparse)
    if sparse is not None:
        structure = sparse.structure
    if structure is None:
        structure = SchurStructure.build(data)
    return _factorize_schur(lin, data, structure, lam, damping, chunk_size, sparse)


def solve_step(
    lin: BlockLinearization | StructuredLinearization,
    data: PointMapData,
    structure: SchurStructure | None,
    lam: Tensor,
    damping: str,
    linear_solver: str = "schur",
    chunk_size: int = 1 << 20,
    sparse: SparseSchur | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Damped Gauss-Newton step (δp (B, m, 6), δl (B, n, 3), ok (B,)) for either
    linearization form (:func:`factorize`, then solve for the linearization's gradient)."""
    f = factorize(lin, data, structure, lam, damping, linear_solver, chunk_size, sparse)
    dp, dl = f.solve(lin.pose_gradient, lin.point_gradient)
    return dp, dl, f.ok


def solve_schur_structured(
    lin: StructuredLinearization, data: PointMapData, lam: Tensor, damping: str
) -> tuple[Tensor, Tensor, Tensor]:
    """Schur step for the structured linearization, dense reduced system (:func:`factorize`)."""
    return solve_step(lin, data, None, lam, damping)


def solve_schur(
    lin: BlockLinearization,
    data: PointMapData,
    structure: SchurStructure,
    lam: Tensor,
    damping: str,
    chunk_size: int = 1 << 20,
) -> tuple[Tensor, Tensor, Tensor]:
    """Schur step for the block linearization, dense reduced system (:func:`factorize`)."""
    return solve_step(lin, data, structure, lam, damping, "schur", chunk_size)


def solve_dense(
    lin: BlockLinearization, data: PointMapData, lam: Tensor, damping: str
) -> tuple[Tensor, Tensor, Tensor]:
    """Damped step from the full (6m + 3n)² system — small problems and cross-checks only."""
    return solve_step(lin, data, None, lam, damping, "dense")


# Entries of the (B, 10·m, c) buffer of one chunk of c points in _monomial_products.
STRUCTURED_CHUNK_ENTRIES = 1 << 24


def _monomial_products(lin: StructuredLinearization, data: PointMapData, v_d: Tensor) -> Tensor:
    """C_f = A·diag(f/v)·Aᵀ for the 10 monomials f, stacked as (B, 10·m, m) (doc of
    :func:`_factorize_structured`), by one batched GEMM per chunk of points.

    A (B, m, c) holds the coupling weights of a chunk of c points, built from the chunk's
    observations; c is chosen so that the (B, 10·m, c) product buffer stays within
    ``STRUCTURED_CHUNK_ENTRIES`` (one chunk for the benchmark cases), so memory is
    O(B·m·c + B·m²), not O(B·m·n).
    """
    B = data.pose_index.shape[0]
    m, n = data.num_poses, data.num_points
    batch = torch.arange(B, device=v_d.device)[:, None]
    # (B, 10, n), contiguous so that the broadcast product below comes out contiguous.
    F = (monomials(lin.points) / v_d[..., None]).transpose(1, 2).contiguous()
    chunk = max(1, min(n, STRUCTURED_CHUNK_ENTRIES // max(1, B * 10 * m)))
    C = v_d.new_zeros(B, 10 * m, m)
    weight = lin.coupling_weight
    for start in range(0, n, chunk):
        c = min(chunk, n - start)
        if c == n:
            inside, local = torch.ones_like(data.valid), data.point_index
        else:
            inside = (data.point_index >= start) & (data.point_index < start + c)
            local = (data.point_index - start).clamp(0, c - 1)
        A = v_d.new_zeros(B * m * c).index_add_(
            0,
            ((batch * m + data.pose_index) * c + local).reshape(-1),
            torch.where(inside, weight, torch.zeros_like(weight)).reshape(-1),
        )
        A = A.reshape(B, m, c)
        # (A diag(f/v))_f for the 10 monomials f, stacked as (B, 10·m, c), times Aᵀ.
        AF = (A[:, None] * F[:, :, None, start : start + c]).reshape(B, 10 * m, c)
        C = C.baddbmm(AF, A.transpose(1, 2)) if c != n else torch.bmm(AF, A.transpose(1, 2))
    return C


def _factorize_structured(
    lin: StructuredLinearization,
    data: PointMapData,
    lam: Tensor,
    damping: str,
    sparse: SparseSchur | None,
) -> Factorization:
    """Schur factorization for the structured (ICP-SLAM, scalar-weight) linearization.

    With W_e = w_e G_jᵀ and V_j = v_j I (module doc of :mod:`.linearize`), the reduced matrix is

        S_ik = δ_ik U_i − Σ_j (a_ij a_kj / v_j) G_jᵀ G_j,

    a_ij the coupling weight of the observation of point j in frame i (0 if none). Densely,
    each of the 10 monomial coefficients of G_jᵀ G_j is one product A·diag(f/v)·Aᵀ, all
    computed by one batched GEMM of (m × n) by (n × 10m): 20·m²·n flops per problem, no
    per-pair products (chunked over the points when the (10m × n) buffer would be large).
    Sparsely, each observation pair (a, b) of point j adds the 10 monomials of X_j times
    −a_a a_b / v_j to its block of the pattern (twice for a ≠ b in one pose: the pair and its
    mirror), and the blocks are formed once per unique block.
    """
    B, _E = data.pose_index.shape
    m, n = data.num_poses, data.num_points
    U = damp(lin.pose_blocks, lam, damping)
    v = lin.point_weight
    if damping == "levenberg":
        v_d = v + lam[:, None]
    else:
        v_d = v + lam[:, None] * v.clamp(1e-6, 1e32)
    batch = torch.arange(B, device=v.device)[:, None]
    if sparse is None:
        C = _monomial_products(lin, data, v_d).reshape(B, 10, m, m)
        S = -blocks_from_monomials(C.permute(0, 2, 3, 1))  # (B, m, m, 6, 6)
        idx = torch.arange(m, device=S.device)
        S[:, idx, idx] += U
        S = S.transpose(2, 3).reshape(B, 6 * m, 6 * m)
        pairs = term_pair_matrix(lin, data)
        if pairs is not None:
            S = S + pairs
        reduced = _DenseCholesky.of(S)
    else:
        st = sparse.structure
        w = lin.coupling_weight.reshape(-1)
        coefficient = -(w[st.first] * w[st.second]) / v_d.reshape(-1)[st.point]
        coefficient = torch.where(st.same_pose & ~st.self_pair, 2 * coefficient, coefficient)
        mono = monomials(lin.points.reshape(-1, 3)[st.point]) * coefficient[:, None]
        sums = mono.new_zeros(sparse.pattern.num_unique, 10).index_add_(0, sparse.pair_slot, mono)
        reduced = sparse.reduced_factor(lin, data, U, blocks_from_monomials(sums))
    X_e = gather_points(lin.points, data)
    w_over_v = lin.coupling_weight / per_observation(v_d, data.flat_point_index)

    def solve(pose_gradient: Tensor, point_gradient: Tensor) -> tuple[Tensor, Tensor]:
        # Right-hand side: −g_p + Σ_e (w_e / v_j) G_jᵀ g_lj.
        y = w_over_v[..., None] * gather_points(point_gradient, data)
        Gty = torch.cat((torch.linalg.cross(X_e, y, dim=-1), y), -1)
        rhs = (
            (-pose_gradient)
            .reshape(B * m, 6)
            .index_add(0, (batch * m + data.pose_index).reshape(-1), Gty.reshape(-1, 6))
        )
        dp = reduced.solve(rhs.reshape(B, 6 * m)).reshape(B, m, 6)
        # Back-substitution: δl_j = −(g_lj + Σ_e w_e G_j δp_i(e)) / v_j, G_j δp = δω × X_j + δv.
        dp_e = per_observation(dp, data.flat_pose_index)
        G_dp = torch.linalg.cross(dp_e[..., :3], X_e, dim=-1) + dp_e[..., 3:]
        acc = point_gradient.reshape(B * n, 3).index_add(
            0,
            (batch * n + data.point_index).reshape(-1),
            (lin.coupling_weight[..., None] * G_dp).reshape(-1, 3),
        )
        return dp, -acc.reshape(B, n, 3) / v_d[..., None]

    return Factorization(reduced, solve)


def _factorize_schur(
    lin: BlockLinearization,
    data: PointMapData,
    structure: SchurStructure,
    lam: Tensor,
    damping: str,
    chunk_size: int,
    sparse: SparseSchur | None,
) -> Factorization:
    """Schur factorization for the block linearization (module doc)."""
    edges = coupling_edges(data)
    B, E = edges.pose_index.shape
    m, n = data.num_poses, data.num_points
    U = damp(lin.pose_blocks, lam, damping)
    V = damp(lin.point_blocks, lam, damping)
    # V⁻¹ through Cholesky of each 3×3 block (a failure marks the whole problem).
    LV, info = torch.linalg.cholesky_ex(V)
    point_ok = (info == 0).all(dim=-1)
    eye3 = torch.eye(3, dtype=V.dtype, device=V.device)
    LV = torch.where((info == 0)[..., None, None], LV, eye3)
    V_inv = torch.cholesky_inverse(LV)  # (B, n, 3, 3)

    W = lin.coupling.reshape(B * E, 6, 3)
    batch = torch.arange(B, device=W.device)[:, None]
    V_inv_e = V_inv.reshape(B * n, 3, 3)[(batch * n + edges.point_index).reshape(-1)]
    Y = W @ V_inv_e  # (B·E, 6, 3)

    if sparse is None:
        blocks = W.new_zeros(B * m * m, 6, 6)
        for start in range(0, structure.num_pairs, chunk_size):
            sl = slice(start, start + chunk_size)
            prod = Y[structure.first[sl]] @ W[structure.second[sl]].transpose(-1, -2)
            prod = torch.where(structure.self_pair[sl, None, None], 0.5 * prod, prod)
            blocks.index_add_(0, structure.block[sl], prod)
        A = blocks.reshape(B, m, m, 6, 6).transpose(2, 3).reshape(B, 6 * m, 6 * m)
        S = -(A + A.transpose(-1, -2))
        S_blocks = S.view(B, m, 6, m, 6)  # a view: adding U on the block diagonal edits S
        idx = torch.arange(m, device=S.device)
        S_blocks[:, idx, :, idx, :] += U.transpose(0, 1)
        pairs = term_pair_matrix(lin, data)
        if pairs is not None:
            S = S + pairs
        reduced = _DenseCholesky.of(S)
    else:
        values = W.new_zeros(sparse.pattern.num_unique, 6, 6)
        for start in range(0, structure.num_pairs, chunk_size):
            sl = slice(start, start + chunk_size)
            prod = Y[structure.first[sl]] @ W[structure.second[sl]].transpose(-1, -2)
            mirror = structure.same_pose[sl] & ~structure.self_pair[sl]
            prod = torch.where(mirror[:, None, None], prod + prod.transpose(-1, -2), prod)
            values.index_add_(0, sparse.pair_slot[sl], -prod)
        reduced = sparse.reduced_factor(lin, data, U, values)

    def solve(pose_gradient: Tensor, point_gradient: Tensor) -> tuple[Tensor, Tensor]:
        # Right-hand side: −g_p + Σ_e Y_e g_l(j(e)).
        gl_e = point_gradient.reshape(B * n, 3)[(batch * n + edges.point_index).reshape(-1)]
        Yg = (Y @ gl_e[..., None])[..., 0].reshape(B, E, 6)
        rhs = (
            (-pose_gradient)
            .reshape(B * m, 6)
            .index_add(0, (batch * m + edges.pose_index).reshape(-1), Yg.reshape(-1, 6))
        )
        dp = reduced.solve(rhs.reshape(B, 6 * m)).reshape(B, m, 6)
        # Back-substitution: δl_j = −V_j⁻¹ (g_lj + Σ_e W_eᵀ δp_i(e)).
        dp_e = per_observation(dp, batch * m + edges.pose_index)
        Wt_dp = (lin.coupling.transpose(-1, -2) @ dp_e[..., None])[..., 0]  # (B, E, 3)
        acc = point_gradient.reshape(B * n, 3).index_add(
            0, (batch * n + edges.point_index).reshape(-1), Wt_dp.reshape(-1, 3)
        )
        return dp, -(V_inv @ acc.reshape(B, n, 3)[..., None])[..., 0]

    return Factorization(reduced, solve, point_ok)


def _factorize_dense(
    lin: BlockLinearization, data: PointMapData, lam: Tensor, damping: str
) -> Factorization:
    """The full (6m + 3n)² system — small problems and cross-checks only.

    Assembled by out-of-place ``index_put`` (no writes through views), so autograd can
    differentiate through it (the unrolled backward).
    """
    B = data.pose_index.shape[0]
    m, n = data.num_poses, data.num_points
    N = 6 * m + 3 * n
    device = lin.coupling.device
    U = damp(lin.pose_blocks, lam, damping)
    V = damp(lin.point_blocks, lam, damping)

    def block_indices(count: int, offset: int, size: int) -> tuple[Tensor, Tensor, Tensor]:
        """(batch, row, col) of the size × size diagonal blocks, (B, count, size, size)."""
        a = torch.arange(size, device=device)
        start = offset + size * torch.arange(count, device=device)[:, None, None]
        rows = (start + a[:, None]).expand(count, size, size)
        cols = (start + a[None, :]).expand(count, size, size)
        batch = torch.arange(B, device=device)[:, None, None, None]
        return torch.broadcast_tensors(batch, rows[None], cols[None])

    H = lin.coupling.new_zeros(B, N, N)
    H = H.index_put(block_indices(m, 0, 6), U)
    H = H.index_put(block_indices(n, 6 * m, 3), V)
    edges = coupling_edges(data)
    rows = 6 * edges.pose_index[..., None, None] + torch.arange(6, device=device)[:, None]
    cols = 6 * m + 3 * edges.point_index[..., None, None] + torch.arange(3, device=device)
    rows, cols = torch.broadcast_tensors(rows, cols)  # (B, E, 6, 3)
    bidx = torch.arange(B, device=device)[:, None, None, None].expand_as(rows)
    H = H.index_put((bidx, rows, cols), lin.coupling, accumulate=True)
    H = H.index_put((bidx, cols, rows), lin.coupling, accumulate=True)
    pairs = term_pair_matrix(lin, data)
    if pairs is not None:
        H = H + torch.nn.functional.pad(pairs, (0, 3 * n, 0, 3 * n))
    full = _DenseCholesky.of(H)

    def solve(pose_gradient: Tensor, point_gradient: Tensor) -> tuple[Tensor, Tensor]:
        g = torch.cat((pose_gradient.reshape(B, 6 * m), point_gradient.reshape(B, 3 * n)), -1)
        x = full.solve(-g)
        return x[:, : 6 * m].reshape(B, m, 6), x[:, 6 * m :].reshape(B, n, 3)

    return Factorization(full, solve)
