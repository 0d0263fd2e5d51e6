"""Linearize: residuals and Jacobians at the current estimate → normal-equation blocks.

Two forms, chosen per iteration by :func:`linearize`; both are accumulated with ``index_add``
from per-observation quantities — never a dense J.

**Block form** (general: information matrices, the ``jacrev`` Jacobian mode, robust kernels
with curvature correction). For each observation e = (i, j), the whitened residual r̃ = Lᵀ r
(Ω = L Lᵀ) and blocks J̃ = Lᵀ [J_r_xi | J_r_point] are robustified with Ceres' corrector
(:func:`torchslam.losses.triggs_correction`), then

    U_i = Σ_e J̃_ξᵀ J̃_ξ (6×6),  V_j = Σ_e J̃_Xᵀ J̃_X (3×3),  W_e = J̃_ξᵀ J̃_X (6×3),
    g_i = Σ_e J̃_ξᵀ r̃,          g_j = Σ_e J̃_Xᵀ r̃.

**Structured form** (the ICP-SLAM fast path: scalar weights, analytic Jacobians, no curvature
correction — always the case for Huber, Cauchy and Tukey under Ceres' clamp). The analytic
blocks factor as J_ξ = J_X · G_j with J_X = −R_i and G_j = [ −[X_j]× | I ] (see
:mod:`torchslam.jacobians`), so with an effective scalar weight w_e (weight × ρ'):

    J̃_Xᵀ J̃_X = w_e I,   W_e = w_e G_jᵀ,   U_i = Σ_e w_e G_jᵀ G_j,   V_j = v_j I with v_j = Σ_e w_e,
    G_jᵀ G_j = [[ |X|² I − X Xᵀ, [X]× ], [ −[X]×, I ]],

so every block is a weighted sum of the 10 monomials (1, x, y, z, x², y², z², xy, xz, yz) of
X_j. The Schur complement then needs no per-pair products at all (see :mod:`.linear`).

**Pose terms** (:mod:`torchslam.terms`: relative poses, priors, user terms). Instance k of a
term touches poses i_1 … i_a with whitened, robustified residual r̃_k and blocks J̃_k,a (d × 6);
it adds J̃_aᵀr̃ to g_(i_a), J̃_aᵀJ̃_a to U_(i_a) (folded into ``pose_blocks`` and
``pose_gradient`` of either form, so damping and Schur see the whole pose Hessian) and the
off-diagonal products J̃_aᵀJ̃_b (a ≠ b) to block (i_a, i_b) of the reduced pose system, kept
as :class:`TermLinearization` ``pair_blocks``; :mod:`.linear` adds them to S (dense) or to
its sparse pattern.

Fixed poses/points and padding contribute nothing; fixed variables get an identity block and
a zero gradient, so their step is exactly zero.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from torchslam import losses
from torchslam.jacobians import analytic_blocks
from torchslam.lie import se3, so3
from torchslam.problem import PointMapData, gather_points, jacobian_blocks, per_observation
from torchslam.terms import (
    Term,
    masked_weighting,
    term_jacobians,
    term_poses,
    term_whitening,
    terms_cost,
)

__all__ = [
    "BlockLinearization",
    "CouplingEdges",
    "StructuredLinearization",
    "TermLinearization",
    "cost_at",
    "coupling_edges",
    "linearize",
    "linearize_terms",
    "monomials",
    "term_pair_keys",
    "whitening_factors",
]


@dataclass(frozen=True)
class CouplingEdges:
    """Every pose-point coupling block W_e of the objective (fixed for a solve).

    The order is the order of :attr:`BlockLinearization.coupling`: the point observations of
    ``data`` first. The Schur complement eliminates the points through these edges only.
    """

    # Pose and point of each edge, long (B, E').
    pose_index: Tensor
    point_index: Tensor
    # The edge couples a free pose with a free point of a valid entry, bool (B, E').
    active: Tensor


def coupling_edges(data: PointMapData) -> CouplingEdges:
    """The :class:`CouplingEdges` of ``data`` (its point observations)."""
    active = (
        data.valid
        & ~torch.gather(data.fixed_poses, 1, data.pose_index)
        & ~torch.gather(data.fixed_points, 1, data.point_index)
    )
    return CouplingEdges(data.pose_index, data.point_index, active)


@dataclass
class TermLinearization:
    """The pose terms' share of the normal equations (B problems, m poses)."""

    # ½ Σ ρ(s) of all terms, (B,).
    cost: Tensor
    # Σ J̃ᵀr̃ per pose, (B, m, 6), and Σ J̃_aᵀJ̃_a per pose, (B, m, 6, 6).
    gradient: Tensor
    diagonal: Tensor
    # J̃_aᵀJ̃_b for a ≠ b of every instance of every term, (B, P, 6, 6), in the order of
    # :func:`term_pair_keys`.
    pair_blocks: Tensor
    # Robustified blocks J of each term, (B, K_t, d_t, a_t, 6), whitened by U for information
    # matrices; with scalar weights w they are not whitened (no √w: its derivative is
    # infinite at w = 0) and ``scales`` holds w, (B, K_t) (ones otherwise): J̃ᵀJ̃ = w JᵀJ.
    jacobians: tuple[Tensor, ...]
    scales: tuple[Tensor, ...]


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
    # Whitened, robustified residuals r̃, (B, E, 3).
    residuals: Tensor
    # Whitened, robustified Jacobian blocks [J̃_ξ | J̃_X], (B, E, 3, 9).
    jacobian: Tensor
    # Pose-point blocks W_e, (B, E, 6, 3).
    coupling: Tensor
    # The pose terms (already folded into cost, pose_gradient, pose_blocks), or None.
    terms: TermLinearization | None = None


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


