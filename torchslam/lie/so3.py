"""SO(3): rotation vectors ω (..., 3) and rotation matrices R (..., 3, 3), batched and exact.

Conventions (kept across torchslam):
- ``hat(ω)`` is the skew matrix [ω]× of the seed, so ``hat(a) @ b = a × b``.
- ``exp`` is Rodrigues' formula (seed eq. L4.1/L4.2); ``log`` is its inverse with θ ∈ [0, π].
- Right Jacobian: Exp(ω + d) ≈ Exp(ω) · Exp(jr(ω) d); left: Exp(ω + d) ≈ Exp(jl(ω) d) · Exp(ω).
  ``jl`` is the J of seed eq. L4.3 and jr(ω) = jl(−ω) = jl(ω)ᵀ.

All functions take arbitrary leading batch dims, keep dtype/device, are differentiable
(finite gradients at θ = 0 and near π) and are ``torch.func`` (vmap/jacrev) compatible.

Bad input is rejected at the boundary: shapes, dtypes and broadcasting always (TypeError /
ValueError naming the function and the argument); NaN/Inf, non-rotations and results that
overflow although the input is finite when value checks are active (see
:func:`torchslam.validation`). Finite input never gives NaN: for |ω| beyond 2²⁰ (float64) /
2¹⁰ (float32) the formulas switch to a unit-axis form that cannot overflow (see
:class:`_Polar`), with the angle reduced modulo 2π (exact up to the input's resolution).

``form="fast"`` (``exp``, ``jl``, ``jr``, ``jl_inv``, ``jr_inv``) skips that switch: the
θ-power formulas only, bitwise equal to the default ``form="robust"`` for |ω| ≤ 2²⁰ (float64;
2¹⁰ in float32) and cheaper (fewer kernels), for hot paths whose input is bounded (the solver's
iterates and steps); beyond the switch it may lose accuracy, and it overflows for |ω| ≳ 1e154.
"""

from __future__ import annotations

import functools
import math
from typing import Literal

import torch
from torch import Tensor

from torchslam import _checks
from torchslam._batched import matmul
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

Form = Literal["robust", "fast"]


def _check_form(fn: str, form: object) -> None:
    if form != "robust" and form != "fast":
        raise ValueError(f"{fn}: argument 'form' must be 'robust' or 'fast', got {form!r}")


def _hat(omega: Tensor) -> Tensor:
    x, y, z = omega.unbind(-1)
    zero = torch.zeros_like(x)
    rows = torch.stack((zero, -z, y, z, zero, -x, -y, x, zero), dim=-1)
    return rows.reshape(*omega.shape[:-1], 3, 3)


def hat(omega: Tensor) -> Tensor:
    """Skew-symmetric matrix [ω]× with ``hat(a) @ b = a × b`` (seed: [P]×).

    Args:
        omega: vectors, shape (..., 3).

    Returns:
        Skew matrices, shape (..., 3, 3).
    """
    _checks.check_tensor("so3.hat", "omega", omega, (3,))
    _checks.check_finite("so3.hat", "omega", omega)
    return _hat(omega)


def vee(Omega: Tensor) -> Tensor:
    """Inverse of :func:`hat`: the vector of a skew matrix (its antisymmetric part is used).

    Args:
        Omega: matrices, shape (..., 3, 3).

    Returns:
        Vectors, shape (..., 3).
    """
    _checks.check_tensor("so3.vee", "Omega", Omega, (3, 3))
    _checks.check_finite("so3.vee", "Omega", Omega)
    return _vee(Omega)


def _vee(Omega: Tensor) -> Tensor:
    # ½a − ½b equals ½(a − b) exactly (halving is exact) but cannot overflow for finite input.
    half = 0.5 * Omega
    return torch.stack(
        (
            half[..., 2, 1] - half[..., 1, 2],
            half[..., 0, 2] - half[..., 2, 0],
            half[..., 1, 0] - half[..., 0, 1],
        ),
        dim=-1,
    )


