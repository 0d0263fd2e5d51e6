"""Linearize: residuals and Jacobians at the current estimate → normal-equation blocks.

Two forms, chosen per iteration by :func:`linearize`; both are summed from per-observation
quantities by :func:`.segments.segment_sum` (``index_add``) — never a dense J.

**Block form** (general: information matrices, the ``jacrev`` Jacobian mode, robust kernels
with curvature correction). For each observation e = (i, j), the whitened residual r̃ = Lᵀ r
(Ω = L Lᵀ) and blocks J̃ = Lᵀ [J_r_xi | J_r_point] are robustified with Ceres' corrector
(:func:`torchslam.losses.triggs_correction`), then (for scalar weights w, r and J are not
whitened and every product below is multiplied by w: no √w, whose derivative is infinite
at w = 0)

    U_i = Σ_e J̃_ξᵀ J̃_ξ (6×6),  V_j = Σ_e J̃_Xᵀ J̃_X (3×3),  W_e = J̃_ξᵀ J̃_X (6×3),
    g_i = Σ_e J̃_ξᵀ r̃,          g_j = Σ_e J̃_Xᵀ r̃.

**Structured form** (the ICP-SLAM fast path: scalar weights, analytic Jacobians, no curvature
correction — always the case for Huber, Cauchy and Tukey under Ceres' clamp). The analytic
blocks factor as J_ξ = J_X · G_j with J_X = −R_i and G_j = [ −[X_j]× | I ] (see
:mod:`torchslam.jacobians`), so with an effective scalar weight w_e (weight × ρ'):

    J̃_Xᵀ J̃_X = w_e I,   W_e = w_e G_jᵀ,   U_i = Σ_e w_e G_jᵀ G_j,   V_j = v_j I with v_j = Σ_e w_e,
    G_jᵀ G_j = [[ |X|² I − X Xᵀ, [X]× ], [ −[X]×, I ]],

so every block is a weighted sum of the 10 monomials (1, x, y, z, x², y², z², xy, xz, yz) of
X_j. The Schur complement then needs no per-pair products at all (see :mod:`.plan`).

**Terms** (:mod:`torchslam.terms`: relative poses, priors, point observations, user terms).
Instance k of a term touches poses i_1 … i_a and, for a term with ``point_index``, one point
j, with whitened, robustified residual r̃_k and blocks J̃_k = [J̃_1 … J̃_a | J̃_X] (d × (6a + 3)),
formed by the same routine as the point observations' blocks (:func:`instance_blocks`). It
adds J̃_aᵀr̃ to g_(i_a) and J̃_aᵀJ̃_a to U_(i_a) (folded into ``pose_blocks`` and
``pose_gradient`` of either form, so damping and Schur see the whole pose Hessian), the
off-diagonal products J̃_aᵀJ̃_b (a ≠ b) to block (i_a, i_b) of the reduced pose system, kept
as :class:`TermLinearization` ``pair_blocks`` (:mod:`.plan` adds them to S, dense or
sparse), and for a point J̃_XᵀJ̃_X to V_j, J̃_Xᵀr̃ to g_j and one coupling block
W = J̃_aᵀJ̃_X per (pose, point) pair, appended to ``coupling`` in the order of
:func:`coupling_edges`. A term that touches points needs the block form.

Fixed poses/points and padding contribute nothing; fixed variables get an identity block and
a zero gradient, so their step is exactly zero.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from torchslam import jacobians, losses
from torchslam._batched import matmul, sum_last
from torchslam.lie import _series, se3
from torchslam.objective.data import (
    PointMapData,
    gather_points,
    per_observation,
    weight_products,
)
from torchslam.objective.terms import (
    Term,
    _cached,
    point_observation_jacobians,
    term_all_valid,
    term_blocks,
    term_fixed_rows,
    term_parameters,
    term_points,
    term_poses,
    term_rows,
    term_whitening,
    terms_cost,
)
from torchslam.objective.whitening import whiten, whitening
from torchslam.solver.segments import pieces, segment_sum, unique_rows

__all__ = [
    "BlockLinearization",
    "CouplingEdges",
    "StructuredLinearization",
    "TermLinearization",
    "cost_at",
    "coupling_edges",
    "instance_blocks",
    "linearize",
    "linearize_terms",
    "model_decrease",
    "monomials",
    "point_terms",
    "term_pair_keys",
    "whitening_factors",
]


@dataclass(frozen=True)
class CouplingEdges:
    """Every pose-point coupling block W_e of the objective (fixed for a solve).

    The order is the order of :attr:`BlockLinearization.coupling`: the point observations of
    ``data`` first, then, term by term (in ``data.terms`` order), each instance of a term that
    touches a point, one edge per pose of the instance (instance-major: (k, a) → k·arity + a).
    The Schur complement eliminates the points through these edges only.
    """

    # Pose and point of each edge, long (B, E').
    pose_index: Tensor
    point_index: Tensor
    # The edge couples a free pose with a free point of a valid entry, bool (B, E').
    active: Tensor


def point_terms(data: PointMapData) -> tuple[Term, ...]:
    """The terms of ``data`` that touch points (a problem without points has none: padding)."""
    if data.num_points == 0:
        return ()
    return tuple(term for term in data.terms if term.has_point)


def coupling_edges(data: PointMapData) -> CouplingEdges:
    """The :class:`CouplingEdges` of ``data``: its point observations, then the pose-point
    pairs of its terms that touch points."""
    pose, point, valid = [data.pose_index], [data.point_index], [data.valid]
    B = data.pose_index.shape[0]
    for term in point_terms(data):
        K, a = term.slot_index.shape[1:]
        pose.append(term.slot_index.reshape(B, K * a))
        point.append(term.point_index[..., None].expand(B, K, a).reshape(B, K * a))
        valid.append(term.valid[..., None].expand(B, K, a).reshape(B, K * a))
    if len(pose) > 1:
        pose, point, valid = (torch.cat(x, dim=1) for x in (pose, point, valid))
    else:
        pose, point, valid = pose[0], point[0], valid[0]
    active = (
        valid
        & ~torch.gather(data.fixed_slots, 1, pose)
        & ~torch.gather(data.fixed_points, 1, point)
    )
    return CouplingEdges(pose, point, active)


@dataclass
class TermLinearization:
    """The terms' share of the normal equations (B problems, m poses, n points)."""

    # ½ Σ ρ(s) of all terms, (B,).
    cost: Tensor
    # Σ J̃ᵀr̃ per pose, (B, m, 6), and Σ J̃_aᵀJ̃_a per pose, (B, m, 6, 6).
    gradient: Tensor
    diagonal: Tensor
    # J̃_aᵀJ̃_b for a ≠ b of every instance of every term, (B, P, 6, 6), in the order of
    # :func:`term_pair_keys`.
    pair_blocks: Tensor
    # Robustified blocks J of each term, (B, K_t, d_t, 6·a_t [+ 3]): the a_t pose blocks side
    # by side, then the point block for a term that touches a point; whitened by U for
    # information matrices; with scalar weights w they are not whitened (no √w: its
    # derivative is infinite at w = 0) and ``scales`` holds w, (B, K_t) (ones otherwise):
    # J̃ᵀJ̃ = w JᵀJ.
    jacobians: tuple[Tensor, ...]
    scales: tuple[Tensor, ...]
    # Σ J̃_Xᵀr̃ per point, (B, n, 3), and Σ J̃_XᵀJ̃_X per point, (B, n, 3, 3) (zero without
    # terms that touch points).
    point_gradient: Tensor | None = None
    point_diagonal: Tensor | None = None
    # W = J̃_aᵀJ̃_X of the terms' coupling edges, (B, E' − E, 6, 3), in the order of
    # :func:`coupling_edges` after the point observations.
    coupling: Tensor | None = None


