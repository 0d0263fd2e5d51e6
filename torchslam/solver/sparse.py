"""Sparse Cholesky-type factorization of block-sparse symmetric systems (the reduced pose system).

With relative-pose terms and local co-visibility, the reduced pose system S (6m × 6m after
the Schur complement on the points) has a 6 × 6 block (i, k) only where poses i and k share a
point or a term: thousands of poses give a few nonzero blocks per row. A dense Cholesky of
S costs (6m)³/3 flops (15,000 × 15,000: about 10 s here); a sparse factorization with a
fill-reducing ordering costs a small fraction of that.

The pattern is fixed for a solve, so :class:`BlockPattern` does the symbolic work once:

- the unique upper blocks (b, i, k), i ≤ k, of the B systems, and for any list of block
  contributions the map that sums them into those blocks;
- per problem, a fill-reducing ordering of its m × m block graph (multiple minimum degree on
  Aᵀ + A from SuperLU, the ordering :mod:`torchslam.posegraph` uses), expanded to the 6 × 6
  blocks, and the CSC layout of the permuted full symmetric matrix P S Pᵀ with the position
  in its data array of every entry of every upper block and of its mirror.

Each factorization then is one gather into the CSC data array and SuperLU
(``scipy.sparse.linalg.splu``) in symmetric mode with diagonal pivots in that order: for an
SPD matrix that is its LDLᵀ factorization (SciPy has no sparse Cholesky; SuperLU exposes no
reusable symbolic factorization, so the ordering is what is reused). The factor's diagonal D
tells positive definiteness: a problem whose D has an entry ≤ 0 (or fails) is reported,
never raises (the solver skips the D check for damped systems, positive definite in exact
arithmetic: :meth:`BlockPattern.factor`). Factors are kept, so further right-hand sides (the
implicit backward of :mod:`.differentiable`) cost two triangular solves each, and
:func:`selected_inverse` gives the blocks of S⁻¹ on the factor's pattern (the covariances of
:mod:`torchslam.covariance`) by the block Takahashi recursion. SciPy works on the CPU: CUDA
tensors are moved to the CPU for the factorization and back.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

if TYPE_CHECKING:
    import scipy.sparse

__all__ = [
    "BlockPattern",
    "SelectedInverse",
    "SparseFactor",
    "factorization_work",
    "fill_reducing_order",
    "pivot_ratios",
    "selected_inverse",
]

# SuperLU's names of the orderings, applied to the block graph.
PERMC_SPEC = {"mmd": "MMD_AT_PLUS_A", "colamd": "COLAMD", "natural": "NATURAL"}


def fill_reducing_order(n: int, first: np.ndarray, second: np.ndarray, ordering: str) -> np.ndarray:
    """New position (n,) of each of n block variables, from SuperLU's column ordering of the
    graph with edges (first[e], second[e]) (entries < 0 or self-loops are ignored).

    SuperLU returns ``perm_c`` with perm_c[v] = the position of column v in the factor. The
    n × n pattern gets a dominant diagonal so that no pivoting disturbs the order. Ordering
    the n blocks instead of the 6n unknowns takes milliseconds and, expanded to blocks, gave
    the same fill as SuperLU's ordering of the full pattern on sphere2500.
    """
    if ordering == "natural" or n <= 1:
        return np.arange(n)
    import scipy.sparse.linalg  # lazily (here and below): import torchslam stays cheap

    both = (first >= 0) & (second >= 0) & (first != second)
    r = np.concatenate((np.arange(n), first[both], second[both]))
    c = np.concatenate((np.arange(n), second[both], first[both]))
    values = np.where(r == c, 4.0 * n, -1.0)
    pattern = scipy.sparse.csc_matrix((values, (r, c)), shape=(n, n))
    lu = scipy.sparse.linalg.splu(
        pattern,
        permc_spec=PERMC_SPEC[ordering],
        diag_pivot_thresh=0.0,
        options={"SymmetricMode": True},
    )
    return np.asarray(lu.perm_c)


def factorization_work(n: int, first: np.ndarray, second: np.ndarray, ordering: str) -> float:
    """Σ_j c_j², c_j the entries of column j of the Cholesky factor of an n-block pattern with
    edges (first[e], second[e]) in the fill-reducing order: proportional to the flops of its
    sparse factorization (a dense one: Σ_j (n − j)² ≈ n³/3)."""
    import scipy.sparse.linalg

    order = fill_reducing_order(n, first, second, ordering)
    both = (first >= 0) & (second >= 0) & (first != second)
    r = np.concatenate((np.arange(n), order[first[both]], order[second[both]]))
    c = np.concatenate((np.arange(n), order[second[both]], order[first[both]]))
    values = np.where(r == c, 4.0 * n, -1.0)
    pattern = scipy.sparse.csc_matrix((values, (r, c)), shape=(n, n))
    lu = scipy.sparse.linalg.splu(
        pattern, permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
    )
    counts = np.diff(lu.L.indptr).astype(np.float64)
    return float((counts * counts).sum())


@dataclass
class _Layout:
    """CSC layout of one problem's permuted full symmetric matrix."""

    # Range [start, stop) of this problem's blocks in the pattern's unique blocks.
    start: int
    stop: int
    # CSC arrays of P S Pᵀ, (6m)².
    indices: np.ndarray
    indptr: np.ndarray
    # data = values[start:stop].ravel()[source]: the entry of the blocks feeding each CSC entry.
    source: np.ndarray
    # Position of each original unknown 6i + a after the permutation, (6m,).
    position: np.ndarray


