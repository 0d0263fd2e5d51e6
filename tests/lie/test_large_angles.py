"""Huge rotation vectors and translations: the unit-axis form of so3/se3, scaled translations.

Beyond |ω| = 2²⁰ (float64; 2¹⁰ in float32) the maps switch from the θ-power formulas to a
unit-axis form that cannot overflow, and translations with entries beyond 2⁵¹² (2⁶⁴) are scaled
by an exact power of two inside the formulas. These tests pin that both forms are the same maps
(by forcing the switch down to moderate angles), that the Jacobians there still equal jacrev
and central differences of their defining relations, and the limits for |ω| → ∞.
"""

from __future__ import annotations

import math

import pytest
import torch
from torch.func import jacrev, vmap

import torchslam
from tests.helpers import HARD_TRANSLATIONS, central_difference, rotation_vectors_with_angles
from torchslam.lie import convert, se3, so3

F64, F32 = torch.float64, torch.float32
# Moderate angles where the θ-power formulas are accurate to round-off; below 2π so that
# jl_inv is finite, away from 2π so that it is well conditioned.
MODERATE_ANGLES = (0.7, 1.0, 2.0, math.pi, 4.0, 5.5)
# Beyond the float64 switch at 2²⁰.
LARGE_ANGLES = (2.0**20 * 1.5, 1e7)


def _max_rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    """Max error relative to max(1, max|b|) per batch row (rows are the leading dim)."""
    scale = b.reshape(b.shape[0], -1).abs().amax(-1).clamp_min(1.0)
    return float(((a - b).reshape(b.shape[0], -1).abs().amax(-1) / scale).max())