@dataclass
class BlockLinearization:
    """General normal-equation blocks of B problems (shapes in the module doc)."""

    # Current cost ½ Σ ρ(s), (B,).
    cost: Tensor
    # Gradient w.r.t. poses, (B, m, 6), and points, (B, n, 3).
    pose_gradient: Tensor
    point_gradient: Tensor
    # Pose blocks U, (B, m, 6, 6).
    pose_blocks: Tensor
    # Point blocks V, (B, n, 3, 3).
    point_blocks: Tensor
    # Robustified residuals r̃ of the point observations, (B, E, 3): whitened for
    # information matrices, not for scalar weights (then ``scale`` holds w).
    residuals: Tensor
    # Robustified Jacobian blocks [J̃_ξ | J̃_X] of the point observations, (B, E, 3, 9),
    # whitened as ``residuals``.
    jacobian: Tensor
    # Pose-point blocks W_e of every coupling edge, (B, E', 6, 3), in the order of
    # :func:`coupling_edges` (the point observations first, then the terms' edges).
    coupling: Tensor
    # The terms (already folded into cost, gradients, pose_blocks, point_blocks and
    # coupling), or None.
    terms: TermLinearization | None = None
    # Scalar weights w of the point observations, (B, E) (0 on padding), or None.
    scale: Tensor | None = None
    # The poses T = Exp(ξ) the linearization was taken at, (B, m, 4, 4) (the retraction
    # reuses them), or None.
    poses: Tensor | None = None


@dataclass
class StructuredLinearization:
    """ICP-SLAM normal equations in the factored form of the module doc."""

    # Current cost ½ Σ ρ(s), (B,).
    cost: Tensor
    # Gradient w.r.t. poses, (B, m, 6), and points, (B, n, 3).
    pose_gradient: Tensor
    point_gradient: Tensor
    # Pose blocks U, (B, m, 6, 6).
    pose_blocks: Tensor
    # v_j with V_j = v_j I, (B, n) (1 for fixed points).
    point_weight: Tensor
    # Effective weight w_e = weight · ρ' of each observation, (B, E) (0 on padding).
    weight: Tensor
    # w_e where both the pose and the point of e are free (the coupling W_e = w_e G_jᵀ), (B, E).
    coupling_weight: Tensor
    # Current points X_j, (B, n, 3) (G_j depends on them).
    points: Tensor
    # Masks: pose / point of each observation is free, (B, E).
    free_pose: Tensor
    free_point: Tensor
    # The pose terms (already folded into cost, pose_gradient, pose_blocks), or None.
    terms: TermLinearization | None = None
    # The poses T = Exp(ξ) the linearization was taken at, (B, m, 4, 4), or None.
    poses: Tensor | None = None
    # The point X_j(e) of each observation, (B, E, 3) (``points`` gathered), or None.
    observed_points: Tensor | None = None


def whitening_factors(data: PointMapData) -> Tensor | None:
    """Lᵀ with Ω = L Lᵀ per observation (B, E, 3, 3), √w (B, E), or None for unit weights."""
    return whitening(data.masked_weights(), data.masked_information())


def monomials(points: Tensor) -> Tensor:
    """(1, x, y, z, x², y², z², xy, xz, yz) of points (..., 3) → (..., 10)."""
    # Whole-row products of slices (x·(y, z) and y·z), one cat: few operations, and no gather
    # along the last dim (several times slower per entry on the many observations of a batch).
    one = _series.constant("one", (1.0,), points.dtype, points.device)
    x, y, yz = points[..., :1], points[..., 1:2], points[..., 1:]
    return torch.cat(
        (one.expand(*points.shape[:-1], 1), points, points * points, x * yz, y * points[..., 2:]),
        dim=-1,
    )


# blocks_from_monomials: entry (r, c) of the 6 × 6 block, row-major, as an index into
# (c (10), −c (10), trace − (cxx, cyy, czz) (3), 0) with c = (c1, cx, cy, cz, cxx, cyy, czz,
# cxy, cxz, cyz): [[trace·I − S, [c]×], [−[c]×, c1·I]] (module doc), S the second moments.
_BLOCK_ENTRIES = (
    *(20, 17, 18, 23, 13, 2),
    *(17, 21, 19, 3, 23, 11),
    *(18, 19, 22, 12, 1, 23),
    *(23, 3, 12, 0, 23, 23),
    *(13, 23, 1, 23, 0, 23),
    *(2, 11, 23, 23, 23, 0),
)