def _layout(start: int, i: np.ndarray, k: np.ndarray, order: np.ndarray, m: int) -> _Layout:
    """CSC layout of P S Pᵀ for the upper blocks (i, k), i ≤ k (the diagonal included), in
    O(blocks) arithmetic, without sorting entries.

    In the permuted numbering p = order, block column c holds the sorted block rows R_c of
    every block and mirror; its scalar column 6c + β lists rows 6r + α for r ∈ R_c, so entry
    (α, β) of the q-th block of the block-CSC order (in column c) sits at data position
    36·ptr[c] + 6·|R_c|·β + 6·(q − ptr[c]) + α. Upper block t = (i, k) with values V_t puts
    V_t[α, β] at rows 6·p_i + α, columns 6·p_k + β; its mirror (i ≠ k) puts the same value at
    rows 6·p_k + β, columns 6·p_i + α. Source index of V_t[α, β]: 36 t + 6 α + β.
    """
    a = np.arange(6)
    pi, pk = order[i], order[k]
    off = i != k
    block_cols = np.concatenate((pk, pi[off]))
    block_rows = np.concatenate((pi, pk[off]))
    keys = block_cols * m + block_rows  # unique: the upper blocks are
    sorted_keys = np.sort(keys)
    ptr = np.zeros(m + 1, dtype=np.int64)
    np.cumsum(np.bincount(block_cols, minlength=m), out=ptr[1:])
    count = np.diff(ptr)
    block_col, block_row = sorted_keys // m, sorted_keys % m
    q_of = np.searchsorted(sorted_keys, keys)  # block-CSC index of each block and mirror

    def positions(q: np.ndarray, c: np.ndarray, first: np.ndarray, second: np.ndarray):
        """Data positions of entries (row index first, column index second) of blocks q."""
        base = 36 * ptr[c] + 6 * (q - ptr[c])
        return base[:, None, None] + 6 * count[c][:, None, None] * second + first

    alpha, beta = a[:, None], a[None, :]  # V[α, β] at [α, β] of a (6, 6) grid
    T = i.shape[0]
    t = np.arange(T)
    source = 36 * t[:, None, None] + 6 * alpha + beta
    direct = positions(q_of[:T], pk, alpha, beta)
    mirror = positions(q_of[T:], pi[off], beta, alpha)
    nnz = 36 * sorted_keys.shape[0]
    data_source = np.empty(nnz, dtype=np.int64)
    data_source[direct.ravel()] = source.ravel()
    data_source[mirror.ravel()] = source[off].ravel()
    indices = np.empty(nnz, dtype=np.int64)
    all_blocks = np.arange(sorted_keys.shape[0])
    grid = positions(all_blocks, block_col, alpha, beta)
    indices[grid.ravel()] = np.broadcast_to(
        6 * block_row[:, None, None] + alpha, grid.shape
    ).ravel()
    indptr = np.append((36 * ptr[:-1, None] + 6 * count[:, None] * a[None, :]).ravel(), nnz)
    position = (6 * order[:, None] + a).ravel()
    return _Layout(
        start,
        start + T,
        indices.astype(np.int32),
        indptr.astype(np.int32),
        data_source,
        position,
    )


