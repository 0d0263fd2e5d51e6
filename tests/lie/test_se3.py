"""SE(3), ξ = (ω, v): hat/vee, exp/log, group identities, Jacobians, autograd, shapes, errors."""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor
from torch.func import jacrev, vmap

import torchslam
from tests.helpers import (
    HARD_ANGLES,
    HARD_TRANSLATIONS,
    TOL,
    central_difference,
    rotation_vectors_with_angles,
    twists_with_hard_inputs,
)
from torchslam.lie import se3, so3

BATCH_SHAPES = [(), (1,), (3, 1, 2)]
EYE6 = torch.eye(6, dtype=torch.float64)


def _random_xi(shape, generator, dtype, max_angle=math.pi - 1e-3, translation=2.0):
    axes = torch.randn(*shape, 3, generator=generator, dtype=torch.float64)
    axes = axes / axes.norm(dim=-1, keepdim=True)
    angles = torch.rand(*shape, 1, generator=generator, dtype=torch.float64) * max_angle
    v = translation * torch.randn(*shape, 3, generator=generator, dtype=torch.float64)
    return torch.cat((axes * angles, v), dim=-1).to(dtype)


def _max_err(a, b) -> float:
    return float((a - b).abs().max())


def _rel_err(a: Tensor, b: Tensor) -> Tensor:
    """Per-row max error relative to max(1, |b|): absolute at unit scale, relative beyond."""
    scale = b.flatten(-2).abs().amax(-1) if b.dim() >= 3 else b.abs().amax(-1)
    err = (a - b).flatten(-2).abs().amax(-1) if b.dim() >= 3 else (a - b).abs().amax(-1)
    return err / scale.clamp_min(1.0)


def _hard_twists(generator, dtype=torch.float64, below_pi=False):
    xi = twists_with_hard_inputs(generator, dtype=torch.float64)
    if below_pi:
        # Rows with θ = π have two valid logs (±ω); keep θ ≤ π − 1e-6.
        xi = xi[xi[:, :3].norm(dim=-1) < math.pi - 1e-7]
    return xi.to(dtype)


# --------------------------------------------------------------------------- hat / vee


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_hat_vee_inverse_pair(shape, dtype, generator):
    xi = torch.randn(*shape, 6, generator=generator, dtype=torch.float64).to(dtype)
    Xi = se3.hat(xi)
    assert Xi.shape == (*shape, 4, 4) and Xi.dtype == dtype
    assert torch.equal(se3.vee(Xi), xi)
    # Rotation first: the top-left block is [ω]×, the last column is v, the last row is 0.
    assert torch.equal(Xi[..., :3, :3], so3.hat(xi[..., :3]))
    assert torch.equal(Xi[..., :3, 3], xi[..., 3:])
    assert not bool(Xi[..., 3, :].any())


# --------------------------------------------------------------------------- exp / log


def test_exp_log_round_trip_hard_inputs(dtype, generator):
    xi = _hard_twists(generator, dtype, below_pi=True)
    T = se3.exp(xi)
    # Tolerance relative to |ξ| for the huge (1e4) translations.
    assert float(_rel_err(se3.log(T), xi).max()) <= TOL[dtype]
    assert float(_rel_err(se3.exp(se3.log(T)), T).max()) <= TOL[dtype]
    assert _max_err(T[..., 3, :], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=dtype)) == 0.0


def test_exp_log_round_trip_random(dtype, generator):
    xi = _random_xi((200,), generator, dtype, max_angle=math.pi - 1e-6)
    assert float(_rel_err(se3.log(se3.exp(xi)), xi).max()) <= TOL[dtype]


def test_exp_log_at_exactly_pi(dtype, generator):
    xi = _hard_twists(generator, torch.float64)
    xi = xi[xi[:, :3].norm(dim=-1) > math.pi - 1e-9].to(dtype)  # θ = π up to round-off
    assert xi.shape[0] == 2 * len(HARD_TRANSLATIONS)
    T = se3.exp(xi)
    assert float(_rel_err(se3.exp(se3.log(T)), T).max()) <= TOL[dtype]