def _twists(omega: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    rows = []
    for scale in HARD_TRANSLATIONS:
        v = scale * torch.randn(omega.shape[0], 3, generator=generator, dtype=F64)
        rows.append(torch.cat((omega.to(F64), v), dim=-1))
    return torch.cat(rows).to(omega.dtype)


SO3_MAPS = [
    so3.exp,
    so3.jl,
    so3.jr,
    so3.jl_inv,
    so3.jr_inv,
    convert.axis_angle_to_quaternion,
]
SE3_MAPS = [se3.exp, se3.jl, se3.jr, se3.jl_inv, se3.jr_inv]


@pytest.mark.parametrize("dtype", [F64, F32], ids=["f64", "f32"])
def test_unit_axis_form_equals_angle_power_form(monkeypatch, generator, dtype):
    # Both forms evaluate the same closed forms to round-off: 1e-13 (float64) / 2e-5 (float32)
    # relative to the entries, which reach ~|v|·θ² for the SE(3) inverse Jacobian at 5.5 rad.
    tol = 1e-13 if dtype == F64 else 2e-5
    omega = rotation_vectors_with_angles(MODERATE_ANGLES, generator, dtype=dtype)
    xi = _twists(omega, generator)
    reference = [f(omega) for f in SO3_MAPS] + [f(xi) for f in SE3_MAPS]
    reference_jac = [vmap(jacrev(f))(omega) for f in SO3_MAPS[:3]]
    reference_jac += [vmap(jacrev(f))(xi) for f in SE3_MAPS[:3]]
    # Every angle above 0.6 now takes the unit-axis form.
    monkeypatch.setitem(so3._LARGE_ANGLE_SQUARED, dtype, 0.36)
    values = [f(omega) for f in SO3_MAPS] + [f(xi) for f in SE3_MAPS]
    jacobians = [vmap(jacrev(f))(omega) for f in SO3_MAPS[:3]]
    jacobians += [vmap(jacrev(f))(xi) for f in SE3_MAPS[:3]]
    for value, expected in zip(values, reference, strict=True):
        assert _max_rel_err(value, expected) <= tol
    # Derivatives of exp and of the Jacobians themselves: the same maps, so the same slopes.
    for value, expected in zip(jacobians, reference_jac, strict=True):
        assert _max_rel_err(value, expected) <= 10 * tol


def test_translation_scaling_is_exact(monkeypatch, generator):
    # Scaling by 2⁻⁵¹² and back is exact in IEEE arithmetic (no product leaves the normal
    # range for these inputs), so forcing it on every translation changes nothing beyond
    # the reassociation-free round-off: equal to 4 ulps.
    omega = rotation_vectors_with_angles((0.0, 1e-8, 0.5, *MODERATE_ANGLES), generator)
    xi = _twists(omega, generator)
    reference = [f(xi) for f in SE3_MAPS]
    monkeypatch.setitem(se3._TRANSLATION_SCALE, F64, (0.0, 2.0**-512))
    for f, expected in zip(SE3_MAPS, reference, strict=True):
        assert _max_rel_err(f(xi), expected) <= 4 * torch.finfo(F64).eps


def _defining_so3_jr(omega):
    return lambda d: so3.log(so3.inverse(so3.exp(omega)) @ so3.exp(omega + d))


def _defining_so3_jl(omega):
    return lambda d: so3.log(so3.exp(omega + d) @ so3.inverse(so3.exp(omega)))


def _defining_se3_jr(xi):
    return lambda d: se3.log(se3.compose(se3.inverse(se3.exp(xi)), se3.exp(xi + d)))


def _defining_se3_jl(xi):
    return lambda d: se3.log(se3.compose(se3.exp(xi + d), se3.inverse(se3.exp(xi))))


@pytest.mark.parametrize(
    ("defining", "analytic", "twist"),
    [
        (_defining_so3_jr, so3.jr, False),
        (_defining_so3_jl, so3.jl, False),
        (_defining_se3_jr, se3.jr, True),
        (_defining_se3_jl, se3.jl, True),
    ],
    ids=["so3.jr", "so3.jl", "se3.jr", "se3.jl"],
)
def test_large_angle_jacobians_equal_jacrev_and_central_differences(
    defining, analytic, twist, generator
):
    # The inverse Jacobians are left out: their defining relation goes through Log, whose
    # principal value differs from ω beyond π (they are pinned by the unit-axis test above).
    omega = rotation_vectors_with_angles(LARGE_ANGLES, generator, per_angle=2)
    inputs = _twists(omega, generator) if twist else omega
    zero = inputs.new_zeros(inputs.shape[-1])
    J_analytic = analytic(inputs)
    J_jacrev = vmap(lambda x: jacrev(defining(x))(zero))(inputs)
    # jacrev differentiates the same floating-point θ: agreement to round-off of the entries
    # (up to ~|v| for the Q block).
    assert _max_rel_err(J_jacrev, J_analytic) <= 1e-11
    eps = 1e-3
    for x, J in zip(inputs, J_analytic, strict=True):
        theta = float(x[:3].norm())
        # ω + d is rounded to ½ulp(θ) per entry, which the quotient divides by 2·eps; the
        # truncation error is O(eps²) with O(1) third derivatives (×|v| for the Q block).
        ulp = math.ulp(theta)
        scale = max(1.0, float(J.abs().max()))
        tol = (2 * ulp / eps + 2 * eps**2) * scale
        assert float((central_difference(defining(x), zero, eps=eps) - J).abs().max()) <= tol


def test_limits_for_infinite_angle():
    # |ω| → ∞ (here 2²⁵⁰, 1e300 and entries whose norm overflows): the 1/θ terms vanish.
    # J_l → u uᵀ, and the Q block → ½V + ½(UUV + VUU) − ½UVU with U = [u]×, V = [v]×.
    u = torch.tensor([2.0, -1.0, 2.0], dtype=F64) / 3.0
    v = torch.tensor([0.5, 1.5, -2.0], dtype=F64)
    U, V = so3.hat(u), so3.hat(v)
    J_limit = torch.outer(u, u)
    Q_limit = 0.5 * V + 0.5 * (U @ U @ V + V @ U @ U) - 0.5 * U @ V @ U
    for theta in (2.0**250, 2.0**350, 1e300):
        J = se3.jl(torch.cat((u * theta, v)))
        # Deviations are O(1/θ) ≤ 1e-75 (the Q coefficients use min(θ, 2³⁰⁰)): round-off only.
        assert float((J[:3, :3] - J_limit).abs().max()) <= 1e-15
        assert float((J[3:, 3:] - J_limit).abs().max()) <= 1e-15
        assert float((J[3:, :3] - Q_limit).abs().max()) <= 1e-15 * float(v.abs().max())
    # Entries of 1.5e308: |ω| overflows the dtype, the rotation is still finite and exact.
    omega = torch.full((3,), 1.5e308, dtype=F64)
    R = so3.exp(omega)
    assert float((R.T @ R - torch.eye(3, dtype=F64)).abs().max()) <= 1e-15
    assert float((so3.jl(omega) - torch.full((3, 3), 1.0 / 3.0, dtype=F64)).abs().max()) <= 1e-15


@pytest.mark.parametrize("dtype", [F64, F32], ids=["f64", "f32"])
def test_robust_forms_equal_the_hot_path_forms_bitwise(generator, dtype):
    # The solver calls form="fast" (the θ-power forms); the default form="robust" takes the very
    # same operations on ordinary input (every hard angle, angles up to the switch,
    # translations up to 1e4): equal bits.
    below_switch = 2.0**20 * 0.99 if dtype == F64 else 2.0**10 * 0.99
    angles = (0.0, 1e-12, 1e-8, 1e-4, 0.3, 0.5, math.pi / 2, math.pi - 1e-6, math.pi, 7.0)
    omega = rotation_vectors_with_angles((*angles, below_switch), generator, dtype=dtype)
    xi = _twists(omega, generator)
    for module, x in ((so3, omega), (se3, xi)):
        for name in ("exp", "jl", "jr", "jl_inv", "jr_inv"):
            f = getattr(module, name)
            with torchslam.validation(False):
                assert torch.equal(f(x, form="fast"), f(x)), f"{module.__name__}.{name}"


def test_form_is_checked():
    for f in (so3.exp, so3.jl, so3.jr, so3.jl_inv, so3.jr_inv):
        with pytest.raises(ValueError, match=rf"so3\.{f.__name__}: argument 'form' must be"):
            f(torch.zeros(3, dtype=F64), form="unit_axis")
    for f in (se3.exp, se3.jl, se3.jr, se3.jl_inv, se3.jr_inv):
        with pytest.raises(ValueError, match=rf"se3\.{f.__name__}: argument 'form' must be"):
            f(torch.zeros(6, dtype=F64), form=None)