def blocks_from_monomials(c: Tensor) -> Tensor:
    """Σ c G_jᵀ G_j as 6×6 blocks from weighted monomial sums c (..., 10) → (..., 6, 6)."""
    squares = c[..., 4:7]
    cxx, cyy, czz = squares.unbind(-1)
    trace = cxx + cyy + czz
    zero = _series.constant("zero", (0.0,), c.dtype, c.device).expand(*c.shape[:-1], 1)
    values = torch.cat((c, -c, trace[..., None] - squares, zero), -1)
    index = _series.constant("monomial blocks", _BLOCK_ENTRIES, torch.long, c.device)
    return values.index_select(-1, index).unflatten(-1, (6, 6))


def _residuals(poses: Tensor, points: Tensor, data: PointMapData):
    """(r (B, E, 3), T_e, X_e) of the point observations at poses T (B, m, 4, 4)."""
    T_e = per_observation(poses, data.flat_pose_index)
    X_e = gather_points(points, data)
    r = data.masked_observations() - se3.act(T_e, X_e)
    if data.all_valid():
        return r, T_e, X_e
    return torch.where(data.valid[..., None], r, 0.0), T_e, X_e


def linearize(
    pose_tangent: Tensor | None,
    points: Tensor,
    data: PointMapData,
    factor: Tensor | None,
    jacobian_mode: str = "analytic",
    structured: bool = True,
    poses: Tensor | None = None,
    parameters: Tensor | None = None,
) -> BlockLinearization | StructuredLinearization:
    """Normal-equation blocks at (pose_tangent (B, m, 6), points (B, n, 3)); ``poses`` are the
    matrices Exp(ξ) (B, m, 4, 4) when the caller has them (the loop's iterate; then
    ``pose_tangent`` is not read and may be None), else computed. ``parameters``: the slot
    values (B, S, 6) of the parameter blocks (:mod:`torchslam.objective.parameters`), for a
    problem that has them; the pose blocks and gradient then cover every slot (B, m + S, …).

    The structured form is used when ``structured`` and the problem allows it (scalar weights,
    analytic Jacobians, no curvature-corrected robust observation, no term that touches a
    point); otherwise the block form. ``factor`` is :func:`whitening_factors` of ``data``
    (its information matrices' factors are reused; scalar weights are read from ``data``).
    """
    structured = structured and not point_terms(data)
    if poses is None:
        poses = se3.exp(pose_tangent, form="fast")
    lin = _linearize_points(poses, points, data, factor, jacobian_mode, structured)
    lin.poses = poses
    if not data.terms:
        return lin
    terms = linearize_terms(poses, points, data, jacobian_mode, parameters)
    if data.parameters is not None:
        lin = _with_parameter_slots(lin, data)
    changes = {}
    if isinstance(lin, BlockLinearization) and terms.coupling.shape[1] > 0:
        changes = dict(
            point_gradient=lin.point_gradient + terms.point_gradient,
            point_blocks=lin.point_blocks + terms.point_diagonal,
            coupling=(
                terms.coupling
                if lin.coupling.shape[1] == 0
                else torch.cat((lin.coupling, terms.coupling), dim=1)
            ),
        )
    return dataclasses.replace(
        lin,
        cost=lin.cost + terms.cost,
        pose_gradient=lin.pose_gradient + terms.gradient,
        pose_blocks=lin.pose_blocks + terms.diagonal,
        terms=terms,
        **changes,
    )


def _with_parameter_slots(lin, data: PointMapData):
    """``lin`` of the point observations (pose blocks and gradient (B, m, …)) extended to the
    parameter blocks' slots (B, m + S, …): zero gradient; identity blocks on the fixed slots
    and on the inert entries past a block's size, zero elsewhere (the terms add theirs)."""
    layout = data.parameters
    B = lin.pose_gradient.shape[0]
    S = layout.num_slots
    like = lin.pose_gradient
    inert = (~layout.active).to(like.device, like.dtype)  # (S, 6)
    fixed = data.fixed_slots[:, data.num_poses :]  # (B, S)
    diagonal = torch.where(fixed[..., None], 1.0, inert)
    blocks = torch.diag_embed(diagonal)
    return dataclasses.replace(
        lin,
        pose_gradient=torch.cat((lin.pose_gradient, like.new_zeros(B, S, 6)), dim=1),
        pose_blocks=torch.cat((lin.pose_blocks, blocks), dim=1),
    )


def _linearize_points(poses, points, data, factor, jacobian_mode, structured):
    empty = data.pose_index.shape[1] == 0
    if empty and structured and data.information is None and jacobian_mode == "analytic":
        return _no_observations(poses, points, data)
    r, T_e, X_e = _residuals(poses, points, data)
    free_pose, free_point = data.observation_masks()
    valid = data.valid
    # Scalar weights with 0 on the padding (whatever it holds), and (unit weights) their
    # products with the free masks, made once per data.
    products = None
    if data.weights is None:
        products = data.unit_weights(r.dtype)
        weight = products[0]
    else:
        weight = torch.where(valid, data.weights, 0.0)

    if structured and data.information is None and jacobian_mode == "analytic":
        s = weight * sum_last(r * r)
        if data.loss is None:
            cost = 0.5 * s.sum(-1)
            w = weight
            isotropic = True
        else:
            rho, rho1, rho2 = data.loss(s)
            cost = 0.5 * torch.where(valid, rho, torch.zeros_like(rho)).sum(-1)
            w = weight * rho1
            # The corrector adds an anisotropic term only where ρ'' > 0 (never for Huber,
            # Cauchy, Tukey); then the block form is needed.
            isotropic = not bool(((rho2 > 0) & (s > 0) & valid & (rho1 > 0)).any())
            if products is not None:  # w·mask = ρ'·(1·mask): the same (exact) products
                products = (w, *(rho1 * p for p in products[1:]))
        if isotropic:
            if products is None:
                products = weight_products(w, free_pose, free_point)
            return _structured(r, T_e, X_e, points, products, cost, free_pose, free_point, data)

    if jacobian_mode == "analytic":
        J_xi, J_X = point_observation_jacobians(T_e, X_e)
    else:
        J_xi, J_X = jacobians._jacrev_blocks_at(T_e, X_e, data.masked_observations())
    return _blocks(r, J_xi, J_X, factor, free_pose, free_point, data)


