"""The planned linear solve: built once per solve, then one factorization per iteration.

:meth:`LinearPlan.build` decides everything that is fixed for a solve — the method (Schur
complement on the points, or the full system for small problems and cross-checks), the
reduced solver (dense batched Cholesky, or sparse :mod:`.sparse` with its block pattern and
fill-reducing ordering), the observation pairs that share a point and the chunking — and
:meth:`LinearPlan.factorize` turns a linearization (:mod:`.linearize`) and the damping λ into a
:class:`Factorization` whose :meth:`~Factorization.solve` gives the step −H⁻¹g for any
gradient. The forward solve, the implicit backward (λ = 0, many right-hand sides) and
covariances all go through it.

The system of one problem, with poses p and points l,

    [ U + λD_U    W       ] [δp]     [g_p]
    [ Wᵀ          V + λD_V] [δl] = − [g_l]

is reduced on the points (the classic bundle-adjustment elimination; V is block-diagonal 3×3:
each coupling edge e of :func:`.linearize.coupling_edges` touches one point):

    S = (U + λD_U) − Σ_j W_j (V_j + λD_Vj)⁻¹ W_jᵀ,   S δp = −g_p + W V⁻¹ g_l,
    δl = −V⁻¹ (g_l + Wᵀ δp)

(the one back-substitution, :meth:`Factorization.solve`). S is assembled from pairs of edges of
the same point: the pair (a, b) with poses (i_a ≤ i_b) adds −Y_a W_bᵀ, Y_a = W_a V_j⁻¹, to the
upper block (i_a, i_b); the terms' pose pairs add their blocks J̃_aᵀJ̃_b. Memory is
O(E + P + pattern) with P = Σ_j (edges of j)², processed in chunks; the dense (6m+3n)² matrix
is formed only by the "dense" method. When terms touch the points (bundle adjustment) and S is
dense, :class:`InstancePairs` forms the points' part per whole term instance instead (its
active columns only: a camera's pose and intrinsics at once), the pairs' products summed per
pair of column sets by batched GEMM pieces. The "poses" of S are its *slots*: the m poses,
then the parameter blocks' slots (:mod:`torchslam.objective.parameters`). A problem whose
matrix is not positive definite is reported (``ok`` False, zero step), never crashes the
batch. For dense co-visibility with a dense reduced system,
:meth:`LinearPlan.factorize_coupling_gemm` forms the points' part of S by one GEMM of the
(6m × 3n) coupling matrix instead of per-pair products (the implicit backward's exact Hessian
uses it; the forward solve keeps :meth:`LinearPlan.factorize`).

Adding a reduced solver means writing one class with the interface of :class:`DenseReduced`
(``slots``, ``num_slots``, ``factor``) and choosing it in :meth:`LinearPlan.build`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from torchslam import _inference
from torchslam._batched import matmul
from torchslam.lie import _series
from torchslam.lie.so3 import hat
from torchslam.objective.data import PointMapData
from torchslam.solver.config import SolverConfig
from torchslam.solver.linearize import (
    BlockLinearization,
    CouplingEdges,
    StructuredLinearization,
    blocks_from_monomials,
    coupling_edges,
    monomials,
    point_terms,
    term_pair_keys,
)
from torchslam.solver.segments import (
    pieces,
    segment_sum,
    stable_argsort,
    unique_inverse,
    unique_rows,
)
from torchslam.solver.sparse import BlockPattern, SparseFactor, factorization_work

__all__ = [
    "STRUCTURED_CHUNK_ENTRIES",
    "DenseReduced",
    "Factorization",
    "LinearPlan",
    "PairStructure",
    "SparseReduced",
    "choose_reduced_solver",
    "damp",
]


def damp(blocks: Tensor, lam: Tensor, damping: str) -> Tensor:
    """Add λD to square diagonal blocks (B, k, d, d); D = diag(block) clamped (Marquardt,
    as Ceres: [1e-6, 1e32]) or I (Levenberg). ``lam`` has shape (B,)."""
    eye = _series.eye(blocks.shape[-1], blocks.dtype, blocks.device)
    if damping == "levenberg":
        D = eye
    else:
        D = torch.diagonal(blocks, dim1=-2, dim2=-1).clamp(1e-6, 1e32)[..., None] * eye
    return blocks + lam[:, None, None, None] * D


# ------------------------------------------------------------------------------------------
# Structure fixed for a solve


@dataclass
class PairStructure:
    """Pairs of coupling edges that share a point (the sparsity of S is fixed for a solve)."""

    # First / second edge of each pair, flat indices into B·E'.
    first: Tensor
    second: Tensor
    # Upper block key (b·m + i_first)·m + i_second (i_first ≤ i_second) each pair adds to.
    key: Tensor
    # Self-pairs (a = b) and pairs of two edges in one pose (a diagonal block), bool.
    self_pair: Tensor
    same_pose: Tensor
    # Flat index b·n + j of the shared point.
    point: Tensor

    @staticmethod
    def build(edges: CouplingEdges, m: int, n: int) -> PairStructure:
        B, E = edges.pose_index.shape
        device = edges.pose_index.device
        batch = torch.arange(B, device=device)[:, None].expand(B, E)
        obs = edges.active.reshape(-1).nonzero().squeeze(1)
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
        return PairStructure(
            first=first,
            second=second,
            key=(b * m + i_a) * m + i_b,
            self_pair=first == second,
            same_pose=i_a == i_b,
            point=(batch * n + edges.point_index).reshape(-1)[first],
        )

    @property
    def num_pairs(self) -> int:
        return self.first.numel()


# Largest buffer of signature-pair blocks (entries) that :class:`InstancePairs` keeps.
MAX_SIGNATURE_ENTRIES = 1 << 22
# Instance pairs per piece of :class:`InstancePairs` (one GEMM of inner size 3·PIECE), and
# pieces per step: a step's gathered operands (~2 MB) stay in cache and below the size at
# which the allocator maps fresh pages for every call.
PIECE = 32
PIECES_PER_STEP = 256


@dataclass
class InstancePairs:
    """The points' part of a dense S from whole term instances (terms that touch points).

    An *instance* is what touches one point: a point observation (one pose), or one instance
    of a term with ``point_index`` (its a' slots: poses and parameter blocks). Its coupling
    W_k = J̃_slotsᵀ J̃_X is taken as one (D × 3) block over its *active* reduced columns only
    (the 6 of each pose, the d_g of each parameter block; D the most of any instance, padded
    with a dummy column), instead of one 6 × 3 block per (slot, point) edge. Each pair of
    instances (k ≤ l) of one point adds Y_k W_lᵀ (Y = W V⁻¹; ½ of it for k = l) to the block
    of its *signature pair* (the two instances' column sets). The pairs of one signature pair
    (few: the cameras' pairs) are cut into pieces of ``PIECE`` pairs, so that a piece's sum
    Σ_p Y_p W_pᵀ is one (D × 3·PIECE)·(3·PIECE × D) product of a batched GEMM (no per-pair
    products, no (pairs, D, D) scratch); the pieces are summed per signature pair and laid
    into the dense matrix with their mirror by one precomputed scatter. Work per iteration
    O(pairs · D²), memory O(instances · D + signature pairs · D²).
    """

    # Per instance: its rows in the flat edge couplings (B·E'·6 rows of 3, + 1 zero row),
    # (count, D); its point slot b·n + j, (count,).
    rows: Tensor
    point: Tensor
    # The pieces (Q, PIECE): the first instance of each pair, an index into [Y; 0], the
    # second, into [W; 0] (padding: the zero row); the signature-pair slot of each piece,
    # (Q,), and whether it holds self pairs (its product counts ½), bool (Q,).
    piece_first: Tensor
    piece_second: Tensor
    piece_slot: Tensor
    piece_half: Tensor
    # Flat index into (B, N + 1, N + 1) of each entry of each signature-pair block and of its
    # mirror, (P_sig · D²,) each; N = 6 · slots.
    flat: Tensor
    flat_mirror: Tensor
    num_signature_pairs: int
    size: int
    # Some instance has fewer columns than D (its rows include the zero row).
    padded: bool = False
    # Per instance its entries in the flat edge couplings (B·E'·18 values, + 3 zeros when
    # padded), in the (3, D) layout of Wᵀ, (count · 3 · D,): one gather of the transposed
    # blocks.
    flat_t: Tensor | None = None
    # Per instance its reduced columns b·(N + 1) + c (N + 1 padding: the dummy column), flat
    # (count · D,); for the back-substitution products of the instance form.
    columns: Tensor | None = None

    @staticmethod
    def build(data: PointMapData, edges: CouplingEdges, B: int, m: int, n: int):
        """The structure of ``data``, or None when its signature pairs would exceed
        ``MAX_SIGNATURE_ENTRIES``."""
        device = edges.pose_index.device
        N = 6 * m
        E_total = edges.pose_index.shape[1]
        batch = torch.arange(B, device=device)[:, None]
        six = torch.arange(6, device=device)
        groups = []  # (rows (B, K, D_t) into B·E'·6, columns (B, K, D_t), point (B, K), keep)
        E = data.pose_index.shape[1]
        if E > 0:
            e = torch.arange(E, device=device)
            rows = (batch * E_total + e)[..., None] * 6 + six
            cols = 6 * data.pose_index[..., None] + six
            keep = edges.active[:, :E]
            groups.append((rows, cols, data.point_index, keep))
        offset = E
        layout = data.parameters
        for term in data.terms:
            if not term.has_point or n == 0:
                continue
            K, a = term.slot_index.shape[1:]
            if a == 0:  # a term on points only: no coupling
                continue
            slots = term.slot_index  # (B, K, a)
            # active columns of each slot position (the same for every instance of the term)
            active = []
            for position in range(a):
                slot = int(slots.reshape(-1, a)[0, position]) if slots.numel() else 0
                if slot < data.num_poses or layout is None:
                    active.append(torch.ones(6, dtype=torch.bool))
                else:
                    active.append(layout.active[slot - data.num_poses])
            active = torch.cat(active).to(device)  # (6a,)
            local = torch.arange(6 * a, device=device)[active]  # (D_t,)
            k = torch.arange(K, device=device)
            edge = offset + k[:, None] * a + local // 6  # (K, D_t) edge of each column
            rows = (batch[..., None] * E_total + edge) * 6 + local % 6
            cols = 6 * slots.gather(2, (local // 6).expand(B, K, -1)) + local % 6
            keep = edges.active[:, offset : offset + K * a].reshape(B, K, a).any(-1)
            groups.append((rows, cols, term.point_index, keep))
            offset += K * a
        if not groups:
            return None
        D = max(g[0].shape[-1] for g in groups)
        zero_row = B * E_total * 6
        all_rows, all_cols, all_points = [], [], []
        for rows, cols, point, keep in groups:
            pad = D - rows.shape[-1]
            if pad:
                rows = torch.nn.functional.pad(rows, (0, pad), value=zero_row)
                cols = torch.nn.functional.pad(cols, (0, pad), value=N)
            all_rows.append(rows[keep])
            all_cols.append(cols[keep])
            all_points.append((batch.expand_as(point) * n + point)[keep])
        rows, cols, point = (torch.cat(x) for x in (all_rows, all_cols, all_points))
        # Signatures: (batch, columns) of each instance.
        b_of = point // max(n, 1)
        sig_key = torch.cat((b_of[:, None], cols), 1)
        signatures, sig = unique_rows(sig_key)
        # Instances numbered by (signature, point): the pairs of a piece (one signature pair,
        # in point order) then read nearly consecutive rows.
        order = torch.from_numpy(np.lexsort((point.cpu().numpy(), sig.cpu().numpy())))
        order = order.to(device)
        rows, cols, point, sig = rows[order], cols[order], point[order], sig[order]
        U = signatures.shape[0]
        # Pairs of instances of one point, k ≤ l in point order.
        order = stable_argsort(point, B * max(n, 1))
        sorted_point = point[order]
        _, counts = torch.unique_consecutive(sorted_point, return_counts=True)
        start = torch.cumsum(counts, 0) - counts
        per = torch.repeat_interleave(counts, counts)  # group size per sorted instance
        pos_start = torch.repeat_interleave(start, counts)
        position = torch.arange(order.numel(), device=device) - pos_start
        span = per - position  # pairs (k, l ≥ k) of each sorted instance
        first_sorted = torch.repeat_interleave(torch.arange(order.numel(), device=device), span)
        local = torch.arange(first_sorted.numel(), device=device) - torch.repeat_interleave(
            torch.cumsum(span, 0) - span, span
        )
        second_sorted = first_sorted + local
        first, second = order[first_sorted], order[second_sorted]
        pair_key = sig[first] * U + sig[second]
        unique_pairs, pair_slot = unique_inverse(pair_key, U * U)
        P_sig = unique_pairs.numel()
        if P_sig * D * D > MAX_SIGNATURE_ENTRIES:
            return None
        sig_a, sig_b = unique_pairs // U, unique_pairs % U
        b = signatures[sig_a, 0]
        r = signatures[sig_a, 1:]  # (P_sig, D)
        c = signatures[sig_b, 1:]
        size = N + 1
        base = (b * size * size)[:, None, None]
        flat = (base + r[:, :, None] * size + c[:, None, :]).reshape(-1)
        flat_mirror = (base + c[:, None, :] * size + r[:, :, None]).reshape(-1)
        # Pieces: the pairs of each signature pair, PIECE at a time, self pairs (k = k, whose
        # products count ½: mirrored below) in pieces of their own.
        count = rows.shape[0]
        group = 2 * pair_slot + (first == second)
        pairs_of, piece_group = pieces(group, 2 * P_sig, PIECE, -1)
        padding = pairs_of < 0
        piece_first = torch.where(padding, count, first[pairs_of.clamp_min(0)])
        piece_second = torch.where(padding, count, second[pairs_of.clamp_min(0)])
        piece_slot, piece_half = piece_group // 2, piece_group % 2 == 1
        padded = bool((rows == zero_row).any())
        flat_t = (rows[:, None, :] * 3 + torch.arange(3, device=device)[None, :, None]).reshape(-1)
        columns = ((point // max(n, 1))[:, None] * (N + 1) + cols).reshape(-1)
        return InstancePairs(
            rows,
            point,
            piece_first,
            piece_second,
            piece_slot,
            piece_half,
            flat,
            flat_mirror,
            P_sig,
            size,
            padded,
            flat_t,
            columns,
        )

    def points_part(
        self, coupling: Tensor, V_inv: Tensor, chunk: int, B: int
    ) -> tuple[Tensor, Tensor | None]:
        """(Σ_j W_j V_j⁻¹ W_jᵀ as a dense (B, N, N) matrix, the instances' blocks Wᵀ
        (count, 3, D) or None with autograd), from the edge couplings (B·E', 6, 3) and V⁻¹
        (B·n, 3, 3)."""
        rows = coupling.reshape(-1, 3)
        if self.padded:  # a zero row for the padding columns
            rows = torch.cat((rows, rows.new_zeros(1, 3)))
        count, D = self.rows.shape
        # [Wᵀ; 0] and [Yᵀ; 0] per instance (count, 3, D), Yᵀ = V⁻¹ Wᵀ (V⁻¹ symmetric)
        V_e = V_inv.reshape(-1, 9).index_select(0, self.point).reshape(count, 3, 3)
        # With autograd (the unrolled backward) every step is out of place; without, the
        # stacks are written in place (no copies): Wᵀ by one gather of its entries, V⁻¹Wᵀ
        # by the small-matrix product of :mod:`torchslam._batched`.
        graph = torch.is_grad_enabled() and (rows.requires_grad or V_inv.requires_grad)
        if graph:
            Wt = rows.index_select(0, self.rows.reshape(-1)).reshape(count, D, 3).transpose(1, 2)
            zero = rows.new_zeros(1, 3, D)
            W_ext = torch.cat((Wt, zero))
            Y_ext = torch.cat((V_e @ Wt, zero))
        else:
            W_ext = rows.new_empty(count + 1, 3, D)
            torch.index_select(rows.reshape(-1), 0, self.flat_t, out=W_ext[:count].view(-1))
            W_ext[count] = 0.0
            Y_ext = rows.new_empty(count + 1, 3, D)
            matmul(V_e, W_ext[:count], out=Y_ext[:count])
            Y_ext[count] = 0.0
        half = torch.where(self.piece_half, 0.5, 1.0).to(rows.dtype)[:, None, None]
        buffer = rows.new_zeros(self.num_signature_pairs, D, D)
        Q = self.piece_slot.numel()
        step = max(1, min(chunk, PIECES_PER_STEP * PIECE) // PIECE)
        for start in range(0, Q, step):
            sl = slice(start, start + step)
            first = self.piece_first[sl].reshape(-1)
            left = Y_ext.reshape(-1, 3 * D).index_select(0, first).reshape(-1, 3 * PIECE, D)
            right = W_ext.reshape(-1, 3 * D).index_select(0, self.piece_second[sl].reshape(-1))
            right = right.reshape(-1, 3 * PIECE, D)
            product = torch.bmm(left.transpose(1, 2), right) * half[sl]
            if graph:
                buffer = buffer.index_add(0, self.piece_slot[sl], product)
            else:
                buffer.index_add_(0, self.piece_slot[sl], product)
        size = self.size
        dense = rows.new_zeros(B * size * size)
        values = buffer.reshape(-1)
        dense = dense.index_add(0, self.flat, values).index_add(0, self.flat_mirror, values)
        dense = dense.reshape(B, size, size)[:, : size - 1, : size - 1]
        return dense, None if graph else W_ext[:count]


def spd_inverse_3x3(V: Tensor) -> tuple[Tensor, Tensor]:
    """(V⁻¹ (..., 3, 3), ok (...)) of symmetric 3×3 blocks V (..., 3, 3), from their lower
    triangle as a Cholesky factorization reads it: the adjugate over the determinant, written
    on the entries (a few elementwise operations on whole columns, several times faster than
    batched LAPACK on 3×3 blocks), of V scaled by its largest diagonal entry s (the entries of
    a positive definite V/s are at most 1, so its cofactors and determinant neither overflow
    nor underflow with V's scale, in float32 too). ``ok`` is Sylvester's test that V is
    positive definite (the leading minors of V/s positive) with a finite V⁻¹; where it fails
    V⁻¹ is I."""
    diagonal = (V[..., 0, 0], V[..., 1, 1], V[..., 2, 2])
    scale = torch.maximum(torch.maximum(diagonal[0], diagonal[1]), diagonal[2])
    usable = (scale > 0) & torch.isfinite(scale)
    reciprocal = 1.0 / torch.where(usable, scale, 1.0)
    a00, a11, a22 = (d * reciprocal for d in diagonal)
    a10, a20, a21 = (V[..., i, j] * reciprocal for i, j in ((1, 0), (2, 0), (2, 1)))
    c00 = a11 * a22 - a21 * a21
    c10 = a21 * a20 - a10 * a22
    c20 = a10 * a21 - a11 * a20
    c11 = a00 * a22 - a20 * a20
    c21 = a10 * a20 - a00 * a21
    c22 = a00 * a11 - a10 * a10
    det = a00 * c00 + a10 * c10 + a20 * c20
    # V⁻¹ = adj(V/s) / (det(V/s) · s)
    factor = reciprocal / torch.where(det > 0, det, 1.0)
    ok = usable & (a00 > 0) & (c22 > 0) & (det > 0) & torch.isfinite(factor)
    e00, e10, e20, e11, e21, e22 = (c * factor for c in (c00, c10, c20, c11, c21, c22))
    V_inv = torch.stack((e00, e10, e20, e10, e11, e21, e20, e21, e22), -1)
    ok = ok & torch.isfinite(V_inv).all(-1)
    eye = _series.eye(3, V.dtype, V.device).reshape(9)
    return torch.where(ok[..., None], V_inv, eye).reshape(*V.shape), ok


def _active_entries(data: PointMapData) -> Tensor | None:
    """The entries of the reduced system that are not inert, long (N',), or None when all
    are (no parameter block has a padded slot)."""
    layout = data.parameters
    if layout is None or bool(layout.active.all()):
        return None
    device = data.pose_index.device
    active = torch.cat(
        (torch.ones(6 * data.num_poses, dtype=torch.bool), layout.active.reshape(-1))
    )
    return active.nonzero()[:, 0].to(device)


def _diagonal_keys(B: int, m: int, device: torch.device) -> Tensor:
    """Keys (b·m + i)·m + i of the diagonal blocks, (B·m,)."""
    return torch.arange(B * m, device=device) * m + torch.arange(m, device=device).repeat(B)


def _upper_term_pairs(data: PointMapData) -> tuple[Tensor, Tensor]:
    """(keys, positions) of the terms' pose-pair blocks that are upper blocks (i ≤ k): their
    keys and their positions in ``lin.terms.pair_blocks`` flattened over B."""
    m = data.num_slots
    keys = term_pair_keys(data).reshape(-1)
    i, k = (keys % (m * m)) // m, keys % m
    keep = (i <= k).nonzero().squeeze(1)
    return keys[keep], keep


# ------------------------------------------------------------------------------------------
# Reduced solvers: the pose system S, from its upper 6 × 6 blocks


@dataclass
class _DenseCholesky:
    """Batched Cholesky of (B, N, N) SPD matrices; never raises on an indefinite one.

    With ``active`` (the indices of N' < N entries) only A's rows and columns there are
    factored: the others are inert (an identity block, uncoupled: the entries of a parameter
    block's last slot past its size, :mod:`torchslam.objective.parameters`), so that they cost
    no flops; ``L`` is then the (B, N', N') factor of that part."""

    L: Tensor
    ok: Tensor
    active: Tensor | None = None
    size: int = 0

    @staticmethod
    def of(A: Tensor, active: Tensor | None = None) -> _DenseCholesky:
        size = A.shape[-1]
        if active is not None:
            A = A.index_select(-1, active).index_select(-2, active)
        L, info = torch.linalg.cholesky_ex(A)
        ok = info == 0
        if not bool(ok.all()):  # rare: swap in I so the batched solve stays finite
            eye = torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)
            L = torch.where(ok[..., None, None], L, eye)
        return _DenseCholesky(L, ok, active, size)

    def solve(self, b: Tensor) -> Tensor:
        """x with A x = b, (B, N) → (B, N); zeros where the factorization failed."""
        if self.active is None:
            x = torch.cholesky_solve(b[..., None], self.L)[..., 0]
        else:  # the inert entries solve I x = b
            part = torch.cholesky_solve(b.index_select(-1, self.active)[..., None], self.L)
            x = b.index_copy(-1, self.active, part[..., 0])
        return torch.where(self.ok[..., None], x, 0.0)

    def inverse(self) -> Tensor:
        """A⁻¹ (B, N, N) (the identity on the inert entries)."""
        inverse = torch.cholesky_inverse(self.L)
        if self.active is None:
            return inverse
        B = inverse.shape[0]
        full = torch.eye(self.size, dtype=inverse.dtype, device=inverse.device).repeat(B, 1, 1)
        idx = self.active
        batch = torch.arange(B, device=idx.device)[:, None, None]
        return full.index_put((batch, idx[None, :, None], idx[None, None, :]), inverse)

    def pivot_ratios(self) -> Tensor:
        """L_kk² / A_kk per entry, (B, N) (1 on the inert entries): the rank test's."""
        d = torch.diagonal(self.L, dim1=-2, dim2=-1).square()
        ratios = d / self.L.square().sum(-1)
        if self.active is None:
            return ratios
        full = ratios.new_ones(ratios.shape[0], self.size)
        return full.index_copy(-1, self.active, ratios)


@dataclass
class DenseReduced:
    """S of B problems as dense (B, 6m, 6m) matrices, factored by batched Cholesky.

    Differentiable (the unrolled backward runs through it). Slots are the block keys
    themselves: a (B·m·m, 6, 6) buffer holds the upper blocks.
    """

    batch_size: int
    num_poses: int
    # The entries of S that are not inert (parameter blocks' padding), long (N',), or None:
    # only those are factored (:class:`_DenseCholesky`).
    active: Tensor | None = None

    @property
    def num_slots(self) -> int:
        return self.batch_size * self.num_poses**2

    def slots(self, keys: Tensor) -> Tensor:
        """Buffer slot of each upper block key (b·m + i)·m + k."""
        return keys

    def matrix(self, upper: Tensor, dense: Tensor | None = None) -> Tensor:
        """The symmetric (B, 6m, 6m) matrix of the upper blocks (num_slots, 6, 6), mirrored,
        plus ``dense``, an optional symmetric (B, 6m, 6m) part. (Without strictly upper blocks
        :meth:`LinearPlan._factor_dense` adds the diagonal ones with :meth:`add_diagonal`.)"""
        B, m = self.batch_size, self.num_poses
        A = upper.reshape(B, m, m, 6, 6)
        strict = ~torch.eye(m, dtype=torch.bool, device=A.device)[None, :, :, None, None]
        lower = torch.where(strict, A, torch.zeros_like(A)).transpose(1, 2).transpose(-1, -2)
        full = (A + lower).transpose(2, 3).reshape(B, 6 * m, 6 * m)
        return full if dense is None else full + dense

    @staticmethod
    def add_diagonal(dense: Tensor, blocks: Tensor) -> Tensor:
        """``dense`` (B, 6m, 6m) with the 6 × 6 ``blocks`` (B, m, 6, 6) added to its diagonal
        blocks, in place; returns ``dense``."""
        B, m = blocks.shape[:2]
        dense.view(B, m, 6, m, 6).diagonal(0, 1, 3).add_(blocks.permute(0, 2, 3, 1))
        return dense

    def factor(
        self, upper: Tensor, dense: Tensor | None = None, definite: bool = False
    ) -> _DenseCholesky:
        """Factor S = :meth:`matrix` (``upper``, ``dense`` (B, 6m, 6m)); Cholesky reports a
        failure at no extra cost, so ``definite`` is not needed."""
        return _DenseCholesky.of(self.matrix(upper, dense), self.active)


@dataclass
class SparseReduced:
    """S of B problems in a block-sparse pattern, factored by :mod:`.sparse` (SuperLU with a
    fill-reducing ordering); not differentiable (the implicit backward works with it)."""

    pattern: BlockPattern

    @staticmethod
    def build(keys: Tensor, batch_size: int, num_poses: int, ordering: str) -> SparseReduced:
        """The pattern of the diagonal blocks and the upper blocks ``keys`` (any order)."""
        pattern, _ = BlockPattern.build(keys, batch_size, num_poses, ordering)
        return SparseReduced(pattern)

    @property
    def num_slots(self) -> int:
        return self.pattern.num_unique

    def slots(self, keys: Tensor) -> Tensor:
        """Pattern slot of each upper block key (every key must be in the pattern)."""
        return torch.searchsorted(self.pattern.keys, keys)

    def factor(
        self, upper: Tensor, dense: Tensor | None = None, definite: bool = False
    ) -> SparseFactor:
        """Factor S (``upper``); ``definite``: S is positive definite in exact arithmetic (a
        damped system), so the O(nnz) sign check of the factor's D is skipped
        (:meth:`BlockPattern.factor`)."""
        if dense is not None:
            raise ValueError("SparseReduced.factor: a dense part has no place in the pattern")
        return self.pattern.factor(upper, check_sign=not definite)


# ------------------------------------------------------------------------------------------
# Elimination of the points: W·, Wᵀ·, V⁻¹· for either linearization form


@dataclass
class _BlockElimination:
    """W_e (B·E', 6, 3) on the coupling edges and V_j⁻¹ (B, n, 3, 3)."""

    W: Tensor
    V_inv: Tensor
    pose_slot: Tensor
    point_slot: Tensor
    shape: tuple[int, int, int]
    # The same couplings by instance (:class:`InstancePairs`): (Wᵀ (count, 3, D), the
    # structure); the products then run over the instances' D active columns.
    instances: tuple[Tensor, InstancePairs] | None = None

    def point_solve(self, x: Tensor) -> Tensor:
        return (self.V_inv @ x[..., None])[..., 0]

    def blocks(self) -> tuple[Tensor, Tensor]:
        """(W_e (B·E', 6, 3), V_j⁻¹ (B, n, 3, 3)) as blocks (the covariances read them)."""
        return self.W, self.V_inv

    def couple(self, y: Tensor) -> Tensor:
        """Σ_e W_e y_j(e) per pose, y (B, n, 3) → (B, m, 6)."""
        B, m, _ = self.shape
        if self.instances is not None:
            Wt, pairs = self.instances
            y_i = y.reshape(-1, 3).index_select(0, pairs.point)
            Wy = matmul(y_i[:, None, :], Wt).reshape(-1, 1)
            out = segment_sum(pairs.columns, B * (6 * m + 1), Wy).reshape(B, 6 * m + 1)
            return out[:, : 6 * m].reshape(B, m, 6)
        y_e = y.reshape(-1, 3).index_select(0, self.point_slot)
        Wy = (self.W @ y_e[..., None])[..., 0]
        return segment_sum(self.pose_slot, B * m, Wy).reshape(B, m, 6)

    def couple_transposed(self, dp: Tensor) -> Tensor:
        """Σ_e W_eᵀ δp_i(e) per point, dp (B, m, 6) → (B, n, 3)."""
        B, m, n = self.shape
        if self.instances is not None:
            Wt, pairs = self.instances
            padded = torch.nn.functional.pad(dp.reshape(B, 6 * m), (0, 1)).reshape(-1)
            dp_i = padded.index_select(0, pairs.columns).reshape(Wt.shape[0], -1, 1)
            Wt_dp = (Wt @ dp_i)[..., 0]
            return segment_sum(pairs.point, B * n, Wt_dp).reshape(B, n, 3)
        dp_e = dp.reshape(-1, 6).index_select(0, self.pose_slot)
        Wt_dp = (self.W.transpose(-1, -2) @ dp_e[..., None])[..., 0]
        return segment_sum(self.point_slot, B * n, Wt_dp).reshape(B, n, 3)


@dataclass
class _StructuredElimination:
    """W_e = w_e G_jᵀ (G_j = [−[X_j]× | I]) and V_j = v_j I (module doc of .linearize)."""

    weight: Tensor  # coupling weights w_e, (B·E,)
    X_e: Tensor  # the edge's point X_j(e), (B·E, 3)
    v: Tensor  # damped v_j, (B, n)
    pose_slot: Tensor
    point_slot: Tensor
    shape: tuple[int, int, int]

    def point_solve(self, x: Tensor) -> Tensor:
        return x / self.v[..., None]

    def blocks(self) -> tuple[Tensor, Tensor]:
        """(W_e = w_e G_jᵀ (B·E, 6, 3), G_jᵀ = [[X_j]×; I], V_j⁻¹ = I / v_j (B, n, 3, 3))."""
        eye = torch.eye(3, dtype=self.X_e.dtype, device=self.X_e.device)
        G_t = torch.cat((hat(self.X_e), eye.expand(self.X_e.shape[0], 3, 3)), dim=-2)
        return self.weight[:, None, None] * G_t, eye / self.v[..., None, None]

    def couple(self, y: Tensor) -> Tensor:
        B, m, _ = self.shape
        y_e = self.weight[:, None] * y.reshape(-1, 3).index_select(0, self.point_slot)
        Gty = torch.cat((torch.linalg.cross(self.X_e, y_e, dim=-1), y_e), -1)
        return segment_sum(self.pose_slot, B * m, Gty).reshape(B, m, 6)

    def couple_transposed(self, dp: Tensor) -> Tensor:
        B, _, n = self.shape
        dp_e = dp.reshape(-1, 6).index_select(0, self.pose_slot)
        G_dp = torch.linalg.cross(dp_e[:, :3], self.X_e, dim=-1) + dp_e[:, 3:]
        w_G_dp = self.weight[:, None] * G_dp
        return segment_sum(self.point_slot, B * n, w_G_dp).reshape(B, n, 3)


@dataclass
class Factorization:
    """A damped system factored once: :meth:`solve` gives the step −H⁻¹g for any gradient."""

    # The factored reduced system S (Schur) or the full system (method "dense"): has
    # ``ok`` (B,) and ``solve`` (B, N) → (B, N).
    factor: _DenseCholesky | SparseFactor
    # The point elimination (Schur), or None for the full system.
    elimination: _BlockElimination | _StructuredElimination | None
    # Problems whose other parts (the 3 × 3 point blocks) factored, bool (B,) or None.
    other_ok: Tensor | None = None
    # (B, m, n) of the system.
    shape: tuple[int, int, int] = field(default=(0, 0, 0))

    @property
    def ok(self) -> Tensor:
        """False where a factorization failed or gave a non-finite step (then zero), (B,)."""
        ok = self.factor.ok
        return ok if self.other_ok is None else ok & self.other_ok

    def solve(self, pose_gradient: Tensor, point_gradient: Tensor) -> tuple[Tensor, Tensor]:
        """The step (δp (B, m, 6), δl (B, n, 3)) = −H⁻¹ g for the gradient g (module doc)."""
        B, m, n = self.shape
        elim = self.elimination
        if elim is None:
            g = torch.cat((pose_gradient.reshape(B, 6 * m), point_gradient.reshape(B, 3 * n)), -1)
            x = self.factor.solve(-g)
            return x[:, : 6 * m].reshape(B, m, 6), x[:, 6 * m :].reshape(B, n, 3)
        rhs = elim.couple(elim.point_solve(point_gradient)) - pose_gradient
        dp = self.factor.solve(rhs.reshape(B, 6 * m)).reshape(B, m, 6)
        return dp, -elim.point_solve(point_gradient + elim.couple_transposed(dp))


# ------------------------------------------------------------------------------------------
# The plan


# The sparse factorization (SuperLU, scalar entries) runs ~10× below the dense batched
# Cholesky's flop rate, and assembly adds to it: sparse wins when its work is well below.
SPARSE_WORK_FACTOR = 30.0
# Entries of the (B, 10·m, c) buffer of one chunk of c points in the structured dense path.
STRUCTURED_CHUNK_ENTRIES = 1 << 24
# Up to this many poses the structured dense path forms all 16 products P_b P_aᵀ by one GEMM
# (1.6× the flops of the 10 it needs, but 4× fewer operations, which bound small problems).
SMALL_POSES = 32


@dataclass
class LinearPlan:
    """What the linear solve of every iteration of one solve does (module doc)."""

    # "schur" (points eliminated) or "dense" (the full (6m + 3n)² system).
    method: str
    damping: str
    # The reduced solver of the Schur method (None for "dense").
    reduced: DenseReduced | SparseReduced | None
    edges: CouplingEdges
    # Edge pairs of each point; built on first use (the structured dense path needs none).
    pairs: PairStructure | None
    # Pairs per chunk of the pair products.
    chunk_size: int
    shape: tuple[int, int, int]
    # Upper term pairs: their slots in the reduced solver and positions in pair_blocks.
    term_slots: Tensor | None = None
    term_positions: Tensor | None = None
    pair_slots: Tensor | None = None
    diagonal_slots: Tensor | None = None
    # Keys of all the terms' pose-pair blocks, flat (B·P,) (the full system adds them all).
    term_keys: Tensor | None = None
    # Index tensors made on first use and kept for the solve (_edge_slots, ...).
    _cache: dict = field(default_factory=dict, repr=False, compare=False)
    # The data the plan was built for (the instance structure reads its terms), or None.
    _data: PointMapData | None = field(default=None, repr=False, compare=False)

    @staticmethod
    def build(data: PointMapData, config: SolverConfig) -> LinearPlan:
        """The plan for solving ``data`` with ``config`` (linear_solver, reduced_solver,
        dense_max_variables, ordering, schur_chunk_size, damping)."""
        B = data.pose_index.shape[0]
        m, n = data.num_slots, data.num_points
        edges = coupling_edges(data)
        shape = (B, m, n)
        if config.linear_solver == "dense":
            return LinearPlan(
                "dense",
                config.damping,
                None,
                edges,
                None,
                config.schur_chunk_size,
                shape,
                term_keys=term_pair_keys(data).reshape(-1),
            )
        choice = choose_reduced_solver(
            data, config.reduced_solver, config.dense_max_variables, config.ordering, edges=edges
        )
        term_keys, term_positions = _upper_term_pairs(data)
        device = data.pose_index.device
        pairs = None
        if choice == "sparse":
            pairs = PairStructure.build(edges, m, n)
            reduced = SparseReduced.build(torch.cat((pairs.key, term_keys)), B, m, config.ordering)
            pair_slots = reduced.slots(pairs.key)
        else:
            reduced = DenseReduced(B, m, _active_entries(data))
            pair_slots = None
        plan = LinearPlan(
            "schur",
            config.damping,
            reduced,
            edges,
            pairs,
            config.schur_chunk_size,
            shape,
            term_slots=reduced.slots(term_keys),
            term_positions=term_positions,
            pair_slots=pair_slots,
            diagonal_slots=reduced.slots(_diagonal_keys(B, m, device)),
            _data=data,
        )
        if edges.pose_index is data.pose_index:  # the edges are the observations: the
            # linearization's flat indices are the edge slots (one cached sparse matrix each)
            plan._cache["edges"] = (
                data.flat_pose_index.reshape(-1),
                data.flat_point_index.reshape(-1),
            )
        return plan

    @property
    def sparse(self) -> bool:
        """Whether the reduced system is factored sparsely."""
        return isinstance(self.reduced, SparseReduced)

    def factorize(
        self, lin: BlockLinearization | StructuredLinearization, lam: Tensor
    ) -> Factorization:
        """Factor the system of ``lin`` damped by ``lam`` (B,) (module doc)."""
        if self.method == "dense":
            if isinstance(lin, StructuredLinearization):
                raise ValueError(
                    "LinearPlan.factorize: the 'dense' method needs the block linearization"
                )
            return self._factorize_full(lin, lam)
        n = self.shape[2]
        # Damped (λ > 0): JᵀJ + λD is positive definite, so is its Schur complement S.
        definite = self.sparse and bool((lam > 0).all())
        U = damp(lin.pose_blocks, lam, self.damping)
        pose_slot, point_slot = self._edge_slots()
        if isinstance(lin, StructuredLinearization):
            v = lin.point_weight
            if self.damping == "levenberg":
                v_d = v + lam[:, None]
            else:
                v_d = v + lam[:, None] * v.clamp(1e-6, 1e32)
            w = lin.coupling_weight.reshape(-1)
            # The edges are the point observations (no term touches a point in this form).
            X_e = lin.observed_points
            X_e = lin.points.reshape(-1, 3)[point_slot] if X_e is None else X_e.reshape(-1, 3)
            elim = _StructuredElimination(w, X_e, v_d, pose_slot, point_slot, self.shape)
            if self.sparse and self._pairs().num_pairs > 0:
                pairs = self._pairs()
                coefficient = -(w[pairs.first] * w[pairs.second]) / v_d.reshape(-1)[pairs.point]
                mirror = pairs.same_pose & ~pairs.self_pair
                coefficient = torch.where(mirror, 2 * coefficient, coefficient)
                mono = monomials(lin.points.reshape(-1, 3)[pairs.point]) * coefficient[:, None]
                sums = mono.new_zeros(self.reduced.num_slots, 10)
                sums = sums.index_add(0, self.pair_slots, mono)
                upper = self._upper(U, lin) + blocks_from_monomials(sums)
                factor = self.reduced.factor(upper, None, definite)
            elif not self.sparse and n > 0:
                factor = self._factor_dense(U, lin, self._monomial_products(lin, v_d))
            else:
                factor = self.reduced.factor(self._upper(U, lin), None, definite)
            return Factorization(factor, elim, None, self.shape)
        V_inv, point_ok = self._point_inverse(lin, lam)
        W = lin.coupling.reshape(-1, 6, 3)
        elim = _BlockElimination(W, V_inv, pose_slot, point_slot, self.shape)
        instances = self._instances()
        if instances is not None:
            B = self.shape[0]
            C, Wt = instances.points_part(W, V_inv.reshape(-1, 3, 3), self.chunk_size, B)
            if Wt is not None:  # the back-substitution by instances: no zero rows, no edges
                elim = dataclasses.replace(elim, instances=(Wt, instances))
            factor = self._factor_dense(U, lin, -C)
            return Factorization(factor, elim, point_ok, self.shape)
        upper = self._upper(U, lin)
        if self._pairs().num_pairs:
            upper = self._subtract_pair_products(upper, W, V_inv, point_slot)
        return Factorization(self.reduced.factor(upper, None, definite), elim, point_ok, self.shape)

    def _subtract_pair_products(
        self, upper: Tensor, W: Tensor, V_inv: Tensor, point_slot: Tensor
    ) -> Tensor:
        """``upper`` (num_slots, 6, 6) less the points' part Σ_j W_ij V_j⁻¹ W_kjᵀ of every
        block (i, k), from the edge couplings W (E, 6, 3) and V⁻¹ (B·n, 3, 3): the pairs of
        each block cut into pieces of P ≤ ``PIECE`` pairs (:meth:`_pair_pieces`), so that a
        piece's sum Σ_p Y_p W_pᵀ (Y = W V⁻¹) is one (6 × 3P)·(3P × 6) product of a batched
        GEMM, ``PIECES_PER_STEP · PIECE`` pairs (at most the plan's chunk size) at a time (no
        per-pair (pairs, 6, 6) scratch).
        A pair of two edges of one pose (a diagonal block, not a self pair) adds Y_a W_bᵀ + its
        transpose."""
        first, second, slot, mirror = self._pair_pieces()
        size = first.shape[1]
        Y = W @ V_inv.reshape(-1, 3, 3)[point_slot]
        zero = W.new_zeros(1, 3, 6)
        # the blocks transposed (E + 1, 3, 6), a zero block last for the padding: a piece's
        # gathered rows are then its (3·PIECE × 6) operand as they lie
        Yt = torch.cat((Y.transpose(1, 2), zero))
        Wt = torch.cat((W.transpose(1, 2), zero))
        graph = torch.is_grad_enabled() and (W.requires_grad or V_inv.requires_grad)
        step = max(1, min(self.chunk_size, PIECES_PER_STEP * PIECE) // size)
        for start in range(0, slot.numel(), step):
            sl = slice(start, start + step)
            left = Yt[first[sl]].reshape(-1, 3 * size, 6)
            right = Wt[second[sl]].reshape(-1, 3 * size, 6)
            product = torch.bmm(left.transpose(1, 2), right)
            product = torch.where(
                mirror[sl, None, None], product + product.transpose(1, 2), product
            )
            if graph:
                upper = upper.index_add(0, slot[sl], product, alpha=-1.0)
            else:
                upper.index_add_(0, slot[sl], product, alpha=-1.0)
        return upper

    def _pair_pieces(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The edge pairs cut into pieces of P pairs of one upper block and kind (mirrored or
        not): first and second edge of each pair (Q, P) (the zero block E on the padding), the
        block's slot (Q,) and whether the piece is mirrored (Q,); built once per plan. P is the
        power of two up to ``PIECE`` that minimizes the padded pairs plus ``PIECE`` per piece
        (a piece's fixed cost): ``PIECE`` where blocks share hundreds of points (keyframes of
        a sequence), less where they share a few (a sparse bundle adjustment)."""

        def compute() -> tuple[Tensor, Tensor, Tensor, Tensor]:
            pairs = self._pairs()
            slots = self.pair_slots if self.pair_slots is not None else pairs.key
            blocks, block = torch.unique(slots, return_inverse=True)
            mirror = pairs.same_pose & ~pairs.self_pair
            group = 2 * block + mirror.long()
            counts = torch.bincount(group, minlength=2 * blocks.numel())
            counts = counts[counts > 0]

            def cost(size: int) -> int:
                per = (counts + size - 1) // size
                return int((per * size).sum()) + PIECE * int(per.sum())

            size = min((1 << k for k in range(PIECE.bit_length())), key=cost)
            items, group = pieces(group, 2 * blocks.numel(), size, -1)
            padding = items < 0
            edges = self.edges.pose_index.numel()
            first = torch.where(padding, edges, pairs.first[items.clamp_min(0)])
            second = torch.where(padding, edges, pairs.second[items.clamp_min(0)])
            return first, second, blocks[group // 2], group % 2 == 1

        return self._kept("pair_pieces", compute)

    def coupling_gemm_pays(self) -> bool:
        """Whether :meth:`factorize_coupling_gemm` applies (Schur method, dense reduced
        system) and pays: the points' part of S by one GEMM costs 216·m²·n flops per problem,
        the per-pair products 216 per pair of edges sharing a point (≈ E'²/(2n) for uniform
        visibility) but ~50× slower per flop (tiny batched products and scatters), so the
        GEMM wins from a co-visibility density E'/(m·n) of about 1/5 on."""
        if self.method != "schur" or self.sparse:
            return False
        _, m, n = self.shape
        return n > 0 and 5 * self.edges.pose_index.shape[1] >= m * n

    def factorize_coupling_gemm(self, lin: BlockLinearization, lam: Tensor) -> Factorization:
        """:meth:`factorize` of a block linearization for a dense reduced system, with the
        points' part of S formed by GEMM instead of per-pair products: the couplings summed
        into a dense (6m × 3n) matrix W per problem (edges of one pose and point add up), then
        S −= (W V⁻¹) Wᵀ, chunked over the points so that a chunk's W stays within
        ``STRUCTURED_CHUNK_ENTRIES`` entries. The same matrix as :meth:`factorize` up to
        rounding (the implicit backward's exact Hessian uses it, :mod:`.hessian`)."""
        if self.method != "schur" or self.sparse:
            raise ValueError(
                "LinearPlan.factorize_coupling_gemm: needs the Schur method with a dense "
                "reduced system"
            )
        B, m, n = self.shape
        U = damp(lin.pose_blocks, lam, self.damping)
        batch = torch.arange(B, device=U.device)[:, None]
        pose_slot, point_slot = self._edge_slots()
        V_inv, point_ok = self._point_inverse(lin, lam)
        W = lin.coupling.reshape(-1, 6, 3)
        elim = _BlockElimination(W, V_inv, pose_slot, point_slot, self.shape)
        Y = W @ V_inv.reshape(-1, 3, 3)[point_slot]
        pose_index, point_index = self.edges.pose_index, self.edges.point_index
        chunk = max(1, min(n, STRUCTURED_CHUNK_ENTRIES // max(1, B * 18 * m)))
        C = U.new_zeros(B, 6 * m, 6 * m)
        for start in range(0, n, chunk):
            c = min(chunk, n - start)
            if c == n:
                inside, local = None, point_index
            else:
                inside = ((point_index >= start) & (point_index < start + c)).reshape(-1)
                local = (point_index - start).clamp(0, c - 1)
            slots = ((batch * m + pose_index) * c + local).reshape(-1)
            dense = []
            for blocks in (W, Y):
                values = (
                    blocks if inside is None else torch.where(inside[:, None, None], blocks, 0.0)
                )
                D = blocks.new_zeros(B * m * c, 6, 3).index_add_(0, slots, values)
                dense.append(D.reshape(B, m, c, 6, 3).transpose(2, 3).reshape(B, 6 * m, 3 * c))
            C = C.baddbmm(dense[1], dense[0].transpose(1, 2), alpha=-1.0)
        return Factorization(self._factor_dense(U, lin, C), elim, point_ok, self.shape)

    def _has_term_pairs(self, lin: BlockLinearization | StructuredLinearization) -> bool:
        """Whether terms add blocks between two poses (off the diagonal of S)."""
        return lin.terms is not None and self.term_positions.numel() > 0

    def _upper(self, U: Tensor, lin: BlockLinearization | StructuredLinearization) -> Tensor:
        """The reduced system's upper blocks before the points' part: the damped pose blocks
        ``U`` (B, m, 6, 6) on the diagonal slots and the terms' pose pairs, (num_slots, 6, 6)."""
        upper = U.new_zeros(self.reduced.num_slots, 6, 6)
        upper = upper.index_add(0, self.diagonal_slots, U.reshape(-1, 6, 6))
        if self._has_term_pairs(lin):
            blocks = lin.terms.pair_blocks.reshape(-1, 6, 6)[self.term_positions]
            upper = upper.index_add(0, self.term_slots, blocks)
        return upper

    def _factor_dense(
        self, U: Tensor, lin: BlockLinearization | StructuredLinearization, points_part: Tensor
    ) -> _DenseCholesky:
        """Factor the dense S = pose side + ``points_part`` (B, 6m, 6m), which is overwritten;
        without term pairs the damped pose blocks ``U`` go straight onto its diagonal (no
        (B·m·m, 6, 6) slot buffer)."""
        if self._has_term_pairs(lin):
            return self.reduced.factor(self._upper(U, lin), points_part)
        return _DenseCholesky.of(DenseReduced.add_diagonal(points_part, U), self.reduced.active)

    def _kept(self, name: str, compute):
        """``compute()`` made once per plan, kept under ``name`` (normal tensors even when
        made in a solve's inference mode, so that what caches per index tensor, e.g.
        :func:`.segments.segment_sum`'s sparse matrices, keeps them too)."""
        value = self._cache.get(name)
        if value is None:
            with _inference.outside():
                value = self._cache[name] = compute()
        return value

    def _edge_slots(self) -> tuple[Tensor, Tensor]:
        """Flat pose slot b·m + i and point slot b·n + j of every coupling edge, (B·E',);
        made once per plan."""

        def compute() -> tuple[Tensor, Tensor]:
            B, m, n = self.shape
            batch = torch.arange(B, device=self.edges.pose_index.device)[:, None]
            return (
                (batch * m + self.edges.pose_index).reshape(-1),
                (batch * n + self.edges.point_index).reshape(-1),
            )

        return self._kept("edges", compute)

    def _point_inverse(self, lin: BlockLinearization, lam: Tensor) -> tuple[Tensor, Tensor]:
        """(V⁻¹ (B, n, 3, 3), ok (B,)) of the damped point blocks (:func:`spd_inverse_3x3`);
        a failure marks the whole problem (its V⁻¹ block is then I)."""
        V_inv, ok = spd_inverse_3x3(damp(lin.point_blocks, lam, self.damping))
        return V_inv, ok.all(dim=-1)

    def _instances(self) -> InstancePairs | None:
        """The :class:`InstancePairs` of a dense reduced system whose points are touched by
        terms (built once; None otherwise, or when too many signature pairs)."""
        if "instances" not in self._cache:
            value = None
            if not self.sparse and self._data is not None and point_terms(self._data):
                B, m, n = self.shape
                with _inference.outside():  # normal tensors: segment_sum keeps their matrices
                    value = InstancePairs.build(self._data, self.edges, B, m, n)
            self._cache["instances"] = value
        return self._cache["instances"]

    def _pairs(self) -> PairStructure:
        if self.pairs is None:
            _, m, n = self.shape
            self.pairs = PairStructure.build(self.edges, m, n)
        return self.pairs

    def _monomial_products(self, lin: StructuredLinearization, v_d: Tensor) -> Tensor:
        """−Σ_j (a_ij a_kj / v_j) G_jᵀ G_j, the points' part of S, as the (B, 6m, 6m) matrix,
        a_ij the coupling weight of point j in frame i (0 if none).

        The 6×6 block of G_jᵀ G_j is linear in the 10 monomials q_ab = s_a s_b of
        s = (1, x, y, z) (.linearize.blocks_from_monomials), so the 10 matrices
        Σ_j a_ij a_kj q_ab(X_j) / v_j are products P_a P_bᵀ of the four (m × n) matrices
        P_a = A·diag(s_a / √v): one batched GEMM per a of P_a by P_{a..3} (20·m²·n flops,
        no per-pair products; the (B, 4, m, c) operand is a third of a monomial-scaled one),
        chunked over c points within STRUCTURED_CHUNK_ENTRIES; up to SMALL_POSES poses one
        GEMM P Pᵀ of all 16 pairs instead (the same products, fewer operations). One small
        product with the constant ±1 selection (36 × 10, exact: each entry is a signed sum of
        at most three monomial sums) gives the 36 entries of every block, and one copy lays
        them out as the matrix.
        """
        B, m, n = self.shape
        point_index = self.edges.point_index
        # (B, 4, n) contiguous, so that P below comes out contiguous (B, 4, m, c)
        scale = v_d.rsqrt()[..., None]
        s = torch.cat((scale, lin.points * scale), -1).transpose(1, 2).contiguous()
        chunk = max(1, min(n, STRUCTURED_CHUNK_ENTRIES // max(1, B * 4 * m)))
        weight = lin.coupling_weight
        small = m <= SMALL_POSES
        parts: list[Tensor] = []
        for start in range(0, n, chunk):
            c = min(chunk, n - start)
            if c == n:  # one chunk: its slots are fixed for the solve
                A = v_d.new_zeros(B * m * n).index_add_(
                    0, self._covisibility_slots(), weight.reshape(-1)
                )
            else:
                inside = (point_index >= start) & (point_index < start + c)
                values = torch.where(inside, weight, torch.zeros_like(weight))
                local = (point_index - start).clamp(0, c - 1)
                A = v_d.new_zeros(B * m * c).index_add_(
                    0, self._edge_slots()[0] * c + local.reshape(-1), values.reshape(-1)
                )
            P = A.reshape(B, 1, m, c) * s[:, :, None, start : start + c]
            if small:  # one product P Pᵀ of all 16 pairs (few operations)
                factors = [(P.reshape(B, 4 * m, c), P.reshape(B, 4 * m, c))]
            else:  # the rows (b ≥ a, a) of C: P_{a..3} P_aᵀ
                factors = [(P[:, a:].reshape(B, (4 - a) * m, c), P[:, a]) for a in range(4)]
            for k, (left, right) in enumerate(factors):
                if start == 0:
                    parts.append(torch.bmm(left, right.transpose(1, 2)))
                else:
                    parts[k] = parts[k].baddbmm(left, right.transpose(1, 2))
        if small:  # the (b, a) blocks of P Pᵀ, (B, 16, m·m), b ≥ a selected below
            C = parts[0].reshape(B, 4, m, 4, m).transpose(2, 3).reshape(B, 16, m * m)
            blocks = _monomial_selection(C.dtype, C.device, all_pairs=True) @ C
        else:
            C = torch.cat(parts, 1)  # (B, 10 m, m): the 10 symmetric (m × m) sums
            blocks = _monomial_selection(C.dtype, C.device) @ C.reshape(B, 10, m * m)
        return blocks.reshape(B, 6, 6, m, m).permute(0, 3, 1, 4, 2).reshape(B, 6 * m, 6 * m)

    def _covisibility_slots(self) -> Tensor:
        """(b·m + i)·n + j of every coupling edge (pose i, point j), (B·E',): its entry of the
        (B, m, n) co-visibility matrix of :meth:`_monomial_products`; made once per plan."""
        n = self.shape[2]
        return self._kept(
            "covisibility",
            lambda: self._edge_slots()[0] * n + self.edges.point_index.reshape(-1),
        )

    def _factorize_full(self, lin: BlockLinearization, lam: Tensor) -> Factorization:
        """The full (6m + 3n)² system — small problems and cross-checks only. Assembled by
        out-of-place ``index_put`` (no writes through views), so autograd can differentiate
        through it (the unrolled backward)."""
        B, m, n = self.shape
        N = 6 * m + 3 * n
        device = lin.coupling.device
        U = damp(lin.pose_blocks, lam, self.damping)
        V = damp(lin.point_blocks, lam, self.damping)
        batch = torch.arange(B, device=device)

        def block_indices(count: int, offset: int, size: int) -> tuple[Tensor, ...]:
            """(batch, row, col) of the size × size diagonal blocks, (B, count, size, size)."""
            a = torch.arange(size, device=device)
            start = offset + size * torch.arange(count, device=device)[:, None, None]
            rows = (start + a[:, None]).expand(count, size, size)
            cols = (start + a[None, :]).expand(count, size, size)
            return torch.broadcast_tensors(batch[:, None, None, None], rows[None], cols[None])

        H = lin.coupling.new_zeros(B, N, N)
        H = H.index_put(block_indices(m, 0, 6), U)
        H = H.index_put(block_indices(n, 6 * m, 3), V)
        pose_index, point_index = self.edges.pose_index, self.edges.point_index
        rows = 6 * pose_index[..., None, None] + torch.arange(6, device=device)[:, None]
        cols = 6 * m + 3 * point_index[..., None, None] + torch.arange(3, device=device)
        rows, cols = torch.broadcast_tensors(rows, cols)  # (B, E', 6, 3)
        bidx = batch[:, None, None, None].expand_as(rows)
        H = H.index_put((bidx, rows, cols), lin.coupling, accumulate=True)
        H = H.index_put((bidx, cols, rows), lin.coupling, accumulate=True)  # the mirror Wᵀ
        if lin.terms is not None and lin.terms.pair_blocks.shape[1] > 0:
            P = lin.terms.pair_blocks.reshape(-1, 6, 6)
            pairs = P.new_zeros(B * m * m, 6, 6).index_add(0, self.term_keys, P)
            pairs = pairs.reshape(B, m, m, 6, 6).transpose(2, 3).reshape(B, 6 * m, 6 * m)
            H = H + torch.nn.functional.pad(pairs, (0, 3 * n, 0, 3 * n))
        return Factorization(_DenseCholesky.of(H), None, None, self.shape)


def _monomial_selection(
    dtype: torch.dtype, device: torch.device, all_pairs: bool = False
) -> Tensor:
    """The (36, 10) matrix of 0 and ±1 taking the monomial sums c of
    :meth:`LinearPlan._monomial_products` (order 1, x, y, z, xx, xy, xz, yy, yz, zz) to the
    36 entries (r, s) of the block −Σ c G_jᵀ G_j (:func:`.linearize.blocks_from_monomials`
    negated): top-left c_rs − δ_rs (c_xx + c_yy + c_zz), top-right −[(c_x, c_y, c_z)]×,
    bottom-left its transpose, bottom-right −c_1 I. Cached per dtype and device.

    ``all_pairs``: (36, 16) instead, for the 16 products P_b P_aᵀ in the order 4b + a, of
    which those with b ≥ a are the 10 sums above (the others get zero columns)."""
    key = ("monomial selection", all_pairs)
    return _series.constant(key, lambda: _selection_matrix(all_pairs), dtype, device)


def _selection_matrix(all_pairs: bool) -> Tensor:
    """:func:`_monomial_selection` in float64 on the CPU."""
    one, x, y, z, xx, xy, xz, yy, yz, zz = range(10)
    M = torch.zeros(6, 6, 10, dtype=torch.float64)
    second = ((xx, xy, xz), (xy, yy, yz), (xz, yz, zz))
    for r in range(3):
        for c in range(3):
            M[r, c, second[r][c]] += 1.0
            if r == c:
                M[r, c, [xx, yy, zz]] -= 1.0
    # top-right −[c]× with c = (c_x, c_y, c_z); bottom-left its transpose
    cross = {(0, 1): (z, 1.0), (0, 2): (y, -1.0), (1, 0): (z, -1.0), (1, 2): (x, 1.0)}
    cross |= {(2, 0): (y, 1.0), (2, 1): (x, -1.0)}
    for (r, c), (q, sign) in cross.items():
        M[r, 3 + c, q] = sign
        M[3 + c, r, q] = sign
    for r in range(3):
        M[3 + r, 3 + r, one] = -1.0
    M = M.reshape(36, 10)
    if all_pairs:
        pairs = [(a, b) for a in range(4) for b in range(a, 4)]  # the order of the 10
        wide = torch.zeros(36, 16, dtype=torch.float64)
        for q, (a, b) in enumerate(pairs):
            wide[:, 4 * b + a] = M[:, q]
        M = wide
    return M


def choose_reduced_solver(
    data: PointMapData,
    reduced_solver: str,
    dense_max_variables: int,
    ordering: str = "mmd",
    max_pairs: int = 10_000_000,
    edges: CouplingEdges | None = None,
) -> str:
    """ "dense" or "sparse" for ``reduced_solver`` "auto" (explicit choices are returned).

    Dense when 6m ≤ ``dense_max_variables``. Otherwise the block pattern of each problem's S
    (pose pairs sharing a point, from the sparse product A Aᵀ of its m × n co-visibility,
    and the terms' pose pairs) is ordered like the sparse path would and its symbolic
    factorization gives the work W = Σ_j c_j² (c_j entries in block column j of the factor):
    sparse when ``SPARSE_WORK_FACTOR``·W < m³ (the dense Cholesky's (6m)³/3 in the same
    units, 216 W vs 72 m³) for every problem. Band-like patterns (trajectories, pose graphs)
    go sparse; random or wide co-visibility, whose factor fills in, stays dense. When the
    edge pairs sharing a point exceed ``max_pairs`` (forming them would be the sparse path's
    cost too), dense.
    """
    if reduced_solver != "auto":
        return reduced_solver
    m, n = data.num_slots, data.num_points
    if 6 * m <= dense_max_variables:
        return "dense"
    edges = coupling_edges(data) if edges is None else edges
    B = edges.pose_index.shape[0]
    batch = torch.arange(B, device=edges.pose_index.device)[:, None]
    flat_point = (batch * n + edges.point_index)[edges.active]
    counts = torch.bincount(flat_point, minlength=B * n).reshape(B, -1)
    if int((counts * (counts + 1) // 2).sum()) > max_pairs:
        return "dense"
    keys = term_pair_keys(data).cpu()
    pose, point, active = (
        t.cpu().numpy() for t in (edges.pose_index, edges.point_index, edges.active)
    )
    import scipy.sparse  # lazily: import torchslam stays cheap

    for b in range(B):
        A = scipy.sparse.csr_matrix(
            (np.ones(int(active[b].sum())), (pose[b][active[b]], point[b][active[b]])),
            shape=(m, n),
        )
        covisible = scipy.sparse.triu(A @ A.T, k=1).tocoo()
        local = keys[b] % (m * m)
        first = np.concatenate((covisible.row, (local // m).numpy()))
        second = np.concatenate((covisible.col, (local % m).numpy()))
        work = factorization_work(m, first, second, ordering)
        if SPARSE_WORK_FACTOR * work >= float(m) ** 3:
            return "dense"
    return "sparse"