@dataclass
class BlockPattern:
    """The block pattern of B reduced systems of m 6 × 6 block rows (module doc)."""

    batch_size: int
    num_blocks: int
    # Unique upper blocks as sorted flat keys (b·m + i)·m + k with i ≤ k, (Q,).
    keys: Tensor
    layouts: list[_Layout]

    @staticmethod
    def build(
        keys: Tensor, batch_size: int, num_blocks: int, ordering: str = "mmd"
    ) -> tuple[BlockPattern, Tensor]:
        """The pattern of the upper blocks named by ``keys`` ((b·m + i)·m + k, i ≤ k, any
        order, repeats allowed; the diagonal blocks of every problem are always included).

        Returns:
            (pattern, slot): ``slot[t]`` is the unique block that ``keys[t]`` adds to.
        """
        B, m = batch_size, num_blocks
        device = keys.device
        diag = (torch.arange(B * m, device=device) * m) + torch.arange(m, device=device).repeat(B)
        unique, inverse = torch.unique(torch.cat((diag, keys)), sorted=True, return_inverse=True)
        keys_np = unique.cpu().numpy()
        b_of, rest = np.divmod(keys_np, m * m)
        row, col = np.divmod(rest, m)
        bounds = np.searchsorted(b_of, np.arange(B + 1))
        layouts = []
        for b in range(B):
            start, stop = int(bounds[b]), int(bounds[b + 1])
            i, k = row[start:stop], col[start:stop]
            order = fill_reducing_order(m, i, k, ordering)
            layouts.append(_layout(start, i, k, order, m))
        return BlockPattern(B, m, unique, layouts), inverse[B * m :]

    @property
    def num_unique(self) -> int:
        return self.keys.numel()

    def factor(self, values: Tensor, check_sign: bool = True) -> SparseFactor:
        """Factor the B systems whose upper blocks are ``values`` (Q, 6, 6).

        A zero pivot, a failure or a non-finite solution always marks a problem not ok; with
        ``check_sign`` (default) so does an entry of D ≤ 0. That check copies the whole
        factor (about 10% of a factorization on sphere2500): a caller whose matrix is positive
        definite in exact arithmetic (a damped system) may skip it: a factor made indefinite
        by round-off then gives a step that Levenberg-Marquardt judges by its model-decrease
        and gain tests like any other.
        """
        import scipy.sparse.linalg

        flat = values.detach().cpu().numpy().reshape(-1, 36)
        factors = []
        for layout in self.layouts:
            data = flat[layout.start : layout.stop].ravel()[layout.source]
            size = layout.indptr.shape[0] - 1
            matrix = scipy.sparse.csc_matrix(
                (data, layout.indices, layout.indptr), shape=(size, size)
            )
            try:
                lu = scipy.sparse.linalg.splu(
                    matrix,
                    permc_spec="NATURAL",
                    diag_pivot_thresh=0.0,
                    options={"SymmetricMode": True},
                )
                # An SPD matrix factors with its own diagonal pivots (no row swap) and its
                # LDLᵀ's D > 0; SuperLU swaps rows at a zero pivot, so check both.
                swapped = not np.array_equal(lu.perm_r, np.arange(size))
                if swapped or (check_sign and not bool((lu.U.diagonal() > 0).all())):
                    lu = None
            except RuntimeError:  # SuperLU: "Factor is exactly singular"
                lu = None
            factors.append(lu)
        return SparseFactor(self.layouts, factors, values.dtype, values.device)