def _structured(r, T_e, X_e, points, products, cost, free_pose, free_point, data):
    """The structured form; ``products``: (w, w·free pose, w·free point, w·both), (B, E)."""
    w, w_pose, w_point, w_both = products
    B = data.pose_index.shape[0]
    m, n = data.num_poses, data.num_points
    # the cached (B, E) indices: segment_sum keeps its sparse matrices per index tensor
    pose_index, point_index = data.flat_pose_index, data.flat_point_index
    # q_e = J_Xᵀ w r = −w Rᵀ r; then J_ξᵀ w r = G_jᵀ q = [X × q; q].
    q = -w[..., None] * (T_e[..., :3, :3].transpose(-1, -2) @ r[..., None])[..., 0]
    q_point = q * free_point[..., None]
    q_pose = q * free_pose[..., None]
    g_pose_e = torch.cat((torch.linalg.cross(X_e, q_pose, dim=-1), q_pose), -1)
    gp = segment_sum(pose_index, B * m, g_pose_e.reshape(-1, 6))
    gl = segment_sum(point_index, B * n, q_point.reshape(-1, 3))
    # U_i = Σ w G_jᵀ G_j from weighted monomial sums.
    mono = monomials(X_e) * w_pose[..., None]
    sums = segment_sum(pose_index, B * m, mono.reshape(-1, 10))
    U = blocks_from_monomials(sums).reshape(B, m, 6, 6)
    v = segment_sum(point_index, B * n, w_point.reshape(-1)).reshape(B, n)
    U = torch.where(data.fixed_poses[..., None, None], _series.eye(6, U.dtype, U.device), U)
    v = torch.where(data.fixed_points, 1.0, v)
    return StructuredLinearization(
        cost=cost,
        pose_gradient=gp.reshape(B, m, 6),
        point_gradient=gl.reshape(B, n, 3),
        pose_blocks=U,
        point_weight=v,
        weight=w,
        coupling_weight=w_both,
        points=points,
        free_pose=free_pose,
        free_point=free_point,
        observed_points=X_e,
    )


def _no_observations(poses, points, data):
    """The structured form of a problem without point observations (a pose graph): what
    :func:`_structured` gives for E = 0, without its passes over empty tensors."""
    B, m, n = poses.shape[0], data.num_poses, data.num_points
    eye6 = torch.eye(6, dtype=poses.dtype, device=poses.device)
    empty = poses.new_zeros(B, 0)
    no_mask = data.valid.new_zeros(B, 0)
    return StructuredLinearization(
        cost=poses.new_zeros(B),
        pose_gradient=poses.new_zeros(B, m, 6),
        point_gradient=poses.new_zeros(B, n, 3),
        pose_blocks=data.fixed_poses[..., None, None] * eye6,
        point_weight=data.fixed_points.to(poses.dtype),
        weight=empty,
        coupling_weight=empty,
        points=points,
        free_pose=no_mask,
        free_point=no_mask,
    )


def _plain(*tensors: Tensor) -> bool:
    """No tensor records autograd history or is wrapped by a torch.func transform."""
    return not any(
        t.requires_grad or torch._C._functorch.is_functorch_wrapped_tensor(t) for t in tensors
    )


def _blocks(r, J_xi, J_X, factor, free_pose, free_point, data):
    """The point observations in the block form: :func:`instance_blocks` with one pose and
    one point per instance (the observations as a :class:`~torchslam.terms.PointObservationTerm`
    with the data's whitening and kernel)."""
    B = data.pose_index.shape[0]
    m, n = data.num_poses, data.num_points
    free_pose, free_point = free_pose[..., None, None], free_point[..., None, None]
    if _plain(J_xi, J_X):
        # [J_ξ·free pose | J_X·free point] written in place: the bits of torch.cat of the
        # two products, without their temporaries (half the time on 10⁵–10⁶ observations).
        J = J_xi.new_empty((*J_xi.shape[:-1], 9))
        torch.mul(J_xi, free_pose, out=J[..., :6])
        torch.mul(J_X, free_point, out=J[..., 6:])
    else:  # out= takes part in neither autograd nor torch.func transforms
        J = torch.cat((J_xi * free_pose, J_X * free_point), -1)
    whitening = None
    if data.information is not None:
        whitening = factor if factor is not None and factor.dim() == 4 else None
        if whitening is None:
            whitening = whitening_factors(data)
    cost, rw, Jw, scale, _, Jtr = instance_blocks(
        r, J, data.valid, whitening, data.masked_weights(), data.loss, data.all_valid(), False
    )
    # The three blocks of J̃ᵀJ̃·w that are used (pose, coupling, point), each by its own
    # product: the same sums as the (9 × 9) product's entries, without its unused lower-left
    # block and the copies of its strided slices.
    Jt = Jw.transpose(-1, -2)
    if scale is not None:
        Jt = scale[..., None, None] * Jt
    Jt_pose = Jt[..., :6, :]
    J_point = Jw[..., 6:]
    pose_block = matmul(Jt_pose, Jw[..., :6])
    coupling = matmul(Jt_pose, J_point)
    point_block = matmul(Jt[..., 6:, :], J_point)
    pose_index, point_index = data.flat_pose_index, data.flat_point_index
    U = segment_sum(pose_index, B * m, pose_block.reshape(-1, 6, 6))
    V = segment_sum(point_index, B * n, point_block.reshape(-1, 3, 3))
    gp = segment_sum(pose_index, B * m, Jtr[..., :6].reshape(-1, 6))
    gl = segment_sum(point_index, B * n, Jtr[..., 6:].reshape(-1, 3))
    eye6, eye3 = _series.eye(6, U.dtype, U.device), _series.eye(3, U.dtype, U.device)
    U = torch.where(data.fixed_poses[..., None, None], eye6, U.reshape(B, m, 6, 6))
    V = torch.where(data.fixed_points[..., None, None], eye3, V.reshape(B, n, 3, 3))
    return BlockLinearization(
        cost=cost,
        pose_gradient=gp.reshape(B, m, 6),
        point_gradient=gl.reshape(B, n, 3),
        pose_blocks=U,
        point_blocks=V,
        residuals=rw,
        jacobian=Jw,
        coupling=coupling,
        scale=scale,
    )