def whitening_factors(data: PointMapData) -> Tensor | None:
    """Lᵀ with Ω = L Lᵀ per observation (B, E, 3, 3), √w (B, E), or None for unit weights."""
    if data.information is not None:
        return torch.linalg.cholesky(data.masked_information()).transpose(-1, -2)
    if data.weights is not None:
        return torch.sqrt(data.masked_weights())
    return None


def _whiten(factor: Tensor | None, x: Tensor) -> Tensor:
    """Apply a whitening factor to (B, E, 3, k)."""
    if factor is None:
        return x
    if factor.dim() == 2:
        return factor[..., None, None] * x
    return factor @ x


def monomials(points: Tensor) -> Tensor:
    """(1, x, y, z, x², y², z², xy, xz, yz) of points (..., 3) → (..., 10)."""
    x, y, z = points.unbind(-1)
    return torch.stack(
        (torch.ones_like(x), x, y, z, x * x, y * y, z * z, x * y, x * z, y * z), dim=-1
    )


def blocks_from_monomials(c: Tensor) -> Tensor:
    """Σ c G_jᵀ G_j as 6×6 blocks from weighted monomial sums c (..., 10) → (..., 6, 6)."""
    c1, cx, cy, cz, cxx, cyy, czz, cxy, cxz, cyz = c.unbind(-1)
    trace = cxx + cyy + czz
    zero = torch.zeros_like(c1)
    top_left = torch.stack(
        (
            torch.stack((trace - cxx, -cxy, -cxz), -1),
            torch.stack((-cxy, trace - cyy, -cyz), -1),
            torch.stack((-cxz, -cyz, trace - czz), -1),
        ),
        -2,
    )
    skew = torch.stack(
        (
            torch.stack((zero, -cz, cy), -1),
            torch.stack((cz, zero, -cx), -1),
            torch.stack((-cy, cx, zero), -1),
        ),
        -2,
    )
    eye = c1[..., None, None] * torch.eye(3, dtype=c.dtype, device=c.device)
    return torch.cat((torch.cat((top_left, skew), -1), torch.cat((-skew, eye), -1)), -2)


def _residuals(pose_tangent: Tensor, points: Tensor, data: PointMapData):
    T_e = per_observation(se3._exp(pose_tangent), data.flat_pose_index)
    X_e = gather_points(points, data)
    r = data.masked_observations() - se3._act(T_e, X_e)
    return torch.where(data.valid[..., None], r, 0.0), T_e, X_e


def _slots(data: PointMapData) -> tuple[Tensor, Tensor]:
    return data.flat_pose_index.reshape(-1), data.flat_point_index.reshape(-1)


def linearize(
    pose_tangent: Tensor,
    points: Tensor,
    data: PointMapData,
    factor: Tensor | None,
    jacobian_mode: str = "analytic",
    structured: bool = True,
) -> BlockLinearization | StructuredLinearization:
    """Normal-equation blocks at (pose_tangent (B, m, 6), points (B, n, 3)).

    The structured form is used when ``structured`` and the problem allows it (scalar weights,
    analytic Jacobians, no curvature-corrected robust observation); otherwise the block form.
    """
    lin = _linearize_points(pose_tangent, points, data, factor, jacobian_mode, structured)
    if not data.terms:
        return lin
    terms = linearize_terms(se3._exp(pose_tangent), data, jacobian_mode)
    return dataclasses.replace(
        lin,
        cost=lin.cost + terms.cost,
        pose_gradient=lin.pose_gradient + terms.gradient,
        pose_blocks=lin.pose_blocks + terms.diagonal,
        terms=terms,
    )