@dataclass
class SparseFactor:
    """Factors of B block-sparse systems (None where the matrix is not positive definite)."""

    layouts: list[_Layout]
    factors: list[object | None]
    dtype: torch.dtype
    device: torch.device

    @property
    def ok(self) -> Tensor:
        """False where the factorization failed, bool (B,)."""
        return torch.tensor([f is not None for f in self.factors], device=self.device)

    def solve(self, rhs: Tensor) -> Tensor:
        """x with S x = rhs for each problem, rhs (B, 6m) → (B, 6m); zeros where not ok (a
        non-finite solution marks its problem not ok from then on)."""
        b_np = rhs.detach().cpu().numpy()
        out = np.zeros_like(b_np)
        for b, (layout, lu) in enumerate(zip(self.layouts, self.factors, strict=True)):
            if lu is None:
                continue
            permuted = np.empty_like(b_np[b])
            permuted[layout.position] = b_np[b]
            x = lu.solve(permuted)
            if np.isfinite(x).all():
                out[b] = x[layout.position]
            else:  # report it: the problem's factorization is unusable
                self.factors[b] = None
        return torch.from_numpy(out).to(device=self.device, dtype=self.dtype)

    def block_order(self, b: int) -> np.ndarray:
        """Position of each 6 × 6 block row of problem ``b`` in its factor, (m,)."""
        return self.layouts[b].position[::6] // 6

    def solve_columns(self, b: int, rhs: np.ndarray) -> np.ndarray:
        """X with S X = rhs for problem ``b`` (which must be ok), rhs (6m, c) → (6m, c)."""
        layout = self.layouts[b]
        permuted = np.empty_like(rhs)
        permuted[layout.position] = rhs
        return self.factors[b].solve(permuted)[layout.position]

    def selected_inverse(self, b: int) -> tuple[SelectedInverse, np.ndarray]:
        """(:func:`selected_inverse` of problem ``b``'s factor, :func:`pivot_ratios` in the
        original numbering (6m,)); problem ``b`` must be ok."""
        lu = self.factors[b]
        D = lu.U.diagonal()
        L = lu.L
        return selected_inverse(L, D), pivot_ratios(L, D)[self.layouts[b].position]


# ------------------------------------------------------------------------------------------
# Selected inverse: the blocks of S⁻¹ on the pattern of the factor (covariances)