def instance_blocks(
    r: Tensor,
    J: Tensor,
    valid: Tensor,
    whitening: Tensor | None,
    weight: Tensor | None,
    loss: object | None,
    all_valid: bool = False,
    products: bool = True,
) -> tuple[Tensor, Tensor, Tensor, Tensor | None, Tensor | None, Tensor]:
    """Whiten, robustify and multiply out K instances of one residual: the one routine of the
    block form, for the point observations and for every term.

    Instance k has residual r_k (d) and Jacobian J_k (d × c) over all the variables it
    touches (its poses' 6-columns side by side, then its point's 3 columns), with the
    columns of fixed variables already zero. With UᵀU = Ω_k (``whitening`` U) or a scalar
    weight w_k, s_k = w_k |U r_k|², and Ceres' corrector (:func:`torchslam.losses.
    triggs_correction`) of r and J applied to the unscaled r, J: with r̂ = r/|r| in whitened
    coordinates it needs only α r̂ r̂ᵀ = (α/s)·w·r rᵀ, so no √w appears (its derivative is
    infinite at w = 0); the products are multiplied by w afterwards.

    Args:
        r: residuals (B, K, d); J: blocks (B, K, d, c); valid: bool (B, K) (padding is inert
            whatever it holds).
        whitening: U (B, K, d, d) with UᵀU = Ω per instance, or None.
        weight: scalar weights w (B, K) (1 on padding), or None.
        loss: robust kernel ρ, or None.
        all_valid: the caller knows no instance is padding (skips the masking copies).
        products: compute J̃ᵀJ̃·w; with False it is None (the caller forms its blocks).

    Returns:
        (cost ½ Σ ρ(s) (B,), r̃ (B, K, d), J̃ (B, K, d, c), w (B, K) with 0 on padding or None,
        J̃ᵀJ̃·w (B, K, c, c) or None, J̃ᵀr̃·w (B, K, c)); everything zero on padding.
    """
    valid_r, valid_J = valid[..., None], valid[..., None, None]
    if not all_valid:
        # Padding instances: zero residual and blocks before whitening (no NaN into U r, U J).
        r = torch.where(valid_r, r, 0.0)
        J = torch.where(valid_J, J, 0.0)
    if whitening is not None:
        r = matmul(whitening, r[..., None])[..., 0]
        J = matmul(whitening, J)
    if weight is not None:
        weight = torch.where(valid, weight, torch.zeros_like(weight))
    s = sum_last(r * r)
    if weight is not None:
        s = weight * s
    if loss is None:
        cost = 0.5 * s.sum(-1)
    else:
        rho, rho1, rho2 = loss(s)
        cost = 0.5 * torch.where(valid, rho, torch.zeros_like(rho)).sum(-1)
        residual_scale, alpha_over_s = losses.triggs_correction(s, rho1, rho2)
        if weight is not None:
            alpha_over_s = alpha_over_s * weight
        # (the shortcut reads α on the host: CPU tensors outside torch.func transforms only)
        plain = alpha_over_s.device.type == "cpu" and not (
            torch._C._functorch.is_functorch_wrapped_tensor(alpha_over_s)
        )
        if not plain or bool((alpha_over_s != 0).any()):
            projector = alpha_over_s[..., None, None] * r[..., :, None]
            J = torch.sqrt(rho1)[..., None, None] * (J - projector @ (r[..., None, :] @ J))
        else:  # α = 0 everywhere (Huber, Cauchy, Tukey: ρ'' ≤ 0): √ρ' scaling alone
            J = torch.sqrt(rho1)[..., None, None] * J
        r = residual_scale[..., None] * r
        if not all_valid:
            r = torch.where(valid_r, r, torch.zeros_like(r))
            J = torch.where(valid_J, J, torch.zeros_like(J))
    # w on one side only: a (c × d) pass instead of a (c × c) one (J̃ᵀJ̃·w is then symmetric
    # to round-off only).
    Jt = J.transpose(-1, -2)
    if weight is not None:
        Jt = weight[..., None, None] * Jt
    JtJ = matmul(Jt, J) if products else None
    # J̃ᵀr̃ as the row r̃ᵀJ̃ (no transposed copy of J̃); for a short residual (a pixel, a
    # 3-vector) as d broadcast rows, faster than stacked products of inner size d.
    d = r.shape[-1]
    if 1 <= d <= 4:
        Jtr = r[..., 0, None] * J[..., 0, :]
        for k in range(1, d):
            Jtr = Jtr + r[..., k, None] * J[..., k, :]
    else:
        Jtr = matmul(r[..., None, :], J)[..., 0, :]
    return cost, r, J, weight, JtJ, Jtr if weight is None else weight[..., None] * Jtr


# A term is grouped (:class:`TermGrouping`) when its instances share at most one slot tuple
# per this many instances, and its Gram blocks then come from pieces of PIECE instances.
GROUPING_RATIO = 8
PIECE = 32