def _linearize_points(pose_tangent, points, data, factor, jacobian_mode, structured):
    r, T_e, X_e = _residuals(pose_tangent, points, data)
    free_pose = ~torch.gather(data.fixed_poses, 1, data.pose_index)
    free_point = ~torch.gather(data.fixed_points, 1, data.point_index)
    valid = data.valid
    weight = data.masked_weights() if data.weights is not None else torch.ones_like(r[..., 0])
    weight = torch.where(valid, weight, torch.zeros_like(weight))

    if structured and data.information is None and jacobian_mode == "analytic":
        s = weight * (r * r).sum(-1)
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
        if isotropic:
            return _structured(r, T_e, X_e, points, w, cost, free_pose, free_point, data)

    if jacobian_mode == "analytic":
        J_xi, J_X = analytic_blocks(T_e[..., :3, :3], X_e)
    else:
        J_xi, J_X = jacobian_blocks(pose_tangent, points, data, jacobian_mode)
    return _blocks(r, J_xi, J_X, factor, free_pose, free_point, data)


def _structured(r, T_e, X_e, points, w, cost, free_pose, free_point, data):
    B = data.pose_index.shape[0]
    m, n = data.num_poses, data.num_points
    pose_slot, point_slot = _slots(data)
    # q_e = J_Xᵀ w r = −w Rᵀ r; then J_ξᵀ w r = G_jᵀ q = [X × q; q].
    q = -w[..., None] * (T_e[..., :3, :3].transpose(-1, -2) @ r[..., None])[..., 0]
    q_point = q * free_point[..., None]
    q_pose = q * free_pose[..., None]
    g_pose_e = torch.cat((torch.linalg.cross(X_e, q_pose, dim=-1), q_pose), -1)
    gp = r.new_zeros(B * m, 6).index_add_(0, pose_slot, g_pose_e.reshape(-1, 6))
    gl = r.new_zeros(B * n, 3).index_add_(0, point_slot, q_point.reshape(-1, 3))
    # U_i = Σ w G_jᵀ G_j from weighted monomial sums.
    mono = monomials(X_e) * (w * free_pose)[..., None]
    sums = r.new_zeros(B * m, 10).index_add_(0, pose_slot, mono.reshape(-1, 10))
    U = blocks_from_monomials(sums).reshape(B, m, 6, 6)
    v = r.new_zeros(B * n).index_add_(0, point_slot, (w * free_point).reshape(-1)).reshape(B, n)
    eye6 = torch.eye(6, dtype=U.dtype, device=U.device)
    U = torch.where(data.fixed_poses[..., None, None], eye6, U)
    v = torch.where(data.fixed_points, torch.ones_like(v), v)
    return StructuredLinearization(
        cost=cost,
        pose_gradient=gp.reshape(B, m, 6),
        point_gradient=gl.reshape(B, n, 3),
        pose_blocks=U,
        point_weight=v,
        weight=w,
        coupling_weight=w * free_pose * free_point,
        points=points,
        free_pose=free_pose,
        free_point=free_point,
    )