# Rotation vectors with θ² above this use the unit-axis form of the formulas (see _polar). The
# bounds keep the θ-power forms (θ⁵ in the SE(3) Q block, θ⁴·|v|) far from overflow; the
# θ-power forms stay in use below them so that ordinary input gets exactly the same values.
_LARGE_ANGLE_SQUARED = {torch.float32: 2.0**20, torch.float64: 2.0**40}


class _Polar:
    """A batch of rotation vectors split for formulas that must not overflow; sync-free.

    On ordinary rows (θ² ≤ _LARGE_ANGLE_SQUARED) ``w`` is ω itself and ``theta2`` its θ², so
    the θ-power formulas run exactly as before. On large rows (including θ² = Inf, i.e. θ² of a
    finite ω overflowing) ``w`` is the unit axis u and ``theta2`` is 1 (= |u|²); the formulas
    then take coefficients from the lazily computed ``theta`` (Inf if |ω| overflows the dtype),
    ``sin_half``/``cos_half`` (θ/2 reduced modulo π, exact) and their combinations. On ordinary
    rows those hold harmless values (from ω replaced by ones), so no branch sees 0/0 in the
    forward or the backward pass, and ``torch.where`` picks the right one per row.
    """

    def __init__(self, omega: Tensor) -> None:
        theta2 = (omega * omega).sum(-1)
        # NaN θ² (NaN input, unchecked) stays on the ordinary branch, which returns NaN.
        self.large = theta2 > _LARGE_ANGLE_SQUARED[omega.dtype]
        large = self.large[..., None]
        om = torch.where(large, omega, 1.0)
        # |ω| = m·|ω/m| with m = max|ω_i|: no overflow in the squares (torch's norm does not
        # rescale: vector_norm([1e308] * 3) is Inf).
        self._m = om.abs().amax(dim=-1)
        s = om / self._m[..., None]
        self._n = torch.linalg.vector_norm(s, dim=-1)  # in [1, √3]
        self.w = torch.where(large, s / self._n[..., None], omega)
        self.theta2 = torch.where(self.large, 1.0, theta2)

    @functools.cached_property
    def _quarter(self) -> Tensor:
        return (0.25 * self._m) * self._n  # θ/4, finite for every finite ω

    @functools.cached_property
    def theta(self) -> Tensor:
        return 4.0 * self._quarter  # Inf only when |ω| exceeds the dtype's range

    @functools.cached_property
    def _half(self) -> Tensor:
        # θ/2 mod π = 2·fmod(θ/4, fl(π/2)): fmod is exact, and reducing by fl(2π) instead of 2π
        # moves the angle by less than half an ulp of θ, the input's own resolution.
        return 2.0 * torch.fmod(self._quarter, math.pi / 2)

    @functools.cached_property
    def sin_half(self) -> Tensor:
        return torch.sin(self._half)  # sin(θ/2) up to a common sign with cos_half

    @functools.cached_property
    def cos_half(self) -> Tensor:
        return torch.cos(self._half)

    @functools.cached_property
    def sin_theta(self) -> Tensor:
        return 2.0 * self.sin_half * self.cos_half

    @functools.cached_property
    def one_minus_cos(self) -> Tensor:
        return 2.0 * self.sin_half * self.sin_half  # 1 − cos θ without cancellation


def _polar(omega: Tensor) -> _Polar:
    """Split rotation vectors (..., 3) into ordinary and large rows (see :class:`_Polar`)."""
    return _Polar(omega)