def test_exp_of_pure_translation_and_pure_rotation(dtype, generator):
    v = torch.randn(5, 3, generator=generator, dtype=torch.float64).to(dtype)
    T = se3.exp(torch.cat((torch.zeros_like(v), v), dim=-1))
    assert torch.equal(T[..., :3, :3], torch.eye(3, dtype=dtype).expand(5, 3, 3))
    assert torch.equal(T[..., :3, 3], v)
    omega = torch.randn(5, 3, generator=generator, dtype=torch.float64).to(dtype)
    T = se3.exp(torch.cat((omega, torch.zeros_like(omega)), dim=-1))
    assert torch.equal(T[..., :3, :3], so3.exp(omega))
    assert not bool(T[..., :3, 3].any())


def test_exp_translation_is_jl_times_v(generator):
    # Seed eq. L3: t = J_l(ω) v.
    xi = _hard_twists(generator)
    T = se3.exp(xi)
    t = (so3.jl(xi[:, :3]) @ xi[:, 3:, None]).squeeze(-1)
    assert _max_err(T[:, :3, 3], t) <= 1e-12 * max(HARD_TRANSLATIONS)


# --------------------------------------------------------------------------- group identities


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_compose_inverse(shape, dtype, generator):
    A, B, C = (se3.exp(_random_xi(shape, generator, dtype)) for _ in range(3))
    eye = torch.eye(4, dtype=dtype)
    tol = 10 * TOL[dtype]
    assert _max_err(se3.compose(A, se3.inverse(A)), eye) <= tol
    assert _max_err(se3.compose(se3.inverse(A), A), eye) <= tol
    assert _max_err(se3.compose(se3.compose(A, B), C), se3.compose(A, se3.compose(B, C))) <= tol
    lhs = se3.inverse(se3.compose(A, B))
    assert _max_err(lhs, se3.compose(se3.inverse(B), se3.inverse(A))) <= tol
    xi = _random_xi(shape, generator, dtype)
    assert _max_err(se3.exp(-xi), se3.inverse(se3.exp(xi))) <= tol
    assert _max_err(se3.compose(se3.exp(0.4 * xi), se3.exp(0.6 * xi)), se3.exp(xi)) <= tol
    # log(T⁻¹) = −log(T) for θ < π.
    assert _max_err(se3.log(se3.inverse(se3.exp(xi))), -xi) <= tol


def test_identity_and_from_rotation_translation(dtype, generator):
    identity = se3.identity(2, 3, dtype=dtype)
    assert identity.shape == (2, 3, 4, 4) and identity.dtype == dtype
    assert torch.equal(se3.log(identity), torch.zeros(2, 3, 6, dtype=dtype))
    assert se3.identity().dtype == torch.float64
    xi = _random_xi((4,), generator, dtype)
    T = se3.exp(xi)
    assert torch.equal(se3.from_rotation_translation(T[..., :3, :3], T[..., :3, 3]), T)
    # A single rotation broadcasts against many translations.
    t = torch.randn(4, 3, generator=generator, dtype=torch.float64).to(dtype)
    assert se3.from_rotation_translation(T[0, :3, :3], t).shape == (4, 4, 4)


def test_act_broadcasting(dtype, generator):
    T = se3.exp(_random_xi((4,), generator, dtype))
    points = torch.randn(4, 5, 3, generator=generator, dtype=torch.float64).to(dtype)
    out = se3.act(T[..., None, :, :], points)
    assert out.shape == (4, 5, 3)
    expected = torch.einsum("bij,bnj->bni", T[:, :3, :3], points) + T[:, None, :3, 3]
    assert _max_err(out, expected) <= 10 * TOL[dtype]
    # Homogeneous coordinates agree.
    homogeneous = torch.cat((points, torch.ones_like(points[..., :1])), dim=-1)
    assert _max_err(out, (T[:, None] @ homogeneous[..., None])[..., :3, 0]) <= 10 * TOL[dtype]
    # One pose against many points; many poses against one point.
    assert se3.act(T[0], points).shape == (4, 5, 3)
    assert se3.act(T, points[0, 0]).shape == (4, 3)
    # act(A·B, p) = act(A, act(B, p)); act(T⁻¹, act(T, p)) = p.
    A, B = T[0], T[1]
    assert _max_err(se3.act(se3.compose(A, B), points), se3.act(A, se3.act(B, points))) <= (
        10 * TOL[dtype]
    )
    back = se3.act(se3.inverse(T)[:, None], out)
    assert _max_err(back, points) <= 10 * TOL[dtype]