def _blocks(r, J_xi, J_X, factor, free_pose, free_point, data):
    B = data.pose_index.shape[0]
    m, n = data.num_poses, data.num_points
    J = torch.cat((J_xi * free_pose[..., None, None], J_X * free_point[..., None, None]), -1)
    valid = data.valid[..., None, None]
    rw = torch.where(valid, _whiten(factor, r[..., None]), torch.zeros_like(r[..., None]))
    Jw = torch.where(valid, _whiten(factor, J), torch.zeros_like(J))
    s = (rw * rw).sum(dim=(-1, -2))
    if data.loss is None:
        cost = 0.5 * s.sum(-1)
    else:
        rho, rho1, rho2 = data.loss(s)
        cost = 0.5 * torch.where(data.valid, rho, torch.zeros_like(rho)).sum(-1)
        residual_scale, alpha_over_s = losses.triggs_correction(s, rho1, rho2)
        sqrt_rho1 = torch.sqrt(rho1)[..., None, None]
        Jw = sqrt_rho1 * (Jw - alpha_over_s[..., None, None] * rw @ (rw.transpose(-1, -2) @ Jw))
        rw = residual_scale[..., None, None] * rw
        rw = torch.where(valid, rw, torch.zeros_like(rw))
        Jw = torch.where(valid, Jw, torch.zeros_like(Jw))

    JtJ = Jw.transpose(-1, -2) @ Jw  # (B, E, 9, 9)
    Jtr = (Jw.transpose(-1, -2) @ rw)[..., 0]  # (B, E, 9)
    pose_slot, point_slot = _slots(data)
    U = JtJ.new_zeros(B * m, 6, 6).index_add_(0, pose_slot, JtJ[..., :6, :6].reshape(-1, 6, 6))
    V = JtJ.new_zeros(B * n, 3, 3).index_add_(0, point_slot, JtJ[..., 6:, 6:].reshape(-1, 3, 3))
    gp = Jtr.new_zeros(B * m, 6).index_add_(0, pose_slot, Jtr[..., :6].reshape(-1, 6))
    gl = Jtr.new_zeros(B * n, 3).index_add_(0, point_slot, Jtr[..., 6:].reshape(-1, 3))
    eye6 = torch.eye(6, dtype=U.dtype, device=U.device)
    eye3 = torch.eye(3, dtype=U.dtype, device=U.device)
    U = torch.where(data.fixed_poses[..., None, None], eye6, U.reshape(B, m, 6, 6))
    V = torch.where(data.fixed_points[..., None, None], eye3, V.reshape(B, n, 3, 3))
    return BlockLinearization(
        cost=cost,
        pose_gradient=gp.reshape(B, m, 6),
        point_gradient=gl.reshape(B, n, 3),
        pose_blocks=U,
        point_blocks=V,
        residuals=rw[..., 0],
        jacobian=Jw,
        coupling=JtJ[..., :6, 6:],
    )


def term_pair_keys(data: PointMapData) -> Tensor:
    """Block (b, i_a, i_b) of each of the ``pair_blocks`` as (b·m + i_a)·m + i_b, long (B, P)."""
    m = data.num_poses
    B = data.pose_index.shape[0]
    batch = torch.arange(B, device=data.pose_index.device)[:, None]
    keys = []
    for term in data.terms:
        for a in range(term.arity):
            for b in range(term.arity):
                if a != b:
                    keys.append((batch * m + term.pose_index[..., a]) * m + term.pose_index[..., b])
    if not keys:
        return data.pose_index.new_zeros(B, 0)
    return torch.cat(keys, dim=1)


def linearize_terms(poses: Tensor, data: PointMapData, jacobian_mode: str) -> TermLinearization:
    """The pose terms' normal-equation blocks at poses T (B, m, 4, 4) (module doc)."""
    B, m = poses.shape[:2]
    cost = poses.new_zeros(B)
    gradient = poses.new_zeros(B * m, 6)
    diagonal = poses.new_zeros(B * m, 6, 6)
    pairs, jacobians, scales = [], [], []
    batch = torch.arange(B, device=poses.device)[:, None, None]
    for term in data.terms:
        r, J = term_jacobians(term, term_poses(term, poses), jacobian_mode)
        slots = batch * m + term.pose_index  # (B, K, a)
        free = ~data.fixed_poses.reshape(-1)[slots]
        rw, Jw, scale = _whitened_term(term, r, J * free[:, :, None, :, None])
        term_cost, rw, Jw = _robustified(term, rw, Jw, scale)
        cost = cost + term_cost
        jacobians.append(Jw)
        scales.append(scale)
        a = term.arity
        K = r.shape[1]
        Jt = Jw.transpose(-3, -2)  # (B, K, a, d, 6)
        g = (Jt.transpose(-1, -2) @ rw[:, :, None, :, None])[..., 0]  # (B, K, a, 6)
        g = scale[:, :, None, None] * g
        gradient.index_add_(0, slots.reshape(-1), g.reshape(-1, 6))
        H = Jt[:, :, :, None].transpose(-1, -2) @ Jt[:, :, None, :]  # (B, K, a, a, 6, 6)
        H = scale[:, :, None, None, None, None] * H
        idx = torch.arange(a, device=poses.device)
        diagonal.index_add_(0, slots.reshape(-1), H[:, :, idx, idx].reshape(-1, 6, 6))
        for i in range(a):
            for j in range(a):
                if i != j:
                    pairs.append(H[:, :, i, j].reshape(B, K, 6, 6))
    pair_blocks = torch.cat(pairs, dim=1) if pairs else poses.new_zeros(B, 0, 6, 6)
    return TermLinearization(
        cost=cost,
        gradient=gradient.reshape(B, m, 6),
        diagonal=diagonal.reshape(B, m, 6, 6),
        pair_blocks=pair_blocks,
        jacobians=tuple(jacobians),
        scales=tuple(scales),
    )