@dataclass(frozen=True)
class TermGrouping:
    """The instances of a term grouped by *signature*: the tuple of slots they touch (in
    bundle adjustment every observation of one camera touches its pose and intrinsics).
    The terms' blocks J̃_aᵀJ̃_b of one signature only ever enter the reduced system summed
    (by slot pair), so a grouped term keeps them summed per signature — ``pair_blocks`` and
    :func:`term_pair_keys` hold one block per signature and slot pair (U per problem,
    padded to the most of any problem with zero blocks) instead of one per instance — and
    :func:`linearize_terms` forms the sums by batched GEMM pieces of ``PIECE`` instances
    (no per-instance products)."""

    # Per problem the signatures' slots, long (B, U, a) (padding: slot 0, zero blocks).
    slots: Tensor
    # Flat signature b·U + u of each instance, long (B·K,).
    signature: Tensor
    # Pieces: flat instances b·K + k, (Q, PIECE) (padding: B·K, a zero row), and the flat
    # signature of each, (Q,).
    piece_rows: Tensor
    piece_signature: Tensor


def term_grouping(term: Term) -> TermGrouping | None:
    """The :class:`TermGrouping` of a bound term, or None when its instances do not share
    signatures enough (fewer than ``GROUPING_RATIO`` instances per signature: pose graphs);
    cached on the term."""
    return _cached(term, "_grouping_cache", (term.slot_index,), lambda: _grouping(term))


def _grouping(term: Term) -> TermGrouping | None:
    slots = term.slot_index
    B, K, a = slots.shape
    if a == 0 or B * K < GROUPING_RATIO:
        return None
    device = slots.device
    batch = torch.arange(B, device=device)[:, None, None].expand(B, K, 1)
    unique, inverse = unique_rows(torch.cat((batch, slots), -1).reshape(B * K, 1 + a))
    count = unique.shape[0]
    if count * GROUPING_RATIO > B * K:
        return None
    per_problem = torch.bincount(unique[:, 0], minlength=B)
    U = int(per_problem.max())
    start = torch.cumsum(per_problem, 0) - per_problem
    flat = unique[:, 0] * U + torch.arange(count, device=device) - start[unique[:, 0]]
    table = torch.zeros(B * U, a, dtype=torch.long, device=device)
    table = table.index_copy(0, flat, unique[:, 1:]).reshape(B, U, a)
    signature = flat[inverse]
    rows, piece_signature = pieces(signature, B * U, PIECE, B * K)
    return TermGrouping(table, signature, rows, piece_signature)


def _term_slots(term: Term) -> Tensor:
    """The slots behind each of the term's blocks: per instance (B, K, a'), or per signature
    (B, U, a') for a grouped term (:class:`TermGrouping`)."""
    grouping = term_grouping(term)
    return term.slot_index if grouping is None else grouping.slots


def term_pair_keys(data: PointMapData) -> Tensor:
    """Block (b, i_a, i_b) of each of the ``pair_blocks`` as (b·m + i_a)·m + i_b, long (B, P),
    m the slots of the reduced system (poses, then parameter blocks)."""
    m = data.num_slots
    B = data.pose_index.shape[0]
    batch = torch.arange(B, device=data.pose_index.device)[:, None]
    keys = []
    for term in data.terms:
        slots = _term_slots(term)
        for a in range(term.slot_arity):
            for b in range(term.slot_arity):
                if a != b:
                    keys.append((batch * m + slots[..., a]) * m + slots[..., b])
    if not keys:
        return data.pose_index.new_zeros(B, 0)
    return torch.cat(keys, dim=1)