def test_adjoint_identity_at_hard_inputs(dtype, generator):
    # T Exp(d) T⁻¹ = Exp(Ad_T d), for T over every hard angle and translation.
    T = se3.exp(_hard_twists(generator, dtype))
    d = 0.5 * _random_xi(T.shape[:1], generator, dtype, translation=1.0)
    lhs = se3.compose(se3.compose(T, se3.exp(d)), se3.inverse(T))
    rhs = se3.exp((se3.adjoint(T) @ d[..., None]).squeeze(-1))
    # Relative: Ad_T d has a translation part |t|·|d| up to 1e4.
    assert float(_rel_err(lhs, rhs).max()) <= 10 * TOL[dtype]


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_adjoint_homomorphism(shape, dtype, generator):
    A = se3.exp(_random_xi(shape, generator, dtype))
    B = se3.exp(_random_xi(shape, generator, dtype))
    tol = 20 * TOL[dtype]
    assert _max_err(se3.adjoint(se3.compose(A, B)), se3.adjoint(A) @ se3.adjoint(B)) <= tol
    assert _max_err(se3.adjoint(se3.inverse(A)) @ se3.adjoint(A), torch.eye(6, dtype=dtype)) <= tol


def test_jacobian_identities_at_hard_inputs(dtype, generator):
    xi = torch.cat((_hard_twists(generator, dtype), _random_xi((16,), generator, dtype)))
    Jl, Jr = se3.jl(xi), se3.jr(xi)
    Jl_inv, Jr_inv = se3.jl_inv(xi), se3.jr_inv(xi)
    for J in (Jl, Jr, Jl_inv, Jr_inv):
        assert bool(torch.isfinite(J).all())  # jl_inv is finite at θ = π
    eye = torch.eye(6, dtype=dtype)
    # Entries grow like |v| (the Q block), products like |v|²: tolerances relative to those.
    scale = (1.0 + xi[:, 3:].norm(dim=-1)) ** 2
    rtol = 10 * TOL[dtype]

    def close(a, b):
        err = (a - b).abs().amax(dim=(-1, -2))
        return bool((err <= rtol * scale).all())

    # Ad(Exp(ξ)) · Jr(ξ) = Jl(ξ).
    assert close(se3.adjoint(se3.exp(xi)) @ Jr, Jl)
    # Jr(−ξ) = Jl(ξ).
    assert close(se3.jr(-xi), Jl)
    # J · J⁻¹ = I, both sides.
    assert close(Jl @ Jl_inv, eye)
    assert close(Jl_inv @ Jl, eye)
    assert close(Jr @ Jr_inv, eye)
    assert close(Jr_inv @ Jr, eye)
    # Jl(ξ) ξ = ξ.
    assert close((Jl @ xi[..., None]).squeeze(-1)[..., None], xi[..., None])
    # The rotation blocks are the SO(3) Jacobians.
    assert torch.equal(Jl[:, :3, :3], so3.jl(xi[:, :3]))
    assert not bool(Jl[:, :3, 3:].any())


# --------------------------------------------------------------------------- Jacobians


def _defining_jr(xi):
    return lambda d: se3.log(se3.compose(se3.inverse(se3.exp(xi)), se3.exp(xi + d)))


def _defining_jl(xi):
    return lambda d: se3.log(se3.compose(se3.exp(xi + d), se3.inverse(se3.exp(xi))))


def _defining_jr_inv(xi):
    return lambda d: se3.log(se3.compose(se3.exp(xi), se3.exp(d)))


