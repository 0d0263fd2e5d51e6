"""Relative-pose (between) and pose-prior residuals on SE(3), with analytic Jacobians.

Conventions: ξ = (ω, v), rotation first; right perturbation T ← T·Exp(δ); a pose graph vertex
T_i maps body-i points into the world, and an edge measures Z_ij ≈ T_i⁻¹ T_j (g2o's meaning).

Residuals
    between:  r_ij = Log(Z_ij⁻¹ · T_i⁻¹ · T_j)     (6,), zero when T_i⁻¹ T_j = Z_ij
    prior:    r    = Log(Z⁻¹ · T)                 (6,), zero when T = Z

Derivation of the analytic Jacobians. Write E = Z⁻¹ T_i⁻¹ T_j, so r = Log(E), and use the
right Jacobian of SE(3): Exp(r + d) ≈ Exp(r) Exp(Jr(r) d), hence for small δ

    Log(Exp(r) · Exp(δ)) = r + Jr⁻¹(r) δ + O(|δ|²).                                   (1)

* Perturb T_j ← T_j Exp(δ_j): E ← E Exp(δ_j), so by (1)

      J_r_delta_j = ∂r/∂δ_j = Jr⁻¹(r).

* Perturb T_i ← T_i Exp(δ_i): T_i⁻¹ ← Exp(−δ_i) T_i⁻¹ and, moving the perturbation to the
  right through A = T_j⁻¹ T_i with A Exp(d) A⁻¹ = Exp(Ad(A) d),

      E ← Z⁻¹ Exp(−δ_i) T_i⁻¹ T_j = E · A Exp(−δ_i) A⁻¹ = E · Exp(−Ad(T_j⁻¹ T_i) δ_i),

  so by (1)

      J_r_delta_i = ∂r/∂δ_i = −Jr⁻¹(r) · Ad(T_j⁻¹ T_i).

  Since Ad(Exp(r)) Jr(r) = Jl(r) and T_j⁻¹ T_i = E⁻¹ Z⁻¹, this also equals −Jl⁻¹(r) Ad(Z⁻¹);
  at the measurement (r = 0) the blocks are (−Ad(Z⁻¹), I).

* Prior, T ← T Exp(δ): Z⁻¹ T Exp(δ) = Exp(r) Exp(δ), so J_r_delta = Jr⁻¹(r).

The blocks are 6 × 6 with rows and columns in (ω, v) order. Jr⁻¹ stays finite for |ω| < 2π, so
the blocks are exact up to |ω| = π (at exactly π, Log itself jumps between ±ω).

Whitening. With Ω = L Lᵀ (Cholesky, L lower triangular) and U = Lᵀ, the weighted cost is
½ rᵀ Ω r = ½ |U r|²; the whitened residual is U r and the whitened Jacobian blocks are U J.

The ``*_jacrev`` functions differentiate r(T_i Exp(δ_i), T_j Exp(δ_j)) at δ = 0 with
``torch.func.jacrev`` vmapped over the edges; they agree with the analytic blocks to round-off
and are the reference the tests check them against.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchslam import _checks
from torchslam.lie import se3
from torchslam.manifold import right_jacobian_jacrev
from torchslam.objective.terms import (
    pose_prior_residual,
    relative_pose_jacobians,
    relative_pose_residual,
)

__all__ = [
    "between_jacobians",
    "between_jacobians_jacrev",
    "between_residual",
    "prior_jacobian",
    "prior_jacobian_jacrev",
    "prior_residual",
    "sqrt_information",
    "weighted_cost",
    "whiten_jacobian",
    "whiten_residual",
]


def _check_poses(fn: str, **poses: Tensor) -> None:
    for name, T in poses.items():
        _checks.check_tensor(fn, name, T, (4, 4))
    _checks.check_same_kind(fn, **poses)
    for name, T in poses.items():
        _checks.check_pose_matrix(fn, name, T)


def _between(T_i: Tensor, T_j: Tensor, Z_ij: Tensor) -> Tensor:
    # The one relative-pose residual on body → world vertices (objective.terms).
    with _checks.validation(False):
        return relative_pose_residual(T_i, T_j, Z_ij, "frame_to_world")


def _prior(T: Tensor, Z: Tensor) -> Tensor:
    with _checks.validation(False):
        return pose_prior_residual(T, Z)


def between_residual(T_i: Tensor, T_j: Tensor, Z_ij: Tensor) -> Tensor:
    """Relative-pose residual r_ij = Log(Z_ij⁻¹ · T_i⁻¹ · T_j), ξ = (ω, v): rotation first.

    Zero when the relative pose T_i⁻¹ T_j equals the measurement Z_ij (g2o's T_ij).

    Args:
        T_i: poses of the first vertices (body i → world), shape (..., 4, 4).
        T_j: poses of the second vertices, shape (..., 4, 4).
        Z_ij: measured relative poses Z_ij ≈ T_i⁻¹ T_j, shape (..., 4, 4).
        The leading dims broadcast; all three share dtype and device.

    Returns:
        Residuals r = (ω, v), shape broadcast(...) + (6,), with |ω| ∈ [0, π].
    """
    _check_poses("between_residual", T_i=T_i, T_j=T_j, Z_ij=Z_ij)
    return _between(T_i, T_j, Z_ij)


def between_jacobians(T_i: Tensor, T_j: Tensor, Z_ij: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Residual and analytic Jacobians of r_ij = Log(Z_ij⁻¹ T_i⁻¹ T_j) (module docstring).

    J_r_delta_i = ∂r/∂δ_i at δ_i = 0 for T_i ← T_i·Exp(δ_i), equal to −Jr⁻¹(r)·Ad(T_j⁻¹ T_i);
    J_r_delta_j = ∂r/∂δ_j at δ_j = 0 for T_j ← T_j·Exp(δ_j), equal to Jr⁻¹(r).
    Rows and columns in (ω, v) order: rotation first.

    Args:
        T_i: poses of the first vertices, shape (..., 4, 4).
        T_j: poses of the second vertices, shape (..., 4, 4).
        Z_ij: measured relative poses, shape (..., 4, 4). Leading dims broadcast.

    Returns:
        ``(r, J_r_delta_i, J_r_delta_j)`` of shapes (..., 6), (..., 6, 6), (..., 6, 6).
    """
    _check_poses("between_jacobians", T_i=T_i, T_j=T_j, Z_ij=Z_ij)
    with _checks.validation(False):
        return relative_pose_jacobians(T_i, T_j, Z_ij, "frame_to_world")


def between_jacobians_jacrev(T_i: Tensor, T_j: Tensor, Z_ij: Tensor) -> tuple[Tensor, Tensor]:
    """The blocks of :func:`between_jacobians` by ``torch.func.jacrev`` (vmapped) at δ = 0.

    Differentiates r(T_i·Exp(δ_i), T_j·Exp(δ_j), Z_ij) with respect to δ_i and δ_j, ξ = (ω, v).

    Args:
        T_i: poses of the first vertices, shape (..., 4, 4).
        T_j: poses of the second vertices, shape (..., 4, 4).
        Z_ij: measured relative poses, shape (..., 4, 4). Leading dims broadcast.

    Returns:
        ``(J_r_delta_i, J_r_delta_j)``, each of shape broadcast(...) + (6, 6).
    """
    _check_poses("between_jacobians_jacrev", T_i=T_i, T_j=T_j, Z_ij=Z_ij)
    batch = _checks.broadcast_shapes(T_i.shape[:-2], T_j.shape[:-2], Z_ij.shape[:-2])
    Ti, Tj, Z = (T.expand(*batch, 4, 4) for T in (T_i, T_j, Z_ij))
    return right_jacobian_jacrev(_between, (Ti, Tj), constants=(Z,), batch_dims=len(batch))


def prior_residual(T: Tensor, Z: Tensor) -> Tensor:
    """Pose-prior residual r = Log(Z⁻¹ · T), ξ = (ω, v): rotation first; zero when T = Z.

    Args:
        T: poses, shape (..., 4, 4).
        Z: prior poses, shape (..., 4, 4). Leading dims broadcast.

    Returns:
        Residuals, shape broadcast(...) + (6,).
    """
    _check_poses("prior_residual", T=T, Z=Z)
    return _prior(T, Z)


def prior_jacobian(T: Tensor, Z: Tensor) -> tuple[Tensor, Tensor]:
    """Residual and Jacobian of r = Log(Z⁻¹ T): J_r_delta = ∂r/∂δ = Jr⁻¹(r) for T ← T·Exp(δ).

    Args:
        T: poses, shape (..., 4, 4).
        Z: prior poses, shape (..., 4, 4). Leading dims broadcast.

    Returns:
        ``(r, J_r_delta)`` of shapes (..., 6) and (..., 6, 6), (ω, v) order.
    """
    _check_poses("prior_jacobian", T=T, Z=Z)
    r = _prior(T, Z)
    with _checks.validation(False):
        return r, se3.jr_inv(r, form="fast")


def prior_jacobian_jacrev(T: Tensor, Z: Tensor) -> Tensor:
    """The block of :func:`prior_jacobian` by ``torch.func.jacrev`` (vmapped) at δ = 0.

    Args:
        T: poses, shape (..., 4, 4).
        Z: prior poses, shape (..., 4, 4). Leading dims broadcast.

    Returns:
        J_r_delta, shape broadcast(...) + (6, 6).
    """
    _check_poses("prior_jacobian_jacrev", T=T, Z=Z)
    batch = _checks.broadcast_shapes(T.shape[:-2], Z.shape[:-2])
    (J,) = right_jacobian_jacrev(
        _prior,
        (T.expand(*batch, 4, 4),),
        constants=(Z.expand(*batch, 4, 4),),
        batch_dims=len(batch),
    )
    return J


def sqrt_information(information: Tensor) -> Tensor:
    """Upper-triangular square root U = Lᵀ of Ω = L Lᵀ (Cholesky), so that UᵀU = Ω.

    Then ½ rᵀ Ω r = ½ |U r|². When validation is on, a matrix that is not symmetric positive
    definite raises ValueError naming its batch index.

    Args:
        information: symmetric positive-definite information matrices, shape (..., k, k)
            (k = 6 for SE(3) residuals, in (ω, v) order).

    Returns:
        U, shape (..., k, k), upper triangular.
    """
    fn = "sqrt_information"
    _checks.check_tensor(fn, "information", information, min_batch_dims=0)
    if information.dim() < 2 or information.shape[-1] != information.shape[-2]:
        raise ValueError(
            f"{fn}: argument 'information' must have shape (..., k, k), "
            f"got {tuple(information.shape)}"
        )
    L, info = torch.linalg.cholesky_ex(information)
    if _checks.value_checks_active() and information.numel() > 0 and bool((info > 0).any()):
        idx = tuple(int(i) for i in (info > 0).nonzero()[0].tolist())
        raise ValueError(
            f"{fn}: argument 'information' must be symmetric positive definite; "
            f"the Cholesky factorization fails at batch index {idx}"
        )
    return L.transpose(-1, -2)


def whiten_residual(sqrt_information: Tensor, residual: Tensor) -> Tensor:
    """Whitened residual U r, so that |U r|² = rᵀ Ω r.

    Args:
        sqrt_information: U from :func:`sqrt_information`, shape (..., k, k).
        residual: residuals, shape (..., k). Leading dims broadcast.

    Returns:
        U r, shape broadcast(...) + (k,).
    """
    k = residual.shape[-1] if residual.dim() > 0 else 0
    _checks.check_tensor("whiten_residual", "sqrt_information", sqrt_information, (k, k))
    _checks.check_tensor("whiten_residual", "residual", residual, (k,))
    _checks.check_same_kind("whiten_residual", sqrt_information=sqrt_information, residual=residual)
    return (sqrt_information @ residual[..., None]).squeeze(-1)


def whiten_jacobian(sqrt_information: Tensor, jacobian: Tensor) -> Tensor:
    """Whitened Jacobian block U J, the Jacobian of the whitened residual U r.

    Args:
        sqrt_information: U from :func:`sqrt_information`, shape (..., k, k).
        jacobian: Jacobian blocks ∂r/∂δ, shape (..., k, n). Leading dims broadcast.

    Returns:
        U J, shape broadcast(...) + (k, n).
    """
    _checks.check_tensor("whiten_jacobian", "jacobian", jacobian, min_batch_dims=0)
    if jacobian.dim() < 2:
        raise ValueError(
            f"whiten_jacobian: argument 'jacobian' must have shape (..., k, n), "
            f"got {tuple(jacobian.shape)}"
        )
    k = jacobian.shape[-2]
    _checks.check_tensor("whiten_jacobian", "sqrt_information", sqrt_information, (k, k))
    _checks.check_same_kind("whiten_jacobian", sqrt_information=sqrt_information, jacobian=jacobian)
    return sqrt_information @ jacobian


def weighted_cost(residual: Tensor, information: Tensor) -> Tensor:
    """Weighted squared error ½ rᵀ Ω r of each residual (no robust kernel).

    Args:
        residual: residuals, shape (..., k) (k = 6 in (ω, v) order for SE(3) terms).
        information: information matrices Ω, shape (..., k, k). Leading dims broadcast.

    Returns:
        Costs, shape broadcast(...).
    """
    k = residual.shape[-1] if residual.dim() > 0 else 0
    _checks.check_tensor("weighted_cost", "residual", residual, (k,))
    _checks.check_tensor("weighted_cost", "information", information, (k, k))
    _checks.check_same_kind("weighted_cost", residual=residual, information=information)
    return 0.5 * (residual[..., None, :] @ information @ residual[..., :, None])[..., 0, 0]
