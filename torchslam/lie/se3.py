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

Bad input is rejected at the boundary: shapes, dtypes and broadcasting always (TypeError /
ValueError naming the function and the argument); NaN/Inf, non-rigid transforms and results
that overflow although the input is finite when value checks are active (see
:func:`torchslam.validation`). Finite input never gives NaN: huge rotation vectors use the
unit-axis form of ``so3`` and huge translations are scaled by an exact power of two inside the
formulas (:func:`_scale_down`).

``form="fast"`` (``exp``, ``jl``, ``jr``, ``jl_inv``, ``jr_inv``) skips both guards: the
θ-power formulas only, bitwise equal to the default ``form="robust"`` for |ω| ≤ 2²⁰ and
translation entries ≤ 2⁵¹² (float32: 2¹⁰, 2⁶⁴), for hot paths whose input is bounded (the
solver's iterates and steps); beyond, it may lose accuracy or overflow (see ``so3``).
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchslam import _checks
from torchslam._batched import matmul
from torchslam.lie import _series, so3
from torchslam.lie.so3 import Form, _check_form

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
    bottom = _series.constant("se3 bottom row", ((0.0, 0.0, 0.0, 1.0),), R.dtype, R.device)
    return torch.cat((top, bottom.expand(*top.shape[:-2], 1, 4)), dim=-2)


# Translations with an entry beyond the first bound are scaled by the second (an exact power of
# two) inside exp and the Jacobians, and the result scaled back, so that products like
# ω × (ω × v) and the Q block cannot overflow; other translations are multiplied by exactly 1.
_TRANSLATION_SCALE = {torch.float32: (2.0**64, 2.0**-64), torch.float64: (2.0**512, 2.0**-512)}
# Large-angle Q-block coefficients use min(θ, cap): they differ from their limit by O(1/θ),
# far below round-off at the cap, and cap·|v| stays representable after _scale_down.
_ANGLE_CAP = {torch.float32: 2.0**40, torch.float64: 2.0**300}


def _scale_down(v: Tensor) -> tuple[Tensor, Tensor]:
    """(v·s, 1/s) with s = 1, or an exact power of two for translations with huge entries."""
    bound, factor = _TRANSLATION_SCALE[v.dtype]
    largest = v.abs().amax(dim=-1)
    big = largest > bound
    scale = torch.where(big, torch.full_like(largest, factor), 1.0)
    return v * scale[..., None], torch.where(big, torch.full_like(largest, 1.0 / factor), 1.0)


def from_rotation_translation(R: Tensor, t: Tensor) -> Tensor:
    """Build T = [[R, t], [0, 1]] from rotations (..., 3, 3) and translations (..., 3).

    Leading dims broadcast. Returns (..., 4, 4). ``R`` is checked (orthonormal, det +1) and
    both are checked finite when validation is on.
    """
    fn = "se3.from_rotation_translation"
    _checks.check_tensor(fn, "R", R, (3, 3))
    _checks.check_tensor(fn, "t", t, (3,))
    _checks.check_same_kind(fn, R=R, t=t)
    batch = _checks.check_broadcast(fn, R=R.shape[:-2], t=t.shape[:-1])
    _checks.check_rotation(fn, "R", R)
    _checks.check_finite(fn, "t", t)
    return _assemble(R.expand(*batch, 3, 3), t.expand(*batch, 3))


def identity(
    *batch_shape: int, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
) -> Tensor:
    """Identity transforms of shape (*batch_shape, 4, 4) (float64 by default).

    Args:
        batch_shape: non-negative ints (none for a single (4, 4) transform).
        dtype: torch.float32 or torch.float64.
        device: where to create the transforms.
    """
    sizes = _checks.check_sizes("se3.identity", "batch_shape", batch_shape)
    _checks.check_dtype_device("se3.identity", dtype, device)
    return torch.eye(4, dtype=dtype, device=device).expand(*sizes, 4, 4).clone()


def hat(xi: Tensor) -> Tensor:
    """Twist matrix of ξ = (ω, v): [[ [ω]×, v ], [0, 0]].

    Args:
        xi: twists ξ = (ω, v), rotation first, shape (..., 6).

    Returns:
        se(3) matrices, shape (..., 4, 4).
    """
    _checks.check_tensor("se3.hat", "xi", xi, (6,))
    _checks.check_finite("se3.hat", "xi", xi)
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
    _checks.check_finite("se3.vee", "Xi", Xi)
    return torch.cat((so3._vee(Xi[..., :3, :3]), Xi[..., :3, 3]), dim=-1)


def _exp(xi: Tensor) -> Tensor:
    # The θ-power form: exp(xi, form="fast").
    omega, v = xi[..., :3], xi[..., 3:]
    theta2 = (omega * omega).sum(-1)
    a, b, c = _series.exp_coefficients(theta2)
    R = so3._skew_quadratic(omega, theta2, a, b)
    # t = J_l(ω) v = v + b ω × v + c ω × (ω × v), without forming J_l.
    w_x_v = torch.linalg.cross(omega, v, dim=-1)
    t = v + b[..., None] * w_x_v + c[..., None] * torch.linalg.cross(omega, w_x_v, dim=-1)
    return _assemble(R, t)


def _exp_robust(xi: Tensor) -> Tensor:
    # Bitwise equal to _exp for |ω| ≤ 2²⁰ and |v| ≤ 2⁵¹² (float32: 2¹⁰, 2⁶⁴); finite beyond.
    omega, v = xi[..., :3], xi[..., 3:]
    p = so3._polar(omega)
    a, b = _series.sinc_coefficients(p.theta2)
    a, b_R = so3._rodrigues_coefficients(p, a, b)
    R = so3._skew_quadratic(p.w, p.theta2, a, b_R)
    # t = J_l(ω) v = v + b ω × v + c ω × (ω × v), without forming J_l (w = ω, or the unit
    # axis with the matching coefficients for huge angles; v scaled when huge).
    b, c = so3._jl_coefficients(p, b)
    v, unscale = _scale_down(v)
    w_x_v = torch.linalg.cross(p.w, v, dim=-1)
    t = v + b[..., None] * w_x_v + c[..., None] * torch.linalg.cross(p.w, w_x_v, dim=-1)
    return _assemble(R, t * unscale[..., None])


def exp(xi: Tensor, *, form: Form = "robust") -> Tensor:
    """Exponential map se(3) → SE(3) (seed eq. L3): [[Exp(ω), J_l(ω) v], [0, 1]].

    Args:
        xi: twists ξ = (ω, v), rotation first, shape (..., 6).
        form: "robust" (finite for every finite ξ) or "fast" (the θ-power form only: the same
            bits for |ω| ≤ 2²⁰ and |v| ≤ 2⁵¹², cheaper; see the module docstring).

    Returns:
        Rigid transforms, shape (..., 4, 4).
    """
    _checks.check_tensor("se3.exp", "xi", xi, (6,))
    _check_form("se3.exp", form)
    _checks.check_finite("se3.exp", "xi", xi)
    result = _exp_robust(xi) if form == "robust" else _exp(xi)
    _checks.check_result_finite("se3.exp", result, xi=xi)
    return result


def _log(T: Tensor) -> Tensor:
    omega = so3._log(T[..., :3, :3])
    t = T[..., :3, 3]
    # v = J_l(ω)⁻¹ t = t − ½ ω × t + d ω × (ω × t), d the [ω]×² coefficient of J_l⁻¹.
    d = _series.inverse_jacobian_coefficient_d((omega * omega).sum(-1))
    wt = torch.linalg.cross(omega, t, dim=-1)
    v = t - 0.5 * wt + d[..., None] * torch.linalg.cross(omega, wt, dim=-1)
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
    result = _log(T)
    _checks.check_result_finite("se3.log", result, T=T)
    return result


def _inverse(T: Tensor) -> Tensor:
    Rt = T[..., :3, :3].transpose(-1, -2)
    return _assemble(Rt, -matmul(Rt, T[..., :3, 3:]).squeeze(-1))


def inverse(T: Tensor) -> Tensor:
    """Inverse transform [[Rᵀ, −Rᵀ t], [0, 1]].

    Args:
        T: rigid transforms, shape (..., 4, 4); checked (rigid, bottom row [0, 0, 0, 1]) when
            validation is on, since the formula inverts rigid transforms only.

    Returns:
        T⁻¹, shape (..., 4, 4).
    """
    _checks.check_tensor("se3.inverse", "T", T, (4, 4))
    _checks.check_pose_matrix("se3.inverse", "T", T)
    result = _inverse(T)
    _checks.check_result_finite("se3.inverse", result, T=T)
    return result


def compose(T1: Tensor, T2: Tensor) -> Tensor:
    """Composition T1 · T2 (apply T2 first); leading dims broadcast.

    Args:
        T1: rigid transforms, shape (..., 4, 4); checked when validation is on.
        T2: rigid transforms, shape (..., 4, 4); checked when validation is on.

    Returns:
        T1 @ T2, shape broadcast(...) + (4, 4).
    """
    fn = "se3.compose"
    _checks.check_tensor(fn, "T1", T1, (4, 4))
    _checks.check_tensor(fn, "T2", T2, (4, 4))
    _checks.check_same_kind(fn, T1=T1, T2=T2)
    _checks.check_broadcast(fn, T1=T1.shape[:-2], T2=T2.shape[:-2])
    _checks.check_pose_matrix(fn, "T1", T1)
    _checks.check_pose_matrix(fn, "T2", T2)
    result = T1 @ T2
    _checks.check_result_finite(fn, result, T1=T1, T2=T2)
    return result


def _act(T: Tensor, points: Tensor) -> Tensor:
    return (T[..., :3, :3] @ points[..., None]).squeeze(-1) + T[..., :3, 3]


def act(T: Tensor, points: Tensor) -> Tensor:
    """Transform points: R p + t, broadcasting ``points`` (..., 3) against ``T`` (..., 4, 4).

    For N points per pose, pass ``T[..., None, :, :]`` with points of shape (..., N, 3).

    Args:
        T: rigid transforms, shape (..., 4, 4); checked when validation is on.
        points: points, shape (..., 3).

    Returns:
        Transformed points, shape broadcast(T.shape[:-2], points.shape[:-1]) + (3,).
    """
    fn = "se3.act"
    _checks.check_tensor(fn, "T", T, (4, 4))
    _checks.check_tensor(fn, "points", points, (3,))
    _checks.check_same_kind(fn, T=T, points=points)
    _checks.check_broadcast(fn, T=T.shape[:-2], points=points.shape[:-1])
    _checks.check_pose_matrix(fn, "T", T)
    _checks.check_finite(fn, "points", points)
    result = _act(T, points)
    _checks.check_result_finite(fn, result, T=T, points=points)
    return result


def _adjoint(T: Tensor) -> Tensor:
    R, t = T[..., :3, :3], T[..., :3, 3]
    top = torch.cat((R, torch.zeros_like(R)), dim=-1)
    bottom = torch.cat((matmul(_hat(t), R), R), dim=-1)
    return torch.cat((top, bottom), dim=-2)


def adjoint(T: Tensor) -> Tensor:
    """Adjoint of SE(3) in (ω, v) order: [[R, 0], [[t]× R, R]].

    Satisfies T · Exp(d) · T⁻¹ = Exp(adjoint(T) d).

    Args:
        T: rigid transforms, shape (..., 4, 4); checked when validation is on.

    Returns:
        Adjoint matrices, shape (..., 6, 6).
    """
    _checks.check_tensor("se3.adjoint", "T", T, (4, 4))
    _checks.check_pose_matrix("se3.adjoint", "T", T)
    result = _adjoint(T)
    _checks.check_result_finite("se3.adjoint", result, T=T)
    return result


def _q_combination(
    W: Tensor, V: Tensor, c: Tensor, q2: Tensor, q3: Tensor, kappa: Tensor | None = None
) -> Tensor:
    """½V + c (WV + VW + κ·WVW) + q2 (WWV + VWW − 3WVW) + q3 (WVWW + WWVW); κ = 1 if None."""
    WV, VW = matmul(W, V), matmul(V, W)
    WVW = matmul(WV, W)
    WWV = matmul(W, WV)
    VWW = matmul(VW, W)
    kWVW = WVW if kappa is None else kappa[..., None, None] * WVW
    return (
        0.5 * V
        + c[..., None, None] * (WV + VW + kWVW)
        + q2[..., None, None] * (WWV + VWW - 3.0 * WVW)
        + q3[..., None, None] * (matmul(WVW, W) + matmul(W, WVW))
    )


def _q_block(omega: Tensor, v: Tensor) -> Tensor:
    """Barfoot's Q(ρ = v, φ = ω): the lower-left block of the SE(3) left Jacobian."""
    theta2 = (omega * omega).sum(-1)
    c = _series.jacobian_coefficient_c(theta2)
    q2, q3 = _series.se3_q_coefficients(theta2)
    return _q_combination(_hat(omega), _hat(v), c, q2, q3)


def _q_block_robust(p: so3._Polar, v: Tensor) -> tuple[Tensor, Tensor]:
    """Barfoot's Q(ρ = v, φ = ω), the lower-left block of the SE(3) left Jacobian, as (Q·s, 1/s).

    Q = ½V + c (WV + VW + WVW) + q2 (WWV + VWW − 3WVW) + q3 (WVWW + WWVW) with W = [ω]×,
    V = [v]×. For huge angles W = θ[u]× and the θ powers move into the coefficients:
    (c, κ, q2, q3) → (cθ, θ, q2θ², q3θ³) with κ the factor of WVW inside the c term (1 for
    ordinary angles). s is the exact power of two of :func:`_scale_down` (1 for ordinary v).
    """
    c = _series.jacobian_coefficient_c(p.theta2)
    q2, q3 = _series.se3_q_coefficients(p.theta2)
    theta = p.theta.clamp_max(_ANGLE_CAP[p.theta.dtype])
    r = 1.0 / theta
    sin_theta, one_minus_cos = p.sin_theta, p.one_minus_cos
    c = torch.where(p.large, r - sin_theta * r * r, c)
    kappa = torch.where(p.large, theta, 1.0)
    q2 = torch.where(p.large, 0.5 - one_minus_cos * r * r, q2)
    q3 = torch.where(p.large, (0.5 * (3.0 - one_minus_cos) - 1.5 * sin_theta * r) * r, q3)
    v, unscale = _scale_down(v)
    return _q_combination(_hat(p.w), _hat(v), c, q2, q3, kappa), unscale[..., None, None]


# The θ-power forms _jl and _jl_inv are form="fast" of the public functions (hot paths); the
# default form="robust" uses the _robust forms (bitwise equal for ordinary input).


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
    return torch.cat((top, torch.cat((matmul(matmul(-J_inv, Q), J_inv), J_inv), dim=-1)), dim=-2)


def _jl_robust(xi: Tensor) -> Tensor:
    omega, v = xi[..., :3], xi[..., 3:]
    p = so3._polar(omega)
    J = so3._jl_from_polar(p)
    Q, unscale = _q_block_robust(p, v)
    top = torch.cat((J, torch.zeros_like(J)), dim=-1)
    return torch.cat((top, torch.cat((Q * unscale, J), dim=-1)), dim=-2)


def _jl_inv_robust(xi: Tensor) -> Tensor:
    omega, v = xi[..., :3], xi[..., 3:]
    p = so3._polar(omega)
    J_inv = so3._jl_inv_from_polar(p)
    Q, unscale = _q_block_robust(p, v)
    top = torch.cat((J_inv, torch.zeros_like(J_inv)), dim=-1)
    return torch.cat(
        (top, torch.cat((matmul(matmul(-J_inv, Q), J_inv) * unscale, J_inv), dim=-1)), dim=-2
    )


_JL_INV_REASON = (
    "J_l is singular at |ω| = 2πk (k ≥ 1) and its inverse grows like |ω|²·|v|, so the inverse "
    "is not representable here"
)


def jl(xi: Tensor, *, form: Form = "robust") -> Tensor:
    """Left Jacobian of SE(3) in (ω, v) order: [[J_l(ω), 0], [Q(v, ω), J_l(ω)]].

    Exp(ξ + d) ≈ Exp(jl(ξ) d) · Exp(ξ) for small d.

    Args:
        xi: twists ξ = (ω, v), rotation first, shape (..., 6).
        form: "robust" (default) or "fast" (θ-power form only; see the module docstring).

    Returns:
        Jacobians, shape (..., 6, 6).
    """
    _checks.check_tensor("se3.jl", "xi", xi, (6,))
    _check_form("se3.jl", form)
    _checks.check_finite("se3.jl", "xi", xi)
    result = _jl_robust(xi) if form == "robust" else _jl(xi)
    _checks.check_result_finite("se3.jl", result, xi=xi)
    return result


def jr(xi: Tensor, *, form: Form = "robust") -> Tensor:
    """Right Jacobian of SE(3): jr(ξ) = jl(−ξ); Exp(ξ + d) ≈ Exp(ξ) · Exp(jr(ξ) d).

    Args:
        xi: twists ξ = (ω, v), rotation first, shape (..., 6).
        form: "robust" (default) or "fast" (θ-power form only; see the module docstring).

    Returns:
        Jacobians, shape (..., 6, 6).
    """
    _checks.check_tensor("se3.jr", "xi", xi, (6,))
    _check_form("se3.jr", form)
    _checks.check_finite("se3.jr", "xi", xi)
    result = _jl_robust(-xi) if form == "robust" else _jl(-xi)
    _checks.check_result_finite("se3.jr", result, xi=xi)
    return result


def jl_inv(xi: Tensor, *, form: Form = "robust") -> Tensor:
    """Inverse of :func:`jl`: [[J_l⁻¹, 0], [−J_l⁻¹ Q J_l⁻¹, J_l⁻¹]] (finite for |ω| < 2π).

    Args:
        xi: twists ξ = (ω, v), rotation first, shape (..., 6).
        form: "robust" (default) or "fast" (θ-power form only; see the module docstring).

    Returns:
        Jacobians, shape (..., 6, 6).
    """
    _checks.check_tensor("se3.jl_inv", "xi", xi, (6,))
    _check_form("se3.jl_inv", form)
    _checks.check_finite("se3.jl_inv", "xi", xi)
    result = _jl_inv_robust(xi) if form == "robust" else _jl_inv(xi)
    _checks.check_result_finite("se3.jl_inv", result, reason=_JL_INV_REASON, xi=xi)
    return result


def jr_inv(xi: Tensor, *, form: Form = "robust") -> Tensor:
    """Inverse of :func:`jr`: jr_inv(ξ) = jl_inv(−ξ).

    Args:
        xi: twists ξ = (ω, v), rotation first, shape (..., 6).
        form: "robust" (default) or "fast" (θ-power form only; see the module docstring).

    Returns:
        Jacobians, shape (..., 6, 6).
    """
    _checks.check_tensor("se3.jr_inv", "xi", xi, (6,))
    _check_form("se3.jr_inv", form)
    _checks.check_finite("se3.jr_inv", "xi", xi)
    result = _jl_inv_robust(-xi) if form == "robust" else _jl_inv(-xi)
    _checks.check_result_finite("se3.jr_inv", result, reason=_JL_INV_REASON, xi=xi)
    return result
