"""SE(3): twists ξ (..., 6) and rigid transforms T (..., 4, 4), batched and exact.

Conventions (kept across torchslam):
- ξ = (ω, v): rotation first, then translation, as in the seed (and GTSAM).
- T = [[R, t], [0, 1]] maps points of its source frame to its target frame: p' = R p + t.
  In the ICP-SLAM problem the pose T_i0 maps world (frame 0) points into frame i.
- exp(ξ) = [[Exp(ω), J_l(ω) v], [0, 1]] (seed eq. L3 with the J of eq. L4.3); log inverts it
  with v = J_l(ω)⁻¹ t (seed eq. L5/L6).
- Right perturbation T·Exp(δ) is torchslam's default; jr is its Jacobian:
  Exp(ξ + d) ≈ Exp(ξ) · Exp(jr(ξ) d), and Exp(ξ + d) ≈ Exp(jl(ξ) d) · Exp(ξ).
- adjoint(T) = [[R, 0], [[t]× R, R]] in (ω, v) order: T Exp(d) T⁻¹ = Exp(adjoint(T) d).

All functions take arbitrary leading batch dims, keep dtype/device, are differentiable and
``torch.func`` (vmap/jacrev) compatible.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchslam import _checks
from torchslam.lie import _series, so3

__all__ = [
    "act",
    "adjoint",
    "compose",
    "exp",
    "from_rotation_translation",
    "hat",
    "identity",
    "inverse",
    "jl",
    "jl_inv",
    "jr",
    "jr_inv",
    "log",
    "vee",
]

_hat = so3._hat


def _assemble(R: Tensor, t: Tensor) -> Tensor:
    """[[R, t], [0, 0, 0, 1]] from R (..., 3, 3) and t (..., 3)."""
    top = torch.cat((R, t[..., None]), dim=-1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom = torch.cat((bottom[..., :3], torch.ones_like(bottom[..., 3:])), dim=-1)
    return torch.cat((top, bottom), dim=-2)


def from_rotation_translation(R: Tensor, t: Tensor) -> Tensor:
    """Build T = [[R, t], [0, 1]] from rotations (..., 3, 3) and translations (..., 3).

    Leading dims broadcast. Returns (..., 4, 4).
    """
    _checks.check_tensor("se3.from_rotation_translation", "R", R, (3, 3))
    _checks.check_tensor("se3.from_rotation_translation", "t", t, (3,))
    _checks.check_same_kind("se3.from_rotation_translation", R=R, t=t)
    batch = torch.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    return _assemble(R.expand(*batch, 3, 3), t.expand(*batch, 3))


def identity(
    *batch_shape: int, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
) -> Tensor:
    """Identity transforms of shape (*batch_shape, 4, 4) (float64 by default)."""
    return torch.eye(4, dtype=dtype, device=device).expand(*batch_shape, 4, 4).clone()


def hat(xi: Tensor) -> Tensor:
    """Twist matrix of ξ = (ω, v): [[ [ω]×, v ], [0, 0]].

    Args:
        xi: twists ξ = (ω, v), rotation first, shape (..., 6).

    Returns:
        se(3) matrices, shape (..., 4, 4).
    """
    _checks.check_tensor("se3.hat", "xi", xi, (6,))
    top = torch.cat((so3._hat(xi[..., :3]), xi[..., 3:, None]), dim=-1)
    return torch.cat((top, torch.zeros_like(top[..., :1, :])), dim=-2)


def vee(Xi: Tensor) -> Tensor:
    """Inverse of :func:`hat`: ξ = (ω, v), rotation first.

    Args:
        Xi: se(3) matrices, shape (..., 4, 4).

    Returns:
        Twists, shape (..., 6).
    """
    _checks.check_tensor("se3.vee", "Xi", Xi, (4, 4))
    return torch.cat((so3._vee(Xi[..., :3, :3]), Xi[..., :3, 3]), dim=-1)


def _exp(xi: Tensor) -> Tensor:
    omega, v = xi[..., :3], xi[..., 3:]
    theta2 = (omega * omega).sum(-1)
    a, b = _series.sinc_coefficients(theta2)
    c = _series.jacobian_coefficient_c(theta2)
    R = so3._skew_quadratic(omega, theta2, a, b)
    # t = J_l(ω) v = v + b ω × v + c ω × (ω × v), without forming J_l.
    w_x_v = torch.linalg.cross(omega, v, dim=-1)
    t = v + b[..., None] * w_x_v + c[..., None] * torch.linalg.cross(omega, w_x_v, dim=-1)
    return _assemble(R, t)


def exp(xi: Tensor) -> Tensor:
    """Exponential map se(3) → SE(3) (seed eq. L3): [[Exp(ω), J_l(ω) v], [0, 1]].

    Args:
        xi: twists ξ = (ω, v), rotation first, shape (..., 6).

    Returns:
        Rigid transforms, shape (..., 4, 4).
    """
    _checks.check_tensor("se3.exp", "xi", xi, (6,))
    _checks.check_finite("se3.exp", "xi", xi)
    return _exp(xi)


def _log(T: Tensor) -> Tensor:
    omega = so3._log(T[..., :3, :3])
    v = (so3._jl_inv(omega) @ T[..., :3, 3:]).squeeze(-1)
    return torch.cat((omega, v), dim=-1)


def log(T: Tensor) -> Tensor:
    """Logarithm SE(3) → se(3): ω = Log(R) (seed eq. L5), v = J_l(ω)⁻¹ t (seed eq. L6).

    Args:
        T: rigid transforms, shape (..., 4, 4); checked when validation is on.

    Returns:
        Twists ξ = (ω, v), rotation first, shape (..., 6), with |ω| ∈ [0, π].
    """
    _checks.check_tensor("se3.log", "T", T, (4, 4))
    _checks.check_pose_matrix("se3.log", "T", T)
    return _log(T)


def _inverse(T: Tensor) -> Tensor:
    Rt = T[..., :3, :3].transpose(-1, -2)
    return _assemble(Rt, -(Rt @ T[..., :3, 3:]).squeeze(-1))


def inverse(T: Tensor) -> Tensor:
    """Inverse transform [[Rᵀ, −Rᵀ t], [0, 1]].

    Args:
        T: rigid transforms, shape (..., 4, 4).

    Returns:
        T⁻¹, shape (..., 4, 4).
    """
    _checks.check_tensor("se3.inverse", "T", T, (4, 4))
    return _inverse(T)


def compose(T1: Tensor, T2: Tensor) -> Tensor:
    """Composition T1 · T2 (apply T2 first); leading dims broadcast.

    Args:
        T1: rigid transforms, shape (..., 4, 4).
        T2: rigid transforms, shape (..., 4, 4).

    Returns:
        T1 @ T2, shape broadcast(...) + (4, 4).
    """
    _checks.check_tensor("se3.compose", "T1", T1, (4, 4))
    _checks.check_tensor("se3.compose", "T2", T2, (4, 4))
    _checks.check_same_kind("se3.compose", T1=T1, T2=T2)
    return T1 @ T2


def _act(T: Tensor, points: Tensor) -> Tensor:
    return (T[..., :3, :3] @ points[..., None]).squeeze(-1) + T[..., :3, 3]


def act(T: Tensor, points: Tensor) -> Tensor:
    """Transform points: R p + t, broadcasting ``points`` (..., 3) against ``T`` (..., 4, 4).

    For N points per pose, pass ``T[..., None, :, :]`` with points of shape (..., N, 3).

    Args:
        T: rigid transforms, shape (..., 4, 4).
        points: points, shape (..., 3).

    Returns:
        Transformed points, shape broadcast(T.shape[:-2], points.shape[:-1]) + (3,).
    """
    _checks.check_tensor("se3.act", "T", T, (4, 4))
    _checks.check_tensor("se3.act", "points", points, (3,))
    _checks.check_same_kind("se3.act", T=T, points=points)
    return _act(T, points)


def _adjoint(T: Tensor) -> Tensor:
    R, t = T[..., :3, :3], T[..., :3, 3]
    top = torch.cat((R, torch.zeros_like(R)), dim=-1)
    bottom = torch.cat((_hat(t) @ R, R), dim=-1)
    return torch.cat((top, bottom), dim=-2)


def adjoint(T: Tensor) -> Tensor:
    """Adjoint of SE(3) in (ω, v) order: [[R, 0], [[t]× R, R]].

    Satisfies T · Exp(d) · T⁻¹ = Exp(adjoint(T) d).

    Args:
        T: rigid transforms, shape (..., 4, 4).

    Returns:
        Adjoint matrices, shape (..., 6, 6).
    """
    _checks.check_tensor("se3.adjoint", "T", T, (4, 4))
    return _adjoint(T)


def _q_block(omega: Tensor, v: Tensor) -> Tensor:
    """Barfoot's Q(ρ = v, φ = ω): the lower-left block of the SE(3) left Jacobian."""
    theta2 = (omega * omega).sum(-1)
    c = _series.jacobian_coefficient_c(theta2)
    q2, q3 = _series.se3_q_coefficients(theta2)
    W, V = _hat(omega), _hat(v)
    WV, VW = W @ V, V @ W
    WVW = WV @ W
    WWV = W @ WV
    VWW = VW @ W
    return (
        0.5 * V
        + c[..., None, None] * (WV + VW + WVW)
        + q2[..., None, None] * (WWV + VWW - 3.0 * WVW)
        + q3[..., None, None] * (WVW @ W + W @ WVW)
    )