@dataclass
class SelectedInverse:
    """The blocks Z_rc of Z = A⁻¹ on the block pattern of the factor L of A = L D Lᵀ
    (:func:`selected_inverse`), in the factor's (permuted) block numbering.

    The pattern of L contains the pattern of A's lower triangle, and each of its columns'
    block rows form a clique of it, so every block of A⁻¹ that A's pattern names (a diagonal
    block, two poses that share a point or a term) is here.
    """

    # Sorted keys c·n + r (r ≥ c) of the stored lower blocks, (K,).
    keys: np.ndarray
    # Z_rc for each key, (K, k, k).
    blocks: np.ndarray
    # Number n of block rows.
    num_blocks: int

    def lookup(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Blocks Z_rc for permuted block indices (rows[t], cols[t]) of any order: (T, k, k)
        (zero where not stored) and whether each was stored, bool (T,)."""
        lo, hi = np.minimum(rows, cols), np.maximum(rows, cols)
        wanted = lo * self.num_blocks + hi
        at = np.minimum(np.searchsorted(self.keys, wanted), max(self.keys.size - 1, 0))
        found = self.keys[at] == wanted if self.keys.size else np.zeros(wanted.shape, bool)
        blocks = np.where(found[:, None, None], self.blocks[at], 0.0)
        # Stored as (row ≥ col): Z_rc with r < c is the transpose of the stored Z_cr.
        return np.where((rows < cols)[:, None, None], blocks.transpose(0, 2, 1), blocks), found


def selected_inverse(L: scipy.sparse.spmatrix, D: np.ndarray, block: int = 6) -> SelectedInverse:
    """The blocks of A⁻¹ on the block pattern of L for A = L D Lᵀ (L unit lower triangular,
    D diagonal, size N = block · n): the block Takahashi recursion, from the last block column
    to the first,

        Z_SJ = −Z_SS M_J,   Z_JJ = (L_JJ D_J L_JJᵀ)⁻¹ − Z_SJᵀ M_J,   M_J = L_SJ L_JJ⁻¹,

    S the block rows of L's block column J below J (every block of Z it reads is on the
    pattern). Work Σ_J |S_J|² block products, the order of the factorization's; memory the
    factor's; never the dense inverse. ``L`` is SuperLU's ``lu.L`` of a symmetric matrix
    factored without pivoting and ``D`` its ``lu.U.diagonal()`` (U = D Lᵀ).
    """
    k = block
    N = L.shape[0]
    n = N // k
    coo = L.tocoo()
    lower = coo.row >= coo.col
    row = coo.row[lower].astype(np.int64)
    col = coo.col[lower].astype(np.int64)
    entry_keys = (col // k) * n + row // k
    keys = np.unique(entry_keys)
    while True:
        K = keys.size
        ptr = np.searchsorted(keys, np.arange(n + 1) * n)
        block_row = keys % n
        diagonal = ptr[:-1]  # the diagonal block comes first in its column (rows ≥ column)
        # Per column J, the |S_J|² blocks of Z_SS as positions in [Z; Zᵀ] (the transposed
        # copy serves the blocks above the diagonal), built for all columns at once.
        s = np.diff(ptr) - 1
        squares = s * s
        start = np.concatenate(([0], np.cumsum(squares)))
        column = np.repeat(np.arange(n), squares)
        local = np.arange(start[-1]) - start[column]
        size = np.maximum(s[column], 1)
        first = diagonal[column] + 1 + local // size
        second = diagonal[column] + 1 + local % size
        r1, r2 = block_row[first], block_row[second]
        wanted = np.minimum(r1, r2) * n + np.maximum(r1, r2)
        at = np.searchsorted(keys, wanted)
        missing = at >= K
        missing[~missing] = keys[at[~missing]] != wanted[~missing]
        if not missing.any():
            break
        # A block of the factor's structure that SuperLU did not store (its entries cancelled
        # to exact zeros): add it (with L = 0 there) and rebuild, so that every block the
        # recursion reads is on the pattern.
        keys = np.union1d(keys, wanted[missing])
    gather = at + K * (r1 < r2)
    Lb = np.zeros((K, k, k))
    Lb[np.searchsorted(keys, entry_keys), row % k, col % k] = coo.data[lower]
    inv_L = np.linalg.inv(Lb[diagonal])
    inv_A = (inv_L.transpose(0, 2, 1) / D.reshape(n, 1, k)) @ inv_L
    M = Lb @ inv_L[keys // n]
    Z = np.zeros((2 * K, k, k))
    for J in range(n - 1, -1, -1):
        d, sJ = diagonal[J], s[J]
        if sJ == 0:
            Z[d] = Z[K + d] = inv_A[J]
            continue
        Z_SS = Z[gather[start[J] : start[J + 1]]]
        Z_SS = Z_SS.reshape(sJ, sJ, k, k).transpose(0, 2, 1, 3).reshape(k * sJ, k * sJ)
        M_J = M[d + 1 : d + 1 + sJ].reshape(k * sJ, k)
        Z_SJ = -(Z_SS @ M_J)
        blocks = Z_SJ.reshape(sJ, k, k)
        Z[d + 1 : d + 1 + sJ] = blocks
        Z[K + d + 1 : K + d + 1 + sJ] = blocks.transpose(0, 2, 1)
        Z_JJ = inv_A[J] - Z_SJ.T @ M_J
        Z[d] = Z[K + d] = 0.5 * (Z_JJ + Z_JJ.T)
    return SelectedInverse(keys, Z[:K], n)


def pivot_ratios(L: scipy.sparse.spmatrix, D: np.ndarray) -> np.ndarray:
    """D_k / A_kk for A = L D Lᵀ, (N,): 1 for a variable independent of the earlier ones,
    → 0 as it becomes a combination of them (a singular A gives ~ round-off)."""
    squares = L.multiply(L).tocsr()
    return D / (squares @ D)