def _defining_jl_inv(xi):
    return lambda d: se3.log(se3.compose(se3.exp(d), se3.exp(xi)))


def _defining_adjoint(T):
    return lambda d: se3.log(se3.compose(se3.compose(T, se3.exp(d)), se3.inverse(T)))


def _jacobian_inputs(generator, angles):
    omega = rotation_vectors_with_angles(angles, generator, per_angle=1)
    rows = [omega.new_zeros(0, 6)]
    for scale in (0.0, 1e-9, 1.0, 1e3):
        v = scale * torch.randn(omega.shape[0], 3, generator=generator, dtype=torch.float64)
        rows.append(torch.cat((omega, v), dim=-1))
    rows.append(_random_xi((4,), generator, torch.float64))
    return torch.cat(rows)


def _check_against_jacrev_and_central(defining, analytic, inputs, eps, rtol_central):
    """For each input x: analytic(x) = jacrev(defining(x))(0) = central differences at 0."""
    zero = inputs.new_zeros(6)
    J_jacrev = vmap(lambda x: jacrev(defining(x))(zero))(inputs)
    J_analytic = analytic(inputs)
    assert bool(torch.isfinite(J_jacrev).all())
    scale = J_analytic.abs().amax(dim=(-1, -2)).clamp_min(1.0)
    err = (J_jacrev - J_analytic).abs().amax(dim=(-1, -2))
    assert float((err / scale).max()) <= 1e-11
    for x, J, s in zip(inputs, J_analytic, scale, strict=True):
        J_central = central_difference(defining(x), zero, eps=eps)
        assert _max_err(J_central, J) <= rtol_central * float(s)


@pytest.mark.parametrize(
    ("defining", "analytic"),
    [(_defining_jr, se3.jr), (_defining_jl, se3.jl)],
    ids=["jr", "jl"],
)
def test_jacobians_equal_jacrev_and_central_differences(defining, analytic, generator):
    # The defining expression stays near the identity, so θ = π is included.
    inputs = _jacobian_inputs(generator, HARD_ANGLES)
    _check_against_jacrev_and_central(defining, analytic, inputs, eps=1e-6, rtol_central=1e-7)


@pytest.mark.parametrize(
    ("defining", "analytic"),
    [(_defining_jr_inv, se3.jr_inv), (_defining_jl_inv, se3.jl_inv)],
    ids=["jr_inv", "jl_inv"],
)
def test_inverse_jacobians_equal_jacrev_and_central_differences(defining, analytic, generator):
    # These differentiate Log at Exp(ξ), which jumps (ω → −ω) at θ = π: use θ ≤ π − 1e-6 and
    # a step of 1e-7 so that the central differences never cross π.
    angles = tuple(a for a in HARD_ANGLES if a < math.pi)
    inputs = _jacobian_inputs(generator, angles)
    _check_against_jacrev_and_central(defining, analytic, inputs, eps=1e-7, rtol_central=1e-6)


def test_adjoint_equals_jacrev_and_central_differences(generator):
    T = se3.exp(_jacobian_inputs(generator, HARD_ANGLES))
    _check_against_jacrev_and_central(
        _defining_adjoint, se3.adjoint, T, eps=1e-6, rtol_central=1e-7
    )


def test_exp_first_order_expansion(generator):
    # Exp(ξ + d) ≈ Exp(ξ) Exp(jr(ξ) d) and ≈ Exp(jl(ξ) d) Exp(ξ), error O(|d|²).
    xi = _jacobian_inputs(generator, HARD_ANGLES)
    xi = xi[xi[:, 3:].norm(dim=-1) < 10]
    d = 1e-5 * _random_xi(xi.shape[:1], generator, torch.float64, translation=1.0)
    lhs = se3.exp(xi + d)
    right = se3.compose(se3.exp(xi), se3.exp((se3.jr(xi) @ d[..., None]).squeeze(-1)))
    left = se3.compose(se3.exp((se3.jl(xi) @ d[..., None]).squeeze(-1)), se3.exp(xi))
    assert _max_err(lhs, right) <= 1e-8
    assert _max_err(lhs, left) <= 1e-8