def _jl(xi: Tensor) -> Tensor:
    omega, v = xi[..., :3], xi[..., 3:]
    J = so3._jl(omega)
    Q = _q_block(omega, v)
    top = torch.cat((J, torch.zeros_like(J)), dim=-1)
    return torch.cat((top, torch.cat((Q, J), dim=-1)), dim=-2)


def _jl_inv(xi: Tensor) -> Tensor:
    omega, v = xi[..., :3], xi[..., 3:]
    J_inv = so3._jl_inv(omega)
    Q = _q_block(omega, v)
    top = torch.cat((J_inv, torch.zeros_like(J_inv)), dim=-1)
    return torch.cat((top, torch.cat((-J_inv @ Q @ J_inv, J_inv), dim=-1)), dim=-2)


def jl(xi: Tensor) -> Tensor:
    """Left Jacobian of SE(3) in (ω, v) order: [[J_l(ω), 0], [Q(v, ω), J_l(ω)]].

    Exp(ξ + d) ≈ Exp(jl(ξ) d) · Exp(ξ) for small d.

    Args:
        xi: twists ξ = (ω, v), rotation first, shape (..., 6).

    Returns:
        Jacobians, shape (..., 6, 6).
    """
    _checks.check_tensor("se3.jl", "xi", xi, (6,))
    return _jl(xi)