class TermAccumulator:
    """Sums the terms' per-instance blocks into the layout of :class:`TermLinearization`: the
    one scatter of :func:`linearize_terms` and of the exact Hessian (:mod:`.hessian`)."""

    def __init__(self, poses: Tensor, points: Tensor, num_slots: int | None = None) -> None:
        self.B, self.m = poses.shape[:2]
        if num_slots is not None:  # poses, then the parameter blocks' slots
            self.m = num_slots
        self.n = points.shape[1]
        B, m, n = self.B, self.m, self.n
        self.cost = poses.new_zeros(B)
        self.gradient = poses.new_zeros(B * m, 6)
        self.diagonal = poses.new_zeros(B * m, 6, 6)
        self.point_gradient = poses.new_zeros(B * n, 3)
        self.point_diagonal = poses.new_zeros(B * n, 3, 3)
        self.pairs: list[Tensor] = []
        self.couplings: list[Tensor] = []
        self.jacobians: list[Tensor] = []
        self.scales: list[Tensor] = []
        self.batch = torch.arange(B, device=poses.device)[:, None]

    def add(
        self,
        term: Term,
        cost: Tensor,
        gradient: Tensor,
        pose_blocks: Tensor,
        point_block: Tensor | None = None,
        coupling: Tensor | None = None,
    ) -> None:
        """One term's share: cost (B,), gradient (B, K, 6a [+ 3]), pose_blocks[i][j] the
        blocks of poses i and j of every instance, (B, K, 6, 6) each (indexable as an
        (a, a, B, K, 6, 6) tensor), and for a term with a point its block (B, K, 3, 3) and its
        couplings (B, K, 6a, 3)."""
        self.add_point_part(term, cost, gradient, point_block, coupling)
        B, a = self.B, term.slot_arity
        grouping = term_grouping(term)
        if grouping is not None:  # the blocks summed per signature
            U = grouping.slots.shape[1]
            summed = [
                [
                    pose_blocks[i][j]
                    .new_zeros(B * U, 6, 6)
                    .index_add_(0, grouping.signature, pose_blocks[i][j].reshape(-1, 6, 6))
                    for j in range(a)
                ]
                for i in range(a)
            ]
            self.add_blocks(term, summed)
            return
        slots = self.batch[..., None] * self.m + term.slot_index  # (B, K, a)
        for i in range(a):
            self.diagonal.index_add_(
                0, slots[..., i].reshape(-1), pose_blocks[i][i].reshape(-1, 6, 6)
            )
        self.pairs.extend(pose_blocks[i][j] for i in range(a) for j in range(a) if i != j)

    def add_point_part(
        self,
        term: Term,
        cost: Tensor,
        gradient: Tensor,
        point_block: Tensor | None,
        coupling: Tensor | None,
    ) -> None:
        """The share of :meth:`add` that is not the slot blocks (a grouped term adds those by
        :meth:`add_blocks`): cost, gradient, and for a point term its point blocks and
        couplings."""
        B, m, n = self.B, self.m, self.n
        K, a = term.slot_index.shape[1:]
        P = 6 * a
        self.cost = self.cost + cost
        # Sums per slot and per point over index tensors cached on the term, so that
        # segment_sum keeps their sparse matrices across iterations.
        slots = _cached(
            term,
            f"_flat_slots_{m}",
            (term.slot_index,),
            lambda: (self.batch[..., None] * m + term.slot_index).reshape(-1),
        )
        self.gradient += segment_sum(slots, B * m, gradient[..., :P].reshape(-1, 6))
        if term.has_point:
            point_slots = _cached(
                term,
                f"_flat_points_{n}",
                (term.point_index,),
                lambda: (self.batch * n + term.point_index).reshape(-1),
            )
            self.point_gradient += segment_sum(point_slots, B * n, gradient[..., P:].reshape(-1, 3))
            self.point_diagonal += segment_sum(
                point_slots, B * n, point_block.reshape(-1, 9)
            ).reshape(-1, 3, 3)
            self.couplings.append(coupling.reshape(B, K * a, 6, 3))

    def add_blocks(self, term: Term, blocks) -> None:
        """The Gram blocks of a grouped term (:class:`TermGrouping`) summed per signature:
        ``blocks[i][j]`` (B·U, 6, 6) for its slot positions i, j (diagonal into the slots'
        blocks, the others as its pair blocks)."""
        grouping = term_grouping(term)
        B, U, a = grouping.slots.shape
        slots = (self.batch[..., None] * self.m + grouping.slots).reshape(B * U, a)
        for i in range(a):
            self.diagonal.index_add_(0, slots[:, i], blocks[i][i])
        self.pairs.extend(
            blocks[i][j].reshape(B, U, 6, 6) for i in range(a) for j in range(a) if i != j
        )

    def result(self) -> TermLinearization:
        B, m, n = self.B, self.m, self.n
        like = self.gradient
        return TermLinearization(
            cost=self.cost,
            gradient=self.gradient.reshape(B, m, 6),
            diagonal=self.diagonal.reshape(B, m, 6, 6),
            pair_blocks=_joined(self.pairs) if self.pairs else like.new_zeros(B, 0, 6, 6),
            jacobians=tuple(self.jacobians),
            scales=tuple(self.scales),
            point_gradient=self.point_gradient.reshape(B, n, 3),
            point_diagonal=self.point_diagonal.reshape(B, n, 3, 3),
            coupling=(_joined(self.couplings) if self.couplings else like.new_zeros(B, 0, 6, 3)),
        )


def _grouped_gram(J: Tensor, scale: Tensor | None, grouping: TermGrouping, a: int):
    """Σ_k w_k J̃_kᵀJ̃_k per signature of a grouped term, as blocks [i][j] (B·U, 6, 6):
    J the robustified slot blocks (B, K, d, 6a), ``scale`` w (B, K) or None; one batched
    GEMM over pieces of PIECE instances (inner size d·PIECE)."""
    B, K, d, P = J.shape
    rows = J.new_empty(B * K + 1, d * P)  # the blocks, then a zero row for the padding
    rows[: B * K].view(B, K, d, P).copy_(J)
    rows[B * K] = 0.0
    right = rows.index_select(0, grouping.piece_rows.reshape(-1)).reshape(-1, PIECE * d, P)
    if scale is None:
        left = right
    else:
        w = torch.cat((scale.reshape(-1), scale.new_zeros(1)))
        w = w.index_select(0, grouping.piece_rows.reshape(-1))
        left = (right.reshape(-1, PIECE, d, P) * w.reshape(-1, PIECE, 1, 1)).reshape(right.shape)
    U = grouping.slots.shape[1]
    gram = J.new_zeros(B * U, P, P).index_add_(
        0, grouping.piece_signature, torch.bmm(left.transpose(1, 2), right)
    )
    gram = gram.reshape(B * U, a, 6, a, 6)
    return [[gram[:, i, :, j, :] for j in range(a)] for i in range(a)]


def _joined(parts: list[Tensor]) -> Tensor:
    """``torch.cat(parts, dim=1)``, without the copy of a single part."""
    return parts[0] if len(parts) == 1 else torch.cat(parts, dim=1)


