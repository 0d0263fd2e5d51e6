"""SO(3): rotation vectors ω (..., 3) and rotation matrices R (..., 3, 3), batched and exact.

Conventions (kept across torchslam):
- ``hat(ω)`` is the skew matrix [ω]× of the seed, so ``hat(a) @ b = a × b``.
- ``exp`` is Rodrigues' formula (seed eq. L4.1/L4.2); ``log`` is its inverse with θ ∈ [0, π].
- Right Jacobian: Exp(ω + d) ≈ Exp(ω) · Exp(jr(ω) d); left: Exp(ω + d) ≈ Exp(jl(ω) d) · Exp(ω).
  ``jl`` is the J of seed eq. L4.3 and jr(ω) = jl(−ω) = jl(ω)ᵀ.

All functions take arbitrary leading batch dims, keep dtype/device, are differentiable
(finite gradients at θ = 0 and near π) and are ``torch.func`` (vmap/jacrev) compatible.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchslam import _checks
from torchslam.lie import _series

__all__ = [
    "act",
    "adjoint",
    "exp",
    "hat",
    "inverse",
    "jl",
    "jl_inv",
    "jr",
    "jr_inv",
    "log",
    "project",
    "vee",
]


def _hat(omega: Tensor) -> Tensor:
    x, y, z = omega.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack(
        (
            torch.stack((zero, -z, y), dim=-1),
            torch.stack((z, zero, -x), dim=-1),
            torch.stack((-y, x, zero), dim=-1),
        ),
        dim=-2,
    )


def hat(omega: Tensor) -> Tensor:
    """Skew-symmetric matrix [ω]× with ``hat(a) @ b = a × b`` (seed: [P]×).

    Args:
        omega: vectors, shape (..., 3).

    Returns:
        Skew matrices, shape (..., 3, 3).
    """
    _checks.check_tensor("so3.hat", "omega", omega, (3,))
    return _hat(omega)


def vee(Omega: Tensor) -> Tensor:
    """Inverse of :func:`hat`: the vector of a skew matrix (its antisymmetric part is used).

    Args:
        Omega: matrices, shape (..., 3, 3).

    Returns:
        Vectors, shape (..., 3).
    """
    _checks.check_tensor("so3.vee", "Omega", Omega, (3, 3))
    return _vee(Omega)


def _vee(Omega: Tensor) -> Tensor:
    return 0.5 * torch.stack(
        (
            Omega[..., 2, 1] - Omega[..., 1, 2],
            Omega[..., 0, 2] - Omega[..., 2, 0],
            Omega[..., 1, 0] - Omega[..., 0, 1],
        ),
        dim=-1,
    )


def _skew_quadratic(omega: Tensor, theta2: Tensor, first: Tensor, second: Tensor) -> Tensor:
    """I + first·[ω]× + second·[ω]×², built entrywise from [ω]×² = ωωᵀ − θ² I.

    Rodrigues' R (first = sin θ/θ, second = (1 − cos θ)/θ²) and the left Jacobian
    (first = (1 − cos θ)/θ², second = (θ − sin θ)/θ³) both have this form; building the nine
    entries directly avoids two batched 3×3 matmuls.
    """
    x, y, z = omega.unbind(-1)
    diagonal = 1.0 - second * theta2
    fx, fy, fz = first * x, first * y, first * z
    sxy, sxz, syz = second * x * y, second * x * z, second * y * z
    return torch.stack(
        (
            diagonal + second * x * x,
            sxy - fz,
            sxz + fy,
            sxy + fz,
            diagonal + second * y * y,
            syz - fx,
            sxz - fy,
            syz + fx,
            diagonal + second * z * z,
        ),
        dim=-1,
    ).unflatten(-1, (3, 3))


def _exp(omega: Tensor) -> Tensor:
    theta2 = (omega * omega).sum(-1)
    a, b = _series.sinc_coefficients(theta2)
    return _skew_quadratic(omega, theta2, a, b)


def exp(omega: Tensor) -> Tensor:
    """Exponential map so(3) → SO(3), Rodrigues' formula (seed eq. L4.1).

    R = I + (sin θ / θ) [ω]× + ((1 − cos θ) / θ²) [ω]×², θ = |ω|, with series branches near 0.

    Args:
        omega: rotation vectors (axis · angle, radians), shape (..., 3).

    Returns:
        Rotation matrices, shape (..., 3, 3).
    """
    _checks.check_tensor("so3.exp", "omega", omega, (3,))
    _checks.check_finite("so3.exp", "omega", omega)
    return _exp(omega)


def _matrix_to_quaternion(R: Tensor) -> Tensor:
    """Shepperd's method, (w, x, y, z), w ≥ 0; vmap-safe and gradient-safe.

    All four candidates are computed; the one built from the largest of
    (1 + tr, 1 + 2R00 − tr, …) is selected. That value is ≥ 1 for a rotation, so clamping
    the square root's argument at 0.25 changes only the discarded candidates (and keeps
    their gradients finite).
    """
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    diag = torch.stack(
        (
            1.0 + m00 + m11 + m22,
            1.0 + m00 - m11 - m22,
            1.0 - m00 + m11 - m22,
            1.0 - m00 - m11 + m22,
        ),
        dim=-1,
    )
    root = torch.sqrt(diag.clamp_min(0.25))  # = 2·|component| for the selected candidate
    r0, r1, r2, r3 = root.unbind(-1)
    candidates = torch.stack(
        (
            torch.stack((r0 * r0, m21 - m12, m02 - m20, m10 - m01), dim=-1) / (2.0 * r0[..., None]),
            torch.stack((m21 - m12, r1 * r1, m01 + m10, m02 + m20), dim=-1) / (2.0 * r1[..., None]),
            torch.stack((m02 - m20, m01 + m10, r2 * r2, m12 + m21), dim=-1) / (2.0 * r2[..., None]),
            torch.stack((m10 - m01, m02 + m20, m12 + m21, r3 * r3), dim=-1) / (2.0 * r3[..., None]),
        ),
        dim=-2,
    )
    best = diag.argmax(dim=-1)
    q = torch.gather(candidates, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    return torch.where(q[..., :1] < 0, -q, q)


def _log(R: Tensor) -> Tensor:
    q = _matrix_to_quaternion(R)
    w, v = q[..., 0], q[..., 1:]
    # ω = θ v / |v| with θ = 2 atan2(|v|, w); the ratio is exact at |v| = 0. It is read off
    # |v|², never |v| (whose derivative is 0/0 at v = 0), so that second derivatives (a
    # double backward, e.g. a Hessian-vector product through the solver) are finite at R = I.
    return (2.0 * _series.atan_ratio_squared((v * v).sum(-1), w))[..., None] * v


def log(R: Tensor) -> Tensor:
    """Logarithm SO(3) → so(3) (seed eq. L5), the rotation vector with angle θ ∈ [0, π].

    Computed through the unit quaternion (w, v) of R, θ = 2·atan2(|v|, w): accurate to
    round-off for every angle, including θ → 0 and θ → π (where trace-based formulas lose
    half the digits). At exactly θ = π both ±ω are valid; either may be returned.

    Args:
        R: rotation matrices, shape (..., 3, 3). Checked (orthonormal, det +1) when
            validation is on; use :func:`project` first for approximately orthonormal input.

    Returns:
        Rotation vectors, shape (..., 3).
    """
    _checks.check_tensor("so3.log", "R", R, (3, 3))
    _checks.check_rotation("so3.log", "R", R)
    return _log(R)


def _jl(omega: Tensor) -> Tensor:
    theta2 = (omega * omega).sum(-1)
    _, b = _series.sinc_coefficients(theta2)
    c = _series.jacobian_coefficient_c(theta2)
    return _skew_quadratic(omega, theta2, b, c)


def _jl_inv(omega: Tensor) -> Tensor:
    theta2 = (omega * omega).sum(-1)
    d = _series.inverse_jacobian_coefficient_d(theta2)
    W = _hat(omega)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device)
    return eye - 0.5 * W + d[..., None, None] * (W @ W)


def jl(omega: Tensor) -> Tensor:
    """Left Jacobian of SO(3), the J of seed eq. L4.3.

    J_l(ω) = I + ((1 − cos θ)/θ²) [ω]× + ((θ − sin θ)/θ³) [ω]×², and
    Exp(ω + d) ≈ Exp(J_l(ω) d) · Exp(ω) for small d.

    Args:
        omega: rotation vectors, shape (..., 3).

    Returns:
        Jacobians, shape (..., 3, 3).
    """
    _checks.check_tensor("so3.jl", "omega", omega, (3,))
    return _jl(omega)


def jr(omega: Tensor) -> Tensor:
    """Right Jacobian of SO(3): jr(ω) = jl(−ω); Exp(ω + d) ≈ Exp(ω) · Exp(jr(ω) d).

    Args:
        omega: rotation vectors, shape (..., 3).

    Returns:
        Jacobians, shape (..., 3, 3).
    """
    _checks.check_tensor("so3.jr", "omega", omega, (3,))
    return _jl(-omega)


def jl_inv(omega: Tensor) -> Tensor:
    """Inverse of :func:`jl`: I − ½[ω]× + ((1 − (θ/2)cot(θ/2))/θ²) [ω]×².

    Finite for θ < 2π (in particular at θ = π).

    Args:
        omega: rotation vectors, shape (..., 3).

    Returns:
        Jacobians, shape (..., 3, 3).
    """
    _checks.check_tensor("so3.jl_inv", "omega", omega, (3,))
    return _jl_inv(omega)


def jr_inv(omega: Tensor) -> Tensor:
    """Inverse of :func:`jr`: jr_inv(ω) = jl_inv(−ω).

    Args:
        omega: rotation vectors, shape (..., 3).

    Returns:
        Jacobians, shape (..., 3, 3).
    """
    _checks.check_tensor("so3.jr_inv", "omega", omega, (3,))
    return _jl_inv(-omega)


def inverse(R: Tensor) -> Tensor:
    """Inverse rotation Rᵀ.

    Args:
        R: rotation matrices, shape (..., 3, 3).

    Returns:
        Rᵀ, shape (..., 3, 3).
    """
    _checks.check_tensor("so3.inverse", "R", R, (3, 3))
    return R.transpose(-1, -2)


def act(R: Tensor, points: Tensor) -> Tensor:
    """Rotate points: R p, broadcasting ``points`` (..., 3) against ``R`` (..., 3, 3).

    Args:
        R: rotation matrices, shape (..., 3, 3).
        points: points, shape (..., 3); leading dims broadcast with those of ``R``.

    Returns:
        Rotated points, shape broadcast(R.shape[:-2], points.shape[:-1]) + (3,).
    """
    _checks.check_tensor("so3.act", "R", R, (3, 3))
    _checks.check_tensor("so3.act", "points", points, (3,))
    _checks.check_same_kind("so3.act", R=R, points=points)
    return (R @ points[..., None]).squeeze(-1)


def adjoint(R: Tensor) -> Tensor:
    """Adjoint of SO(3): Ad_R = R, so that R Exp(d) Rᵀ = Exp(R d).

    Args:
        R: rotation matrices, shape (..., 3, 3).

    Returns:
        Adjoint matrices, shape (..., 3, 3) (a copy of ``R``).
    """
    _checks.check_tensor("so3.adjoint", "R", R, (3, 3))
    return R.clone()


def project(M: Tensor) -> Tensor:
    """Nearest rotation matrix (Frobenius norm) to ``M``, via SVD with a det +1 fix.

    Use it to clean up matrices that are rotations up to round-off or noise before
    :func:`log`; torchslam never projects silently.

    Args:
        M: matrices, shape (..., 3, 3).

    Returns:
        Rotation matrices, shape (..., 3, 3).
    """
    _checks.check_tensor("so3.project", "M", M, (3, 3))
    _checks.check_finite("so3.project", "M", M)
    U, _, Vh = torch.linalg.svd(M)
    det = torch.linalg.det(U @ Vh)
    fix = torch.ones(*M.shape[:-2], 3, dtype=M.dtype, device=M.device)
    fix = torch.cat((fix[..., :2], det[..., None].sign()), dim=-1)
    return (U * fix[..., None, :]) @ Vh