def jr(xi: Tensor) -> Tensor:
    """Right Jacobian of SE(3): jr(ξ) = jl(−ξ); Exp(ξ + d) ≈ Exp(ξ) · Exp(jr(ξ) d).

    Args:
        xi: twists ξ = (ω, v), rotation first, shape (..., 6).

    Returns:
        Jacobians, shape (..., 6, 6).
    """
    _checks.check_tensor("se3.jr", "xi", xi, (6,))
    return _jl(-xi)


def jl_inv(xi: Tensor) -> Tensor:
    """Inverse of :func:`jl`: [[J_l⁻¹, 0], [−J_l⁻¹ Q J_l⁻¹, J_l⁻¹]] (finite for |ω| < 2π).

    Args:
        xi: twists ξ = (ω, v), rotation first, shape (..., 6).

    Returns:
        Jacobians, shape (..., 6, 6).
    """
    _checks.check_tensor("se3.jl_inv", "xi", xi, (6,))
    return _jl_inv(xi)


def jr_inv(xi: Tensor) -> Tensor:
    """Inverse of :func:`jr`: jr_inv(ξ) = jl_inv(−ξ).

    Args:
        xi: twists ξ = (ω, v), rotation first, shape (..., 6).

    Returns:
        Jacobians, shape (..., 6, 6).
    """
    _checks.check_tensor("se3.jr_inv", "xi", xi, (6,))
    return _jl_inv(-xi)