# --------------------------------------------------------------------------- autograd

GRAD_ANGLES = (0.0, 1e-8, math.pi / 2, math.pi - 1e-6)


def _grad_points(generator, angles=GRAD_ANGLES):
    omega = rotation_vectors_with_angles(angles, generator, per_angle=1)
    v = torch.randn(omega.shape[0], 3, generator=generator, dtype=torch.float64)
    return torch.cat((omega, v), dim=-1)


@pytest.mark.parametrize("fn", [se3.exp, se3.jl, se3.jr, se3.jl_inv, se3.jr_inv], ids=str)
def test_gradcheck_at_zero_and_near_pi(fn, generator):
    for xi in _grad_points(generator, (*GRAD_ANGLES, math.pi)):
        assert torch.autograd.gradcheck(fn, (xi.clone().requires_grad_(True),))


def test_gradgradcheck_exp_at_zero():
    x = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradgradcheck(se3.exp, (x,))


def test_log_gradients_at_zero_and_near_pi(generator):
    # log as a function of T in the ambient 4×4 space (validation off: gradcheck's steps leave
    # SE(3)); at θ = π − 1e-6 a step of 1e-8 keeps θ below π.
    for xi in _grad_points(generator):
        T = se3.exp(xi).requires_grad_(True)
        with torchslam.validation(False):
            assert torch.autograd.gradcheck(se3.log, (T,), eps=1e-8, atol=1e-6)
        # Along the manifold: d log(exp(ξ)) / dξ = I.
        J = torch.autograd.functional.jacobian(lambda x: se3.log(se3.exp(x)), xi)
        assert _max_err(J, EYE6) <= 1e-9


@pytest.mark.parametrize("fn", [se3.exp, se3.jl, se3.jr, se3.jl_inv], ids=str)
def test_autograd_equals_central_differences(fn, generator):
    for xi in _grad_points(generator):
        J_autograd = torch.autograd.functional.jacobian(fn, xi).reshape(-1, 6)
        assert bool(torch.isfinite(J_autograd).all())
        assert _max_err(J_autograd, central_difference(fn, xi, eps=1e-6)) <= 1e-8


def test_act_gradient_matches_closed_form(generator):
    # ∂(T Exp(d) p)/∂d at d = 0 = R [I | … ] in (ω, v) order: [−R [p]×, R].
    T = se3.exp(_random_xi((), generator, torch.float64))
    p = torch.randn(3, generator=generator, dtype=torch.float64)
    J = jacrev(lambda d: se3.act(se3.compose(T, se3.exp(d)), p))(torch.zeros(6).double())
    R = T[:3, :3]
    expected = torch.cat((-R @ so3.hat(p), R), dim=-1)
    assert _max_err(J, expected) <= 1e-12


# --------------------------------------------------------------------------- shapes, vmap


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_batch_shapes_dtype_device(shape, dtype, device, generator):
    xi = _random_xi(shape, generator, dtype).to(device)
    T = se3.exp(xi)
    assert T.shape == (*shape, 4, 4) and T.dtype == dtype and T.device == xi.device
    for fn in (se3.jl, se3.jr, se3.jl_inv, se3.jr_inv):
        out = fn(xi)
        assert out.shape == (*shape, 6, 6) and out.dtype == dtype and out.device == xi.device
    for out in (se3.hat(xi), se3.inverse(T), se3.compose(T, T)):
        assert out.shape == (*shape, 4, 4) and out.dtype == dtype and out.device == xi.device
    assert se3.adjoint(T).shape == (*shape, 6, 6)
    for out in (se3.log(T), se3.vee(se3.hat(xi))):
        assert out.shape == (*shape, 6) and out.dtype == dtype and out.device == xi.device
    points = xi[..., 3:]
    out = se3.act(T, points)
    assert out.shape == (*shape, 3) and out.dtype == dtype and out.device == xi.device


