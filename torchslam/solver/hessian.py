"""The exact Hessian of the objective in the chart, in the forward solve's block structure.

The implicit backward of :func:`torchslam.solve_differentiable` (``ImplicitConfig(hessian=
"exact")``) needs H = ∇²F(x ⊞ δ) at δ = 0, with x ⊞ δ = (T·Exp(δ_p), X + δ_l) (right
perturbation, δ_p = (ω, v) rotation first). :func:`exact_hessian` returns it as a
:class:`~torchslam.solver.linearize.BlockLinearization` — pose blocks (B, m, 6, 6), point
blocks (B, n, 3, 3), pose–point coupling blocks on the edges of
:func:`~torchslam.solver.linearize.coupling_edges` and the terms' pose-pair blocks — so that
:meth:`torchslam.solver.plan.LinearPlan.factorize` (λ = 0) factors it exactly like the forward
solve factors its Gauss-Newton matrix (dense or sparse reduced system, or the full system).

Every residual r (d entries; whitened by Ω = UᵀU or a scalar weight w, so Ω = w I) with
robust kernel ρ applied to s = rᵀΩr contributes, over the variables it touches (J = ∂r/∂δ),

    H = Jᵀ (ρ' Ω + 2ρ'' (Ωr)(Ωr)ᵀ) J + Σ_k λ_k ∇²r_k,      λ = ρ' Ω r,

the exact second derivative of ½ρ(s) (the forward's Triggs corrector approximates the first
part; here ρ'' enters as it is). ρ' = 1, ρ'' = 0 without a kernel.

Point observations, r = z − T Exp(δ) X: to second order Exp(δ)(X + δX) = X + ω × X + v +
ω × δX + ½ ω × (ω × X) + ½ ω × v, so with μ = Rᵀλ (λ in the frame, μ in the world)

    Σ_k λ_k ∇²r_k = −∇²(μ · Exp(δ)(X + δX)):
        ωω: (μ·X) I − ½ (μ Xᵀ + X μᵀ),   ωv: ½ [μ]×,   vω: −½ [μ]×,
        ωX: [μ]×,                        Xω: −[μ]×,    vv = vX = XX = 0

(μᵀ(ω × v) = −ωᵀ[μ]× v gives the antisymmetric ωv pair; r is linear in X). Terms
(:mod:`torchslam.objective.terms`): the second-order part of each instance is the Hessian of
λᵀ r(T_a Exp(δ_a), X + δX) at zero (λ held fixed), by ``torch.func.hessian`` vmapped over the
instances; their first-order blocks J come from :func:`~torchslam.objective.terms.term_blocks`
(analytic where the term has them).

Fixed variables get an identity block and no coupling (as in the forward's linearization);
padding and masked-out entries (``valid`` False) contribute exactly zero, whatever they hold.
H need not be positive definite (a robust kernel's far residuals, a saddle): the
factorization then reports ``ok`` False for that problem.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchslam._batched import matmul
from torchslam.lie import se3, so3
from torchslam.objective.data import PointMapData, gather_points, per_observation
from torchslam.objective.terms import (
    Term,
    masked_constants,
    masked_weighting,
    term_blocks,
    term_free_poses,
    term_points,
    term_poses,
)
from torchslam.solver.linearize import BlockLinearization, TermAccumulator, TermLinearization

__all__ = ["dense_hessian", "exact_hessian"]


def _kernel(s: Tensor, valid: Tensor, loss: object | None) -> tuple[Tensor, Tensor, Tensor]:
    """(ρ, ρ', ρ'') of squared norms s, zero where ``valid`` is False."""
    if loss is None:
        rho1 = valid.to(s.dtype)
        return s, rho1, torch.zeros_like(s)
    zero = torch.zeros((), dtype=s.dtype, device=s.device)
    return tuple(torch.where(valid, x, zero) for x in loss(s))


def _curvature(
    r: Tensor,
    valid: Tensor,
    weight: Tensor | None,
    information: Tensor | None,
    loss: object | None,
) -> tuple[Tensor, Tensor, Tensor]:
    """(½ρ(s) (…,), λ = ρ'Ωr (…, d), M = ρ'Ω + 2ρ''(Ωr)(Ωr)ᵀ (…, d, d)) of residuals r (…, d);
    exactly zero where ``valid`` is False. ``weight`` (…) / ``information`` (…, d, d) are the
    masked ones (finite on padding); neither: Ω = I."""
    zero = torch.zeros((), dtype=r.dtype, device=r.device)
    r = torch.where(valid[..., None], r, zero)
    eye = torch.eye(r.shape[-1], dtype=r.dtype, device=r.device)
    if information is not None:
        omega = torch.where(valid[..., None, None], information, zero)
    else:
        scale = valid.to(r.dtype) if weight is None else torch.where(valid, weight, zero)
        omega = scale[..., None, None] * eye
    omega_r = matmul(omega, r[..., None])[..., 0]
    # rᵀΩr ≥ 0 in exact arithmetic; clamp the round-off of an indefinite-looking product.
    s = (r * omega_r).sum(-1).clamp_min(0.0)
    rho, rho1, rho2 = _kernel(s, valid, loss)
    lam = rho1[..., None] * omega_r
    M = rho1[..., None, None] * omega + (2.0 * rho2)[..., None, None] * (
        omega_r[..., :, None] * omega_r[..., None, :]
    )
    return 0.5 * rho, lam, M


def _point_observations(poses: Tensor, points: Tensor, data: PointMapData):
    """The point observations' exact blocks (module doc): (cost (B,), U (B, m, 6, 6),
    V (B, n, 3, 3), W (B, E, 6, 3) per observation, pose gradient (B, m, 6), point gradient
    (B, n, 3)); padding contributes zero, and so do fixed variables to the coupling (their
    own blocks and gradients are replaced by the caller).

    With J_ξ = −R G, G = [−A | I], A = [X]×, J_X = −R and M̃ = Rᵀ M R, μ = Rᵀλ:
    J_ξᵀMJ_ξ = [[−A M̃ A, A M̃], [−M̃ A, M̃]], J_ξᵀMJ_X = [A M̃; M̃], J_XᵀMJ_X = M̃,
    J_ξᵀλ = (μ × X, −μ), J_Xᵀλ = −μ; plus the second-order blocks."""
    B = data.valid.shape[0]
    m, n = data.num_poses, data.num_points
    T_e = per_observation(poses, data.flat_pose_index)
    X_e = gather_points(points, data)
    valid = data.valid
    r = data.masked_observations() - se3.act(T_e, X_e)
    r = torch.where(valid[..., None], r, 0.0)
    free_pose = ~torch.gather(data.fixed_poses, 1, data.pose_index)
    both = (free_pose & ~torch.gather(data.fixed_points, 1, data.point_index)).to(r.dtype)
    R = T_e[..., :3, :3]
    Rt = R.transpose(-1, -2)
    eye = torch.eye(3, dtype=r.dtype, device=r.device)
    if data.information is not None:
        cost, lam, M = _curvature(r, valid, None, data.masked_information(), data.loss)
        Mt = matmul(Rt, matmul(M, R))
        mu = matmul(Rt, lam[..., None])[..., 0]
    else:
        # Ω = w I: M̃ = ρ'w I + 2ρ''w² q qᵀ and μ = ρ'w q with q = Rᵀr (no 3 × 3 products).
        w = valid.to(r.dtype) if data.weights is None else torch.where(valid, data.weights, 0.0)
        q = matmul(Rt, r[..., None])[..., 0]
        s = w * (r * r).sum(-1)
        rho, rho1, rho2 = _kernel(s, valid, data.loss)
        cost = 0.5 * rho
        c = rho1 * w
        mu = c[..., None] * q
        wq = w[..., None] * q
        Mt = c[..., None, None] * eye + (2.0 * rho2)[..., None, None] * (
            wq[..., :, None] * wq[..., None, :]
        )
    # A M̃ = X × (columns of M̃); −(A M̃) A = X × (rows of A M̃) (Aᵀ = −A).
    AM = torch.linalg.cross(X_e[..., :, None].expand_as(Mt), Mt, dim=-2)
    minus_AMA = torch.linalg.cross(X_e[..., None, :].expand_as(AM), AM, dim=-1)
    mu_x = so3.hat(mu)
    outer = mu[..., :, None] * X_e[..., None, :]
    top_left = (
        minus_AMA
        + (mu * X_e).sum(-1)[..., None, None] * eye
        - 0.5 * (outer + outer.transpose(-1, -2))
    )
    # The blocks and gradients of fixed variables are replaced below (identity, zero), so
    # only the coupling needs the masks.
    pose_parts = torch.stack((top_left, AM + 0.5 * mu_x, Mt), 2)
    pose_slot = data.flat_pose_index.reshape(-1)
    point_slot = data.flat_point_index.reshape(-1)
    sums = r.new_zeros(B * m, 3, 3, 3).index_add_(0, pose_slot, pose_parts.reshape(-1, 3, 3, 3))
    tl, tr, br = sums.unbind(1)
    U = torch.cat((torch.cat((tl, tr), -1), torch.cat((tr.transpose(-1, -2), br), -1)), -2)
    V = r.new_zeros(B * n, 3, 3).index_add_(0, point_slot, Mt.reshape(-1, 3, 3))
    W = torch.cat((AM + mu_x, Mt), -2) * both[..., None, None]
    g_pose = torch.cat((torch.linalg.cross(mu, X_e, dim=-1), -mu), -1)
    gp = r.new_zeros(B * m, 6).index_add_(0, pose_slot, g_pose.reshape(-1, 6))
    gl = r.new_zeros(B * n, 3).index_add_(0, point_slot, -mu.reshape(-1, 3))
    return (
        cost.sum(-1),
        U.reshape(B, m, 6, 6),
        V.reshape(B, n, 3, 3),
        W,
        gp.reshape(B, m, 6),
        gl.reshape(B, n, 3),
    )


def _term_second_order(term: Term, poses: Tensor, X: Tensor | None, lam: Tensor) -> Tensor:
    """Σ_k λ_k ∇²r_k of every instance, (B, K, c, c) with c = 6a (+ 3 for a point term): the
    Hessian of λᵀ r(T_a Exp(δ_a), X + δX) at zero by ``torch.func``, vmapped."""
    B, K, a = poses.shape[:3]
    c = 6 * a + (3 if term.has_point else 0)
    N = B * K
    if N == 0 or c == 0:
        return lam.new_zeros(B, K, c, c)
    constants = {k: v.reshape(N, *v.shape[2:]) for k, v in masked_constants(term).items()}
    Ts = poses.reshape(N, a, 4, 4)
    Xs = X.reshape(N, 3) if X is not None else lam.new_zeros(N, 0)
    lams = lam.reshape(N, -1)

    def contraction(z: Tensor, T: Tensor, point: Tensor, weight: Tensor, consts) -> Tensor:
        moved = T @ se3.exp(z[: 6 * a].reshape(a, 6), form="fast")
        if term.has_point:
            r = term.residual(moved, point + z[6 * a :], **consts)
        else:
            r = term.residual(moved, **consts)
        return (weight * r).sum()

    hessian = torch.func.vmap(torch.func.hessian(contraction))
    return hessian(lam.new_zeros(N, c), Ts, Xs, lams, constants).reshape(B, K, c, c)


def _term_blocks(term: Term, poses: Tensor, points: Tensor, data: PointMapData, mode: str):
    """(cost (B,), gradient (B, K, c), exact Hessian (B, K, c, c)) of one bound term's
    instances, c = 6a (+ 3); fixed variables' rows and columns zero, padding zero."""
    X = term_points(term, points) if term.has_point else None
    T = term_poses(term, poses)
    r, J, J_point = term_blocks(term, T, X, mode)
    B, K, a = term.pose_index.shape
    valid = term.valid
    free = term_free_poses(term, data.fixed_poses)
    pose_mask = torch.ones(B, K, a, 6, dtype=r.dtype, device=r.device)
    if free is not None:
        pose_mask = pose_mask * free[..., None]
    mask = pose_mask.reshape(B, K, 6 * a)
    J = J.flatten(-2) * mask[:, :, None, :]
    if term.has_point:
        n = points.shape[1]
        batch = torch.arange(B, device=points.device)[:, None]
        free_point = ~data.fixed_points.reshape(-1)[batch * n + term.point_index]
        point_mask = free_point[..., None].to(r.dtype).expand(B, K, 3)
        mask = torch.cat((mask, point_mask), -1)
        J = torch.cat((J, J_point * point_mask[:, :, None, :]), -1)
    J = torch.where(valid[..., None, None], J, 0.0)
    weight, information = masked_weighting(term)
    cost, lam, M = _curvature(r, valid, weight, information, term.loss)
    Jt = J.transpose(-1, -2)
    H = matmul(Jt, matmul(M, J))
    second = _term_second_order(term, T, X, lam)
    second = torch.where(valid[..., None, None], second, 0.0)
    H = H + second * mask[..., :, None] * mask[..., None, :]
    return cost.sum(-1), matmul(Jt, lam[..., None])[..., 0], H


def _terms(poses: Tensor, points: Tensor, data: PointMapData, mode: str) -> TermLinearization:
    """The terms' exact blocks in the layout of :func:`~.linearize.linearize_terms`."""
    B, n = poses.shape[0], points.shape[1]
    total = TermAccumulator(poses, points)
    for term in data.terms:
        if term.has_point and n == 0:
            continue  # no points: every instance of the term is padding
        term_cost, g, H = _term_blocks(term, poses, points, data, mode)
        K, a = term.pose_index.shape[1:]
        P = 6 * a
        # (a, a, B, K, 6, 6) views of the pose blocks of the instances' full (c × c) H.
        pose_blocks = H[..., :P, :P].reshape(B, K, a, 6, a, 6).permute(2, 4, 0, 1, 3, 5)
        total.add(term, term_cost, g, pose_blocks, H[..., P:, P:], H[..., :P, P:])
    return total.result()


def exact_hessian(
    pose_tangent: Tensor, points: Tensor, data: PointMapData, jacobian_mode: str = "analytic"
) -> BlockLinearization:
    """The exact Hessian (and gradient) of the objective at (ξ (B, m, 6), X (B, n, 3)) in
    the chart (T·Exp(δ_p), X + δ_l), as the blocks the forward's plan factors (module doc).

    Args:
        pose_tangent: ξ (B, m, 6); points: X (B, n, 3); data: the problem.
        jacobian_mode: how the terms' first-order blocks are formed ("analytic" uses their
            analytic Jacobians where they have them, "jacrev" always differentiates).

    Returns:
        A :class:`~torchslam.solver.linearize.BlockLinearization` whose ``pose_blocks``,
        ``point_blocks``, ``coupling`` (edges of :func:`~.linearize.coupling_edges`) and
        ``terms.pair_blocks`` (order of :func:`~.linearize.term_pair_keys`) hold H,
        ``pose_gradient``/``point_gradient`` the gradient and ``cost`` the cost (B,);
        ``residuals`` and ``jacobian`` are zeros and ``terms.jacobians`` is empty: no model
        decrease is evaluated on it.
        Fixed variables: identity blocks, zero gradient and coupling.
    """
    poses = se3.exp(pose_tangent, form="fast")
    cost, U, V, coupling, gp, gl = _point_observations(poses, points, data)
    terms = None
    if data.terms:
        terms = _terms(poses, points, data, jacobian_mode)
        cost = cost + terms.cost
        U = U + terms.diagonal
        gp = gp + terms.gradient
        V = V + terms.point_diagonal
        gl = gl + terms.point_gradient
        coupling = torch.cat((coupling, terms.coupling), dim=1)
    eye6 = torch.eye(6, dtype=U.dtype, device=U.device)
    eye3 = torch.eye(3, dtype=U.dtype, device=U.device)
    U = torch.where(data.fixed_poses[..., None, None], eye6, U)
    V = torch.where(data.fixed_points[..., None, None], eye3, V)
    gp = torch.where(data.fixed_poses[..., None], 0.0, gp)
    gl = torch.where(data.fixed_points[..., None], 0.0, gl)
    return BlockLinearization(
        cost=cost,
        pose_gradient=gp,
        point_gradient=gl,
        pose_blocks=U,
        point_blocks=V,
        residuals=coupling.new_zeros(*coupling.shape[:2], 3),
        jacobian=coupling.new_zeros(*coupling.shape[:2], 3, 9),
        coupling=coupling,
        terms=terms,
        poses=poses,
    )


def dense_hessian(lin: BlockLinearization, data: PointMapData) -> Tensor:
    """The full symmetric (B, 6m + 3n, 6m + 3n) matrix of a block linearization (poses
    first, then points): small problems, tests and diagnostics only."""
    from torchslam.solver.linearize import coupling_edges, term_pair_keys

    B, m = lin.pose_blocks.shape[:2]
    n = lin.point_blocks.shape[1]
    N = 6 * m + 3 * n
    H = lin.pose_blocks.new_zeros(B, N, N)
    device = H.device

    def add(batch: Tensor, row: Tensor, col: Tensor, blocks: Tensor) -> None:
        """H[b, row + r, col + c] += blocks[…, r, c] for blocks (…, p, q) at offsets (…)."""
        p, q = blocks.shape[-2:]
        r = row[..., None, None] + torch.arange(p, device=device)[:, None]
        c = col[..., None, None] + torch.arange(q, device=device)
        b = batch[..., None, None].expand(*r.shape[:-2], p, q)
        H.index_put_((b, r.expand(b.shape), c.expand(b.shape)), blocks, accumulate=True)

    batch = torch.arange(B, device=device)[:, None]
    poses = 6 * torch.arange(m, device=device).expand(B, m)
    points = 6 * m + 3 * torch.arange(n, device=device).expand(B, n)
    add(batch.expand(B, m), poses, poses, lin.pose_blocks)
    add(batch.expand(B, n), points, points, lin.point_blocks)
    edges = coupling_edges(data)
    coupling = torch.where(edges.active[..., None, None], lin.coupling, 0.0)
    row, col = 6 * edges.pose_index, 6 * m + 3 * edges.point_index
    edge_batch = batch.expand_as(row)
    add(edge_batch, row, col, coupling)
    add(edge_batch, col, row, coupling.transpose(-1, -2))
    if lin.terms is not None and lin.terms.pair_blocks.shape[1] > 0:
        keys = term_pair_keys(data) % (m * m)
        add(batch.expand_as(keys), 6 * (keys // m), 6 * (keys % m), lin.terms.pair_blocks)
    return H