def _whitened_term(term: Term, r: Tensor, J: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(U r, U J, ones) for information matrices, (r, J, w) for scalar weights, (r, J, ones)
    otherwise (J (B, K, d, a, 6)); zero on padding."""
    scale = torch.ones_like(r[..., 0])
    valid = term.valid
    # Padding instances: zero residual and blocks before whitening (no NaN into U r, U J).
    r = torch.where(valid[..., None], r, 0.0)
    J = torch.where(valid[..., None, None, None], J, 0.0)
    if term.information is not None:
        U = term_whitening(term)
        r = (U @ r[..., None])[..., 0]
        J = (U @ J.flatten(-2)).reshape(J.shape)
    elif term.weight is not None:
        scale = masked_weighting(term)[0]
    return (
        torch.where(valid[..., None], r, torch.zeros_like(r)),
        torch.where(valid[..., None, None, None], J, torch.zeros_like(J)),
        torch.where(valid, scale, torch.zeros_like(scale)),
    )


def _robustified(
    term: Term, rw: Tensor, Jw: Tensor, scale: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """(cost (B,), r̃, J̃): ½ Σ ρ(s), s = w |U r|², and Ceres' corrector of r and J.

    The corrector is applied to the unscaled r, J: with r̂ = r/|r| it needs only
    α r̂ r̂ᵀ = (α/s)·w·r rᵀ, so no √w appears; the products are multiplied by w afterwards.
    """
    s = scale * (rw * rw).sum(-1)
    if term.loss is None:
        return 0.5 * s.sum(-1), rw, Jw
    rho, rho1, rho2 = term.loss(s)
    cost = 0.5 * torch.where(term.valid, rho, torch.zeros_like(rho)).sum(-1)
    residual_scale, alpha_over_s = losses.triggs_correction(s, rho1, rho2)
    shape = Jw.shape
    Jf = Jw.flatten(-2)  # (B, K, d, a·6)
    projector = (alpha_over_s * scale)[..., None, None] * rw[..., :, None]
    Jf = torch.sqrt(rho1)[..., None, None] * (Jf - projector * (rw[..., None, :] @ Jf))
    rw = residual_scale[..., None] * rw
    valid = term.valid
    return (
        cost,
        torch.where(valid[..., None], rw, torch.zeros_like(rw)),
        torch.where(valid[..., None, None], Jf, torch.zeros_like(Jf)).reshape(shape),
    )


def cost_at(
    pose_tangent: Tensor, points: Tensor, data: PointMapData, factor: Tensor | None
) -> Tensor:
    """½ Σ ρ(s) per problem, (B,), with the same whitening as :func:`linearize`."""
    r, _, _ = _residuals(pose_tangent, points, data)
    rw = _whiten(factor, r[..., None])
    s = (rw * rw).sum(dim=(-1, -2))
    if data.loss is not None:
        s = data.loss(s)[0]
    points_cost = 0.5 * torch.where(data.valid, s, torch.zeros_like(s)).sum(-1)
    return points_cost + terms_cost(data.terms, se3._exp(pose_tangent))


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
        X_e = gather_points(lin.points, data)
        # J̃δ = √w · (−R)(δX + δω × X + δv): its norm needs no R.
        u = (
            dl_e * lin.free_point[..., None]
            + (so3._hat(dp_e[..., :3]) @ X_e[..., None])[..., 0] * lin.free_pose[..., None]
            + dp_e[..., 3:] * lin.free_pose[..., None]
        )
        quad = (lin.weight * (u * u).sum(-1)).sum(-1)
    else:
        Jd = (lin.jacobian @ torch.cat((dp_e, dl_e), -1)[..., None])[..., 0]
        quad = (Jd * Jd).sum((-1, -2))
    if lin.terms is not None:
        B, m = dp.shape[:2]
        batch = torch.arange(B, device=dp.device)[:, None, None]
        for term, J, scale in zip(data.terms, lin.terms.jacobians, lin.terms.scales, strict=True):
            K, a = term.pose_index.shape[1:]
            d_term = dp.reshape(B * m, 6)[(batch * m + term.pose_index).reshape(-1)]
            Jd = (J.flatten(-2) @ d_term.reshape(B, K, a * 6, 1))[..., 0]
            quad = quad + (scale * (Jd * Jd).sum(-1)).sum(-1)
    return -(g_dot + 0.5 * quad)