def test_functions_run_inside_vmap(generator):
    xi = _random_xi((5,), generator, torch.float64)
    T = se3.exp(xi)
    for fn, x in [
        (se3.exp, xi),
        (se3.log, T),
        (se3.jl, xi),
        (se3.jr, xi),
        (se3.jl_inv, xi),
        (se3.jr_inv, xi),
        (se3.hat, xi),
        (se3.vee, se3.hat(xi)),
        (se3.inverse, T),
        (se3.adjoint, T),
    ]:
        assert _max_err(vmap(fn)(x), fn(x)) <= 1e-14
    assert _max_err(vmap(se3.act)(T, xi[:, 3:]), se3.act(T, xi[:, 3:])) <= 1e-14
    assert _max_err(vmap(se3.compose)(T, T), se3.compose(T, T)) <= 1e-14


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("fn", "name", "bad_shape"),
    [
        (se3.exp, "xi", (4, 3)),
        (se3.hat, "xi", (5,)),
        (se3.jl, "xi", (2, 7)),
        (se3.jr, "xi", (3,)),
        (se3.jl_inv, "xi", (6, 1)),
        (se3.jr_inv, "xi", (1,)),
        (se3.log, "T", (3, 4)),
        (se3.vee, "Xi", (4,)),
        (se3.inverse, "T", (2, 4, 3)),
        (se3.adjoint, "T", (6, 6)),
    ],
)
def test_wrong_shape_names_function_argument_and_shape(fn, name, bad_shape):
    with pytest.raises(ValueError) as info:
        fn(torch.zeros(bad_shape, dtype=torch.float64))
    message = str(info.value)
    assert message.startswith(f"se3.{fn.__name__}: argument '{name}'")
    assert f"got {bad_shape}" in message


def test_wrong_dtype_type_and_mixed_kinds():
    with pytest.raises(TypeError, match=r"se3\.exp: argument 'xi' must be float32 or float64"):
        se3.exp(torch.zeros(6, dtype=torch.int32))
    with pytest.raises(TypeError, match=r"se3\.log: argument 'T' must be a torch\.Tensor"):
        se3.log(torch.eye(4).numpy())
    T64 = torch.eye(4, dtype=torch.float64)
    with pytest.raises(TypeError, match=r"se3\.compose: 'T1' is torch\.float64 but 'T2'"):
        se3.compose(T64, T64.float())
    with pytest.raises(TypeError, match=r"se3\.act: 'T' is torch\.float64 but 'points'"):
        se3.act(T64, torch.zeros(3))
    with pytest.raises(ValueError, match=r"se3\.act: argument 'points' must have shape"):
        se3.act(T64, torch.zeros(4, dtype=torch.float64))


def test_non_finite_non_rigid_and_bad_bottom_row_rejected():
    xi = torch.zeros(3, 6, dtype=torch.float64)
    xi[2, 4] = float("nan")
    with pytest.raises(
        ValueError, match=r"se3\.exp: argument 'xi' contains 1 non-finite.*\(2, 4\)"
    ):
        se3.exp(xi)
    T = se3.identity(2)
    T[1, :3, :3] *= 2.0
    with pytest.raises(ValueError, match=r"se3\.log: argument 'T' must hold rotation matrices"):
        se3.log(T)
    T = se3.identity(2)
    T[0, 3, 1] = 0.5
    with pytest.raises(ValueError, match=r"se3\.log: argument 'T' must have bottom row"):
        se3.log(T)
    T = se3.identity()
    T[0, 3] = float("inf")
    with pytest.raises(ValueError, match=r"se3\.log: argument 'T' contains 1 non-finite"):
        se3.log(T)


def test_validation_false_disables_value_checks():
    T = se3.identity()
    T[3, 0] = 0.5
    with torchslam.validation(False):
        assert se3.log(T).shape == (6,)
        with pytest.raises(ValueError, match=r"se3\.log"):
            se3.log(torch.eye(3, dtype=torch.float64))
    with pytest.raises(ValueError, match="bottom row"):
        se3.log(T)