def _rodrigues_coefficients(
    p: _Polar, a: Tensor | None = None, b: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """(first, second) with Exp(ω) = I + first·[w]× + second·[w]×² (w = ω, or u when large).

    ``a``, ``b`` are the series-safe sinc coefficients at ``p.theta2`` if the caller has them.
    """
    if a is None or b is None:
        a, b = _series.sinc_coefficients(p.theta2)
    # Large rows: w = u, so first = sin θ and second = 1 − cos θ.
    return torch.where(p.large, p.sin_theta, a), torch.where(p.large, p.one_minus_cos, b)


def _jl_coefficients(p: _Polar, b: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """(first, second) with J_l(ω) = I + first·[w]× + second·[w]×².

    ``b`` is the Rodrigues (1 − cos θ)/θ² at ``p.theta2`` when the caller has it already.
    """
    if b is None:
        _, b = _series.sinc_coefficients(p.theta2)
    c = _series.jacobian_coefficient_c(p.theta2)
    # Large rows: first = (1 − cos θ)/θ, second = 1 − sin θ/θ (both bounded; 1/θ = 0 at Inf).
    inv_theta = 1.0 / p.theta
    return (
        torch.where(p.large, p.one_minus_cos * inv_theta, b),
        torch.where(p.large, 1.0 - p.sin_theta * inv_theta, c),
    )


# _skew_quadratic: entry (r, c) of the 3 × 3 result, row-major, as (k, l) with the quadratic
# part (second·w_k)·w_l (the same product for (r, c) and (c, r)), and as an index into
# (1 − second·θ², first·w, −first·w) for the rest: the diagonal, or ±first·w of [w]×.
_QUADRATIC_FIRST = (0, 0, 0, 0, 1, 1, 0, 1, 2)
_QUADRATIC_SECOND = (0, 1, 2, 1, 1, 2, 2, 2, 2)
_LINEAR = (0, 6, 2, 3, 0, 4, 5, 1, 0)


def _skew_quadratic(omega: Tensor, theta2: Tensor, first: Tensor, second: Tensor) -> Tensor:
    """I + first·[ω]× + second·[ω]×², built entrywise from [ω]×² = ωωᵀ − θ² I.

    Rodrigues' R (first = sin θ/θ, second = (1 − cos θ)/θ²) and the left Jacobian
    (first = (1 − cos θ)/θ², second = (θ − sin θ)/θ³) both have this form; building the nine
    entries directly avoids two batched 3×3 matmuls. Entry (r, c) is
    (1 − second·θ²)·[r = c] + (second·ω_r)·ω_c ± first·ω_k, the quadratic part formed once
    for each pair r ≤ c (so the result is exactly symmetric in it), all nine entries by a few
    whole-tensor operations (small batches are bound by their number).
    """
    device = omega.device
    second_w = second[..., None] * omega
    quadratic = second_w.index_select(
        -1, _series.constant("quadratic first", _QUADRATIC_FIRST, torch.long, device)
    ) * omega.index_select(
        -1, _series.constant("quadratic second", _QUADRATIC_SECOND, torch.long, device)
    )
    first_w = first[..., None] * omega
    linear = torch.cat(((1.0 - second * theta2)[..., None], first_w, -first_w), dim=-1)
    linear = linear.index_select(-1, _series.constant("skew linear", _LINEAR, torch.long, device))
    return (linear + quadratic).unflatten(-1, (3, 3))


def _exp(omega: Tensor) -> Tensor:
    # The θ-power form, for the solver's hot path (finite up to |ω| ≈ 1e154 in float64).
    theta2 = (omega * omega).sum(-1)
    a, b = _series.sinc_coefficients(theta2)
    return _skew_quadratic(omega, theta2, a, b)


def _exp_robust(omega: Tensor) -> Tensor:
    # Bitwise equal to _exp up to |ω| = 2²⁰ (2¹⁰ in float32), a rotation for every finite ω.
    p = _polar(omega)
    a, b = _rodrigues_coefficients(p)
    return _skew_quadratic(p.w, p.theta2, a, b)


def exp(omega: Tensor, *, form: Form = "robust") -> Tensor:
    """Exponential map so(3) → SO(3), Rodrigues' formula (seed eq. L4.1).

    R = I + (sin θ / θ) [ω]× + ((1 − cos θ) / θ²) [ω]×², θ = |ω|, with series branches near 0.
    Finite for every finite ω (the result is a rotation even for |ω| = 1e300).

    Args:
        omega: rotation vectors (axis · angle, radians), shape (..., 3).
        form: "robust" (finite for every finite ω) or "fast" (the θ-power form only: the same
            bits up to |ω| = 2²⁰, cheaper; see the module docstring).

    Returns:
        Rotation matrices, shape (..., 3, 3).
    """
    _checks.check_tensor("so3.exp", "omega", omega, (3,))
    _check_form("so3.exp", form)
    _checks.check_finite("so3.exp", "omega", omega)
    return _exp_robust(omega) if form == "robust" else _exp(omega)


def _log(R: Tensor) -> Tensor:
    # Through the unit quaternion: the one quaternion code is in convert.
    return convert._canonical_quaternion_to_axis_angle(convert._matrix_to_quaternion(R))


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


# The θ-power forms _jl and _jl_inv are form="fast" of the public functions (hot paths); the
# default form="robust" uses the _robust forms (bitwise equal up to |ω| = 2²⁰).


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
    return eye - 0.5 * W + d[..., None, None] * matmul(W, W)


def _jl_from_polar(p: _Polar) -> Tensor:
    first, second = _jl_coefficients(p)
    return _skew_quadratic(p.w, p.theta2, first, second)


def _jl_robust(omega: Tensor) -> Tensor:
    return _jl_from_polar(_polar(omega))


def _jl_inv_from_polar(p: _Polar) -> Tensor:
    d = _series.inverse_jacobian_coefficient_d(p.theta2)
    # Large rows (w = u): I − (θ/2)[u]× + (1 − (θ/2)cot(θ/2))[u]×²; it grows like θ and is
    # singular at θ = 2πk (Inf/NaN there, reported by the public functions).
    half_theta = 0.5 * p.theta
    h = torch.where(p.large, half_theta, 0.5)
    d = torch.where(p.large, 1.0 - half_theta * p.cos_half / p.sin_half, d)
    W = _hat(p.w)
    eye = torch.eye(3, dtype=W.dtype, device=W.device)
    return eye - h[..., None, None] * W + d[..., None, None] * matmul(W, W)


def _jl_inv_robust(omega: Tensor) -> Tensor:
    return _jl_inv_from_polar(_polar(omega))


_JL_INV_SINGULAR = (
    "J_l is singular at |ω| = 2πk (k ≥ 1) and its inverse grows like |ω|/2, so the inverse "
    "is not representable here"
)


def jl(omega: Tensor, *, form: Form = "robust") -> Tensor:
    """Left Jacobian of SO(3), the J of seed eq. L4.3.

    J_l(ω) = I + ((1 − cos θ)/θ²) [ω]× + ((θ − sin θ)/θ³) [ω]×², and
    Exp(ω + d) ≈ Exp(J_l(ω) d) · Exp(ω) for small d.

    Args:
        omega: rotation vectors, shape (..., 3).
        form: "robust" (default) or "fast" (θ-power form only; see the module docstring).

    Returns:
        Jacobians, shape (..., 3, 3).
    """
    _checks.check_tensor("so3.jl", "omega", omega, (3,))
    _check_form("so3.jl", form)
    _checks.check_finite("so3.jl", "omega", omega)
    return _jl_robust(omega) if form == "robust" else _jl(omega)


def jr(omega: Tensor, *, form: Form = "robust") -> Tensor:
    """Right Jacobian of SO(3): jr(ω) = jl(−ω); Exp(ω + d) ≈ Exp(ω) · Exp(jr(ω) d).

    Args:
        omega: rotation vectors, shape (..., 3).
        form: "robust" (default) or "fast" (θ-power form only; see the module docstring).

    Returns:
        Jacobians, shape (..., 3, 3).
    """
    _checks.check_tensor("so3.jr", "omega", omega, (3,))
    _check_form("so3.jr", form)
    _checks.check_finite("so3.jr", "omega", omega)
    return _jl_robust(-omega) if form == "robust" else _jl(-omega)


def jl_inv(omega: Tensor, *, form: Form = "robust") -> Tensor:
    """Inverse of :func:`jl`: I − ½[ω]× + ((1 − (θ/2)cot(θ/2))/θ²) [ω]×².

    Finite for θ < 2π (in particular at θ = π); singular at θ = 2πk, k ≥ 1. When value checks
    are active a result that is not finite raises ValueError.

    Args:
        omega: rotation vectors, shape (..., 3).
        form: "robust" (default) or "fast" (θ-power form only; see the module docstring).

    Returns:
        Jacobians, shape (..., 3, 3).
    """
    _checks.check_tensor("so3.jl_inv", "omega", omega, (3,))
    _check_form("so3.jl_inv", form)
    _checks.check_finite("so3.jl_inv", "omega", omega)
    result = _jl_inv_robust(omega) if form == "robust" else _jl_inv(omega)
    _checks.check_result_finite("so3.jl_inv", result, reason=_JL_INV_SINGULAR, omega=omega)
    return result


def jr_inv(omega: Tensor, *, form: Form = "robust") -> Tensor:
    """Inverse of :func:`jr`: jr_inv(ω) = jl_inv(−ω).

    Args:
        omega: rotation vectors, shape (..., 3).
        form: "robust" (default) or "fast" (θ-power form only; see the module docstring).

    Returns:
        Jacobians, shape (..., 3, 3).
    """
    _checks.check_tensor("so3.jr_inv", "omega", omega, (3,))
    _check_form("so3.jr_inv", form)
    _checks.check_finite("so3.jr_inv", "omega", omega)
    result = _jl_inv_robust(-omega) if form == "robust" else _jl_inv(-omega)
    _checks.check_result_finite("so3.jr_inv", result, reason=_JL_INV_SINGULAR, omega=omega)
    return result


def inverse(R: Tensor) -> Tensor:
    """Inverse rotation Rᵀ.

    Args:
        R: rotation matrices, shape (..., 3, 3); checked (orthonormal, det +1) when
            validation is on, since Rᵀ is the inverse of rotations only.

    Returns:
        Rᵀ, shape (..., 3, 3).
    """
    _checks.check_tensor("so3.inverse", "R", R, (3, 3))
    _checks.check_rotation("so3.inverse", "R", R)
    return R.transpose(-1, -2)


def act(R: Tensor, points: Tensor) -> Tensor:
    """Rotate points: R p, broadcasting ``points`` (..., 3) against ``R`` (..., 3, 3).

    Args:
        R: rotation matrices, shape (..., 3, 3); checked when validation is on.
        points: points, shape (..., 3); leading dims broadcast with those of ``R``.

    Returns:
        Rotated points, shape broadcast(R.shape[:-2], points.shape[:-1]) + (3,).
    """
    fn = "so3.act"
    _checks.check_tensor(fn, "R", R, (3, 3))
    _checks.check_tensor(fn, "points", points, (3,))
    _checks.check_same_kind(fn, R=R, points=points)
    _checks.check_broadcast(fn, R=R.shape[:-2], points=points.shape[:-1])
    _checks.check_rotation(fn, "R", R)
    _checks.check_finite(fn, "points", points)
    result = (R @ points[..., None]).squeeze(-1)
    _checks.check_result_finite(fn, result, R=R, points=points)
    return result


def adjoint(R: Tensor) -> Tensor:
    """Adjoint of SO(3): Ad_R = R, so that R Exp(d) Rᵀ = Exp(R d).

    Args:
        R: rotation matrices, shape (..., 3, 3); checked when validation is on.

    Returns:
        Adjoint matrices, shape (..., 3, 3) (a copy of ``R``).
    """
    _checks.check_tensor("so3.adjoint", "R", R, (3, 3))
    _checks.check_rotation("so3.adjoint", "R", R)
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
    # The nearest rotation does not depend on a positive scale of M: bring matrices with huge
    # or tiny entries to unit scale first (the SVD loses them otherwise); others are untouched.
    m = M.detach().abs().amax(dim=(-1, -2))
    rescale = (m > 0) & ~((m >= 2.0**-64) & (m <= 2.0**64))
    M = M / torch.where(rescale, m, torch.ones_like(m))[..., None, None]
    U, _, Vh = torch.linalg.svd(M)
    det = torch.linalg.det(U @ Vh)
    fix = torch.ones(*M.shape[:-2], 3, dtype=M.dtype, device=M.device)
    fix = torch.cat((fix[..., :2], det[..., None].sign()), dim=-1)
    return (U * fix[..., None, :]) @ Vh


# convert holds the quaternion code that log uses; it imports this module, hence the import here
# at the end (either module may be imported first).
from torchslam.lie import convert  # noqa: E402