def linearize_terms(
    poses: Tensor,
    points: Tensor,
    data: PointMapData,
    jacobian_mode: str,
    parameters: Tensor | None = None,
) -> TermLinearization:
    """The terms' normal-equation blocks at poses T (B, m, 4, 4), points (B, n, 3) and
    parameter slots (B, S, 6) (module doc): :func:`instance_blocks` per term, summed by
    :class:`TermAccumulator` into the slot and point blocks, the slot pairs and the coupling
    edges."""
    B = poses.shape[0]
    n = points.shape[1]
    total = TermAccumulator(poses, points, data.num_slots)
    for term in data.terms:
        has_point = term.has_point
        if has_point and n == 0:
            continue  # no points: every instance of the term is padding
        X = term_points(term, points) if has_point else None
        values = None
        if term.has_parameters:
            values = term_parameters(term, data.parameters, parameters)
        K, a = term.slot_index.shape[1:]
        T_k = term_poses(term, poses)
        if has_point:  # J (B, K, d, 6a + 3): the slots' columns, then the point's
            free_point = None
            if bool(data.fixed_points.any()):
                free_point = ~data.fixed_points.reshape(-1)[total.batch * n + term.point_index]
            r, J = term_rows(term, T_k, X, jacobian_mode, values, free_point)
        else:
            r, J, _ = term_blocks(term, T_k, X, jacobian_mode, values)
            J = J.flatten(-2)  # (B, K, d, 6a)
        fixed = term_fixed_rows(term, data.fixed_slots)
        if fixed is not None:  # the columns of fixed poses are zero (on those rows only)
            rows, free = fixed
            flat = J.reshape(B * K, *J.shape[2:])
            scale = free[:, None, :, None].expand(-1, 1, -1, 6).reshape(-1, 1, 6 * a)
            if has_point:
                scale = torch.cat((scale, scale.new_ones(scale.shape[0], 1, 3)), -1)
            J = flat.index_copy(0, rows, flat[rows] * scale).reshape(J.shape)
        all_valid = term_all_valid(term)
        whitening = term_whitening(term) if term.information is not None else None
        weight = term.weight
        if weight is not None and not all_valid:
            weight = torch.where(term.valid, weight, 1.0)
        term_cost, _, Jw, scale, _, Jtr = instance_blocks(
            r, J, term.valid, whitening, weight, term.loss, all_valid=all_valid, products=False
        )
        total.jacobians.append(Jw)
        total.scales.append(term.valid.to(r.dtype) if scale is None else scale)
        P, d = 6 * a, Jw.shape[-2]
        Jt = Jw.transpose(-1, -2)
        if scale is not None:  # w on one side only (the products are symmetric to round-off)
            Jt = scale[..., None, None] * Jt
        point_block = coupling = None
        if has_point:
            # w J̃ᵀJ̃_X in one small product (3 columns: the point's), then its rows: the
            # couplings J̃_slotsᵀ J̃_X and the point block J̃_Xᵀ J̃_X.
            J_point = Jw[..., P:]
            coupling = matmul(Jt[..., :P, :], J_point)  # contiguous: a view per slot
            point_block = matmul(Jt[..., P:, :], J_point)
        grouping = term_grouping(term)
        if grouping is not None and not torch.is_grad_enabled():
            # Σ J̃ᵀJ̃·w per signature by GEMM pieces (TermGrouping), then the slot blocks.
            blocks = _grouped_gram(Jw[..., :P], scale, grouping, a)
            total.add_point_part(term, term_cost, Jtr, point_block, coupling)
            total.add_blocks(term, blocks)
            continue
        # H[a, b] = J̃_aᵀJ̃_b·w of every instance, (a, a, B, K, 6, 6): each block contiguous.
        H = matmul(
            Jt[..., :P, :].reshape(B, K, a, 6, d).permute(2, 0, 1, 3, 4)[:, None],
            Jw[..., :P].reshape(B, K, d, a, 6).permute(3, 0, 1, 2, 4)[None],
        )
        total.add(term, term_cost, Jtr, H, point_block, coupling)
    return total.result()


def cost_at(
    pose_tangent: Tensor,
    points: Tensor,
    data: PointMapData,
    factor: Tensor | None,
    parameters: Tensor | None = None,
) -> Tensor:
    """½ Σ ρ(s) per problem, (B,), with the same whitening as :func:`linearize`
    (``parameters``: the parameter blocks' slot values (B, S, 6), if the problem has them)."""
    poses = se3.exp(pose_tangent, form="fast")
    r, _, _ = _residuals(poses, points, data)
    rw = whiten(factor, r[..., None])
    s = sum_last((rw * rw)[..., 0])
    if data.loss is not None:
        s = data.loss(s)[0]
    points_cost = 0.5 * torch.where(data.valid, s, torch.zeros_like(s)).sum(-1)
    return points_cost + terms_cost(data.terms, poses, points, data.parameters, parameters)


def model_decrease(
    lin: BlockLinearization | StructuredLinearization,
    data: PointMapData,
    dp: Tensor,
    dl: Tensor,
) -> Tensor:
    """Decrease of the Gauss-Newton model, L(0) − L(δ) = −(gᵀδ + ½ δᵀHδ), per problem (B,).

    δᵀHδ is evaluated as Σ_e ‖J̃_e δ‖² from per-observation quantities (exact, no H).
    """
    dp_e = per_observation(dp, data.flat_pose_index)
    dl_e = gather_points(dl, data)
    g_dot = (lin.pose_gradient * dp).flatten(1).sum(-1) + (lin.point_gradient * dl).flatten(1).sum(
        -1
    )
    if isinstance(lin, StructuredLinearization):
        X_e = lin.observed_points
        if X_e is None:
            X_e = gather_points(lin.points, data)
        # J̃δ = √w · (−R)(δX + δω × X + δv): its norm needs no R.
        u = (
            dl_e * lin.free_point[..., None]
            + torch.linalg.cross(dp_e[..., :3], X_e, dim=-1) * lin.free_pose[..., None]
            + dp_e[..., 3:] * lin.free_pose[..., None]
        )
        quad = (lin.weight * sum_last(u * u)).sum(-1)
    else:
        Jd = (lin.jacobian @ torch.cat((dp_e, dl_e), -1)[..., None])[..., 0]
        squares = Jd * Jd if lin.scale is None else lin.scale[..., None] * (Jd * Jd)
        quad = squares.sum((-1, -2))  # one reduction: summing 3 entries per row first is slow
    if lin.terms is not None:
        B, m = dp.shape[:2]
        n = dl.shape[1]
        batch = torch.arange(B, device=dp.device)[:, None]
        terms = [t for t in data.terms if not (t.has_point and n == 0)]
        for term, J, scale in zip(terms, lin.terms.jacobians, lin.terms.scales, strict=True):
            K, a = term.slot_index.shape[1:]
            step = dp.reshape(B * m, 6)[(batch[..., None] * m + term.slot_index).reshape(-1)]
            step = step.reshape(B, K, 6 * a)
            if term.has_point:
                dl_k = dl.reshape(B * n, 3)[(batch * n + term.point_index).reshape(-1)]
                step = torch.cat((step, dl_k.reshape(B, K, 3)), -1)
            Jd = (J @ step[..., None])[..., 0]
            quad = quad + (scale * (Jd * Jd).sum(-1)).sum(-1)
    return -(g_dot + 0.5 * quad)
