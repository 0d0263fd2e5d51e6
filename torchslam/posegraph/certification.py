"""SE-Sync's dual certificate of global optimality for the SE-Sync objective.

Problem (Rosen, Carlone, Bandeira, Leonard, IJRR 2019, eq. 12; d = 3, or d = 2 for 2D graphs):

    f(R, t) = Σ_(i,j) κ_ij ‖R_j − R_i R̃_ij‖_F² + τ_ij ‖t_j − t_i − R_i t̃_ij‖²

over R_i ∈ SO(d), t_i ∈ ℝᵈ, weights (κ, τ) as SE-Sync's reader computes them
(:func:`torchslam.posegraph.objectives.graph_sesync_weights`).

Data matrices. With R = [R_1 … R_n] (d × dn) and t = [t_1 … t_n] (d × n), f = tr(X M Xᵀ),
X = [t R], for the symmetric matrix M = [[L_τ, V], [Vᵀ, L_ρ + Σ]] built edge by edge:

- L_τ (n × n): the τ-weighted graph Laplacian;
- V (n × dn): V[i, block i] += τ t̃ᵀ, V[j, block i] −= τ t̃ᵀ;
- L_ρ (dn × dn): the connection Laplacian, blocks (i, i) and (j, j) += κ I, (i, j) −= κ R̃_ij,
  (j, i) −= κ R̃_ijᵀ;  Σ (dn × dn): block (i, i) += τ t̃ t̃ᵀ.

Minimizing over t (translations eliminated analytically; one vertex anchored, which changes
nothing since 1ᵀV = 0) leaves f(R, t*(R)) = tr(R Q Rᵀ) with the rotation-only quadratic form

    Q = L_ρ + Σ − V_redᵀ L_τ,red⁻¹ V_red,

the "red" matrices without the anchored vertex's row (the paper's Q = L(G̃ρ) + T̃ᵀΩ^½ΠΩ^½T̃).
Q is dense; it is never formed: products Q x use the sparse matrices and one sparse
factorization of L_τ,red.

Certificate. At a candidate R, Λ = SymBlockDiag_d(Q Rᵀ R) (SE-Sync's ``compute_Lambda``:
Λ_i = sym((Q Rᵀ)_i R_i)) and S = Q − Λ. If S ⪰ 0, R is a global minimizer of f over SO(d)ⁿ
(and (R, t*(R)) of the SE-Sync problem): the SDP relaxation is exact there. Numerically the
test is λ_min(S) ≥ −η. For any R, tr(Λ) = f(R, t*) and the dual bound

    f* ≥ f(R, t*) + min(λ_min, 0) · d n

holds (the relaxation's feasible Z = YᵀY have tr Z = dn), so ``objective − lower_bound``
bounds the suboptimality.

Eigenvalue computation (SE-Sync's fast verification, on the reduced S). S − σI is the Schur
complement of the sparse symmetric matrix A(σ) = [[L_τ,red, V_red], [V_redᵀ, L_ρ + Σ − Λ − σI]]
with respect to its positive-definite block L_τ,red, so S − σI ≻ 0 ⟺ A(σ) ≻ 0, decided by a
sparse LDLᵀ-type factorization (SuperLU with a symmetric fill-reducing ordering and diagonal
pivots only: all pivots positive ⟺ positive definite, by Sylvester's law of inertia). SE-Sync
factors S + ηI the same way (Cholesky) and certifies when that succeeds. The value λ_min is
then computed by shift-and-invert Lanczos (ARPACK ``eigsh``) on (S − σI)⁻¹ with a shift σ
below the spectrum (σ = −η when certified; otherwise σ = −η·10ᵏ, the first that makes A(σ)
positive definite): the largest eigenvalue μ of (S − σI)⁻¹ gives λ_min = σ + 1/μ, accurate
relative to λ_min − σ.

Tolerance η. SE-Sync's C++ default is an absolute η = 1e-6 (its MATLAB default 1e-4). An
absolute η means little across data sets: S scales with the weights (multiplying every κ and
τ by c multiplies S by c), and by the dual bound above a given η admits a suboptimality of
up to η·dn. The default here is therefore relative to what it certifies: η = ε·f(R, t*)/(dn)
with ε = ``tolerance`` = 1e-6, so that "certified" means f(R, t*) − f* ≤ ε·f(R, t*) (at least
1e-12 · max diag M, a round-off floor for exact data where f = 0); ``relative=False`` takes
``tolerance`` as an absolute η, as SE-Sync does.

Conventions: vertex poses T_i = [[R_i, t_i], [0, 1]] body → world, edges Z_ij ≈ T_i⁻¹ T_j, as
:class:`torchslam.posegraph.PoseGraph`. Runs in NumPy/SciPy float64 on the CPU; not
differentiable.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
import scipy.sparse.linalg
import torch
from torch import Tensor

from torchslam import _checks
from torchslam.posegraph import objectives
from torchslam.posegraph.graph import PoseGraph

__all__ = ["Certificate", "SESyncMatrices", "certify", "sesync_matrices"]

# Default relative suboptimality ε of the certificate (module docstring).
DEFAULT_TOLERANCE = 1e-6
# Round-off floor of η, relative to the largest diagonal entry of M.
_ROUNDOFF = 1e-12


@dataclass(frozen=True)
class Certificate:
    """Outcome of :func:`certify` (module docstring)."""

    # λ_min(S) ≥ −η: the rotations (and their optimal translations) are a global minimizer
    # of the SE-Sync objective.
    certified: bool
    # Smallest eigenvalue of S = Q − Λ.
    lambda_min: float
    # f(R, t*(R)) = tr(R Q Rᵀ): the SE-Sync objective at the candidate's rotations with their
    # optimal translations (≤ the objective at the candidate's own translations).
    objective: float
    # A lower bound on the global minimum: objective + min(λ_min, 0)·d·n.
    lower_bound: float
    # The tolerance η used (absolute).
    eta: float
    # 3 (SE(3)) or 2 (SE(2)).
    dimension: int
    # Number of vertices n.
    num_poses: int
    # Wall-clock seconds of the certification.
    seconds: float

    @property
    def suboptimality_bound(self) -> float:
        """objective − lower_bound ≥ objective − f*."""
        return self.objective - self.lower_bound

    def summary(self) -> str:
        """``certified global optimum: yes|no (λ_min = …)``."""
        return (
            f"certified global optimum: {'yes' if self.certified else 'no'} "
            f"(λ_min = {self.lambda_min:.3e}, η = {self.eta:.1e}; SE-Sync objective "
            f"{self.objective:.8g}, lower bound {self.lower_bound:.8g})"
        )


@dataclass(frozen=True)
class SESyncMatrices:
    """The sparse data of the SE-Sync problem of a graph (module docstring), float64 SciPy
    CSR matrices: ``rotation`` = L_ρ + Σ (dn × dn), ``coupling`` = V (n × dn),
    ``translation`` = L_τ (n × n); ``d`` and ``n``."""

    rotation: scipy.sparse.csr_matrix
    coupling: scipy.sparse.csr_matrix
    translation: scipy.sparse.csr_matrix
    d: int
    n: int

    @property
    def full(self) -> scipy.sparse.csr_matrix:
        """M = [[L_τ, V], [Vᵀ, L_ρ + Σ]], ((d + 1) n)², with f(R, t) = tr([t R] M [t R]ᵀ)."""
        return scipy.sparse.bmat(
            [[self.translation, self.coupling], [self.coupling.T, self.rotation]], format="csr"
        )

    def _reduced_solver(self):
        cached = getattr(self, "_solver", None)
        if cached is None:
            reduced = self.translation[1:, 1:].tocsc()
            if self.n > 1:
                cached = scipy.sparse.linalg.splu(
                    reduced, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0
                )
            else:
                cached = False
            object.__setattr__(self, "_solver", cached)
        return cached

    def q_product(self, X: np.ndarray) -> np.ndarray:
        """Q X for X of shape (dn,) or (dn, k), Q the rotation-only form (module docstring)."""
        out = self.rotation @ X
        solver = self._reduced_solver()
        if solver is not False:
            W = self.coupling[1:] @ X
            out = out - self.coupling[1:].T @ solver.solve(np.asarray(W))
        return out

    def translations(self, R: np.ndarray) -> np.ndarray:
        """t*(R) (d × n), the translations minimizing f for rotations R (d × dn), t_0 = 0."""
        t = np.zeros((self.d, self.n))
        solver = self._reduced_solver()
        if solver is not False:
            # ∂f/∂t = 2 (t L_τ + R Vᵀ) = 0 with t_0 = 0.
            t[:, 1:] = -solver.solve(np.asarray(self.coupling[1:] @ R.T)).T
        return t


def _check_graph(fn: str, graph: object) -> PoseGraph:
    if not isinstance(graph, PoseGraph):
        raise TypeError(
            f"{fn}: argument 'graph' must be a PoseGraph, got {_checks.describe(graph)}"
        )
    return graph


def sesync_matrices(graph: PoseGraph) -> SESyncMatrices:
    """The sparse SE-Sync data matrices of a graph (:class:`SESyncMatrices`), d = 2 for 2D
    graphs (the top-left 2 × 2 rotation blocks and (x, y) translations of the measurements).

    Raises:
        ValueError: when the SE-Sync weights are undefined (information blocks not positive
            definite, :func:`torchslam.posegraph.objectives.graph_sesync_weights`).
    """
    fn = "sesync_matrices"
    graph = _check_graph(fn, graph)
    kappa, tau = objectives.graph_sesync_weights(graph, fn)
    d = 2 if graph.dimension == 2 else 3
    n = graph.num_vertices
    kappa = kappa.detach().cpu().to(torch.float64).numpy()
    tau = tau.detach().cpu().to(torch.float64).numpy()
    edges = graph.edges.cpu().numpy()
    Z = graph.measurements.detach().cpu().to(torch.float64).numpy()
    Rm, tm = Z[:, :d, :d], Z[:, :d, 3]
    i, j = edges[:, 0], edges[:, 1]
    E = edges.shape[0]
    k = np.arange(d)

    # L_τ.
    rows = np.concatenate((i, j, i, j))
    cols = np.concatenate((i, j, j, i))
    vals = np.concatenate((tau, tau, -tau, -tau))
    translation = scipy.sparse.coo_matrix((vals, (rows, cols)), shape=(n, n)).tocsr()

    # V: V[i, d i + k] = τ t̃_k, V[j, d i + k] = −τ t̃_k.
    block_i = d * i[:, None] + k[None, :]  # (E, d)
    rows = np.concatenate((np.repeat(i, d), np.repeat(j, d)))
    cols = np.concatenate((block_i.reshape(-1), block_i.reshape(-1)))
    tv = (tau[:, None] * tm).reshape(-1)
    coupling = scipy.sparse.coo_matrix(
        (np.concatenate((tv, -tv)), (rows, cols)), shape=(n, d * n)
    ).tocsr()

    # L_ρ + Σ.
    block_j = d * j[:, None] + k[None, :]
    r_ii = np.broadcast_to(block_i[:, :, None], (E, d, d))
    c_ii = np.broadcast_to(block_i[:, None, :], (E, d, d))
    r_jj = np.broadcast_to(block_j[:, :, None], (E, d, d))
    c_jj = np.broadcast_to(block_j[:, None, :], (E, d, d))
    eye = np.eye(d)
    diag = kappa[:, None, None] * eye
    sigma = tau[:, None, None] * tm[:, :, None] * tm[:, None, :]
    off = -kappa[:, None, None] * Rm  # block (i, j); block (j, i) is its transpose
    # Block (i, j) = off: entry (d i + r, d j + c) = off[r, c]; block (j, i) = offᵀ: entry
    # (d j + c, d i + r) = off[r, c]. At [r, c]: r_ii = d i + r, c_jj = d j + c.
    rows = np.concatenate([a.reshape(-1) for a in (r_ii, r_jj, r_ii, c_jj)])
    cols = np.concatenate([a.reshape(-1) for a in (c_ii, c_jj, c_jj, r_ii)])
    vals = np.concatenate(
        [(diag + sigma).reshape(-1), diag.reshape(-1), off.reshape(-1), off.reshape(-1)]
    )
    rotation = scipy.sparse.coo_matrix((vals, (rows, cols)), shape=(d * n, d * n)).tocsr()
    return SESyncMatrices(rotation, coupling, translation, d, n)


def _rotations(fn: str, graph: PoseGraph, poses: Tensor | None, d: int) -> np.ndarray:
    """R = [R_1 … R_n] (d × dn) of the poses (each d × d block projected onto SO(d))."""
    if poses is None:
        poses = graph.poses
    _checks.check_tensor(fn, "poses", poses, (graph.num_vertices, 4, 4), min_batch_dims=0)
    if poses.dim() != 3:
        raise ValueError(
            f"{fn}: argument 'poses' must have shape ({graph.num_vertices}, 4, 4), got "
            f"{tuple(poses.shape)}"
        )
    _checks.check_finite(fn, "poses", poses)
    blocks = poses.detach().cpu().to(torch.float64).numpy()[:, :d, :d]
    U, _, Vt = np.linalg.svd(blocks)
    D = np.ones((blocks.shape[0], d))
    D[:, -1] = np.sign(np.linalg.det(U @ Vt))
    projected = (U * D[:, None, :]) @ Vt
    return projected.transpose(1, 0, 2).reshape(d, -1)


def _lambda_blocks(matrices: SESyncMatrices, R: np.ndarray) -> np.ndarray:
    """Λ_i = sym((Q Rᵀ)_i R_i), (n, d, d)."""
    d, n = matrices.d, matrices.n
    QRt = np.asarray(matrices.q_product(R.T)).reshape(n, d, d)  # (Q Rᵀ)_i, d × d
    P = QRt @ R.reshape(d, n, d).transpose(1, 0, 2)
    return 0.5 * (P + P.transpose(0, 2, 1))


def _block_diagonal(blocks: np.ndarray) -> scipy.sparse.csr_matrix:
    n, d, _ = blocks.shape
    base = d * np.arange(n)[:, None, None]
    rows = base + np.arange(d)[None, :, None] + np.zeros((1, 1, d), dtype=int)
    cols = base + np.arange(d)[None, None, :] + np.zeros((1, d, 1), dtype=int)
    return scipy.sparse.coo_matrix(
        (blocks.reshape(-1), (rows.reshape(-1), cols.reshape(-1))), shape=(d * n, d * n)
    ).tocsr()


class _ShiftedFactor:
    """Sparse factorization of A(σ) = [[L_τ,red, V_red], [V_redᵀ, L_ρ + Σ − Λ − σI]] with
    diagonal pivots only; ``positive_definite`` tells whether S − σI ≻ 0."""

    def __init__(self, upper_left, coupling, lower_right, sigma: float) -> None:
        m = upper_left.shape[0]
        size = lower_right.shape[0]
        shifted = lower_right - sigma * scipy.sparse.identity(size, format="csr")
        self.offset = m
        self.size = size
        A = (
            scipy.sparse.bmat([[upper_left, coupling], [coupling.T, shifted]], format="csc")
            if m
            else shifted.tocsc()
        )
        self.positive_definite = False
        self.lu = None
        try:
            lu = scipy.sparse.linalg.splu(
                A,
                permc_spec="MMD_AT_PLUS_A",
                diag_pivot_thresh=0.0,
                options={"SymmetricMode": True},
            )
        except RuntimeError:  # an exactly singular pivot
            return
        pivots = lu.U.diagonal()
        symmetric = np.array_equal(lu.perm_r, lu.perm_c)
        self.positive_definite = bool(symmetric and np.all(pivots > 0))
        self.lu = lu

    def solve_rotation(self, x: np.ndarray) -> np.ndarray:
        """(S − σI)⁻¹ x through A(σ) [y_t; y_R] = [0; x]."""
        rhs = np.zeros(self.offset + self.size)
        rhs[self.offset :] = x
        return self.lu.solve(rhs)[self.offset :]


def certify(
    graph: PoseGraph,
    poses: Tensor | None = None,
    *,
    tolerance: float = DEFAULT_TOLERANCE,
    relative: bool = True,
) -> Certificate:
    """SE-Sync's certificate of global optimality of the rotations of ``poses`` for the
    SE-Sync objective (module docstring).

    The certificate concerns the SE-Sync objective (eq. 12), whatever objective produced the
    poses: certify the solution of ``solve_pose_graph(..., config=PoseGraphSolverConfig(
    objective="sesync"))`` (a standard-cost ("chi2") optimum is not a critical point of the
    SE-Sync objective, so its certificate is "no" in general; refine it with the SE-Sync
    objective first, as ``torchslam posegraph --certify`` does).

    Args:
        graph: the pose graph (connected); 2D graphs are certified in SE(2).
        poses: candidate poses (N, 4, 4), body → world; ``graph.poses`` when None. Only their
            rotations matter (each d × d block is projected onto SO(d); for 2D graphs the
            top-left 2 × 2 blocks), the translations are eliminated.
        tolerance: the relative suboptimality ε certified (η = ε·f/(dn), module docstring),
            or the absolute η when ``relative`` is False; ≥ 0.
        relative: whether ``tolerance`` is relative (default) or an absolute η.

    Returns:
        A :class:`Certificate`.

    Raises:
        ValueError, TypeError: bad arguments, a disconnected graph, undefined weights.
    """
    fn = "certify"
    start = time.perf_counter()
    graph = _check_graph(fn, graph)
    if isinstance(tolerance, bool) or not isinstance(tolerance, (int, float)):
        raise TypeError(f"{fn}: argument 'tolerance' must be a float, got {tolerance!r}")
    if not (np.isfinite(tolerance) and tolerance >= 0):
        raise ValueError(f"{fn}: argument 'tolerance' must be finite and ≥ 0, got {tolerance!r}")
    if not isinstance(relative, bool):
        raise TypeError(f"{fn}: argument 'relative' must be a bool, got {relative!r}")
    d = 2 if graph.dimension == 2 else 3
    R = _rotations(fn, graph, poses, d)
    matrices = sesync_matrices(graph)
    n = matrices.n
    if n > 1:
        components, _ = scipy.sparse.csgraph.connected_components(
            matrices.translation, directed=False
        )
        if components > 1:
            raise ValueError(
                f"{fn}: the graph must be connected (its edges join its {n} vertices into "
                f"{components} components); certify each component on its own"
            )
    blocks = _lambda_blocks(matrices, R)
    objective = float(np.trace(blocks, axis1=1, axis2=2).sum())
    dn = d * n
    scale = max(
        float(matrices.rotation.diagonal().max(initial=0.0)),
        float(matrices.translation.diagonal().max(initial=0.0)),
    )
    if relative:
        eta = max(float(tolerance) * max(objective, 0.0) / dn, _ROUNDOFF * scale)
    else:
        eta = float(tolerance)
    lower_right = (matrices.rotation - _block_diagonal(blocks)).tocsr()
    upper_left = matrices.translation[1:, 1:]
    coupling = matrices.coupling[1:]

    factor = _ShiftedFactor(upper_left, coupling, lower_right, -eta)
    certified = factor.positive_definite
    sigma = -eta
    if not certified:
        # Find a shift below the spectrum: −η·10ᵏ (λ_min ≥ −‖S‖, so this ends).
        step = max(eta, _ROUNDOFF * scale, 1e-300)
        for _ in range(400):
            step *= 10.0
            factor = _ShiftedFactor(upper_left, coupling, lower_right, -step)
            if factor.positive_definite:
                sigma = -step
                break
        else:  # pragma: no cover - unreachable for finite data
            raise RuntimeError(f"{fn}: no shift below the spectrum of S was found")
    if dn <= 3:
        S_inv = np.stack([factor.solve_rotation(e) for e in np.eye(dn)], axis=1)
        mu = float(np.linalg.eigvalsh(0.5 * (S_inv + S_inv.T))[-1])
    else:
        op = scipy.sparse.linalg.LinearOperator(
            (dn, dn), matvec=factor.solve_rotation, dtype=np.float64
        )
        v0 = R[0] + 0.03 * np.linalg.norm(R[0]) * np.random.default_rng(0).standard_normal(dn)
        mu = float(
            scipy.sparse.linalg.eigsh(
                op, k=1, which="LA", tol=1e-10, v0=v0, return_eigenvectors=False
            )[0]
        )
    lambda_min = sigma + 1.0 / mu
    return Certificate(
        certified=bool(certified),
        lambda_min=lambda_min,
        objective=objective,
        lower_bound=objective + min(lambda_min, 0.0) * dn,
        eta=eta,
        dimension=d,
        num_poses=n,
        seconds=time.perf_counter() - start,
    )
