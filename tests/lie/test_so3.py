"""SO(3): hat/vee, exp/log round trips, group identities, Jacobians, autograd, shapes, errors."""

from __future__ import annotations

import math

import pytest
import torch
from pytorch_kinematics.transforms import so3_log_map
from torch.func import jacrev, vmap

import torchslam
from tests.helpers import (
    HARD_ANGLES,
    TOL,
    central_difference,
    rotation_vectors_with_angles,
)
from torchslam.lie import so3

BATCH_SHAPES = [(), (1,), (3, 1, 2)]
EYE = torch.eye(3, dtype=torch.float64)
# Angles where Log is differentiable (θ < π); derivative-of-log checks use these.
ANGLES_BELOW_PI = tuple(a for a in HARD_ANGLES if a < math.pi)


def _random_omega(shape, generator, dtype, max_angle=math.pi - 1e-3):
    axes = torch.randn(*shape, 3, generator=generator, dtype=torch.float64)
    axes = axes / axes.norm(dim=-1, keepdim=True)
    angles = torch.rand(*shape, 1, generator=generator, dtype=torch.float64) * max_angle
    return (axes * angles).to(dtype)


def _max_err(a, b) -> float:
    return float((a - b).abs().max())


# --------------------------------------------------------------------------- hat / vee


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_hat_vee_inverse_pair(shape, dtype, generator):
    omega = torch.randn(*shape, 3, generator=generator, dtype=torch.float64).to(dtype)
    W = so3.hat(omega)
    assert W.shape == (*shape, 3, 3) and W.dtype == dtype
    assert torch.equal(so3.vee(W), omega)
    assert torch.equal(W, -W.transpose(-1, -2))
    b = torch.randn(*shape, 3, generator=generator, dtype=torch.float64).to(dtype)
    cross = torch.linalg.cross(omega, b, dim=-1)
    assert _max_err((W @ b[..., None]).squeeze(-1), cross) <= TOL[dtype]
    # hat(vee(S)) = S for a skew S; vee uses the antisymmetric part of a general matrix.
    M = torch.randn(*shape, 3, 3, generator=generator, dtype=torch.float64).to(dtype)
    S = M - M.transpose(-1, -2)
    assert _max_err(so3.hat(so3.vee(S)), S) <= TOL[dtype]
    assert _max_err(so3.vee(M), so3.vee(0.5 * S)) <= TOL[dtype]


# --------------------------------------------------------------------------- exp / log


def _sweep_angles() -> list[float]:
    """Angles from 1e-12 to π − 1e-6: the hard ones plus a log/linear sweep."""
    logs = torch.logspace(-12, 0, 25, dtype=torch.float64).tolist()
    lins = torch.linspace(1.0, math.pi - 1e-6, 25, dtype=torch.float64).tolist()
    extra = [math.pi - d for d in (1e-2, 1e-3, 1e-4, 1e-5, 1e-6)]
    return sorted({*ANGLES_BELOW_PI, *logs, *lins, *extra})


def test_exp_log_round_trip_up_to_pi(dtype, generator):
    angles = _sweep_angles()
    omega = rotation_vectors_with_angles(angles, generator, per_angle=4, dtype=dtype)
    R = so3.exp(omega)
    # log(exp(ω)) = ω ...
    assert _max_err(so3.log(R), omega) <= TOL[dtype]
    # ... and exp(log(R)) = R, with R orthonormal.
    assert _max_err(so3.exp(so3.log(R)), R) <= TOL[dtype]
    RtR = R.transpose(-1, -2) @ R
    assert _max_err(RtR, torch.eye(3, dtype=dtype)) <= TOL[dtype]


def test_exp_log_round_trip_float64_is_1e12_exact(generator):
    # The issue's bound: error ≤ 1e-12 for every angle in [1e-12, π − 1e-6] (float64).
    omega = rotation_vectors_with_angles(_sweep_angles(), generator, per_angle=8)
    errors = (so3.log(so3.exp(omega)) - omega).abs().amax(dim=-1)
    assert float(errors.max()) <= 1e-12


def test_exp_log_at_exactly_pi(dtype, generator):
    # At θ = π both ±ω are valid logs, so check exp(log(R)) = R and |log(R)| = π.
    omega = rotation_vectors_with_angles([math.pi], generator, per_angle=16, dtype=dtype)
    axes_aligned = math.pi * torch.eye(3, dtype=dtype)
    omega = torch.cat((omega, axes_aligned, -axes_aligned))
    R = so3.exp(omega)
    log_R = so3.log(R)
    assert _max_err(so3.exp(log_R), R) <= TOL[dtype]
    assert _max_err(log_R.norm(dim=-1), torch.full_like(log_R[..., 0], math.pi)) <= TOL[dtype]
    # log_R is ±ω.
    sign_err = torch.minimum((log_R - omega).abs().amax(-1), (log_R + omega).abs().amax(-1))
    assert float(sign_err.max()) <= 10 * TOL[dtype]


def test_exp_at_zero_is_identity(dtype):
    omega = torch.zeros(2, 3, dtype=dtype)
    assert torch.equal(so3.exp(omega), torch.eye(3, dtype=dtype).expand(2, 3, 3))
    assert torch.equal(so3.log(torch.eye(3, dtype=dtype)), torch.zeros(3, dtype=dtype))


def test_log_near_pi_issue_2():
    # Rotation by θ = π − 1e-6 about z. pytorch_kinematics 0.10's so3_log_map returns
    # [0, 0, 4.433e-4] here (float32: 4.898e-4): it clamps cos θ and sin θ with eps = 1e-4,
    # so its angle saturates at 3.1345 and the division by the clamped sin θ collapses the
    # result. torchslam's log goes through the quaternion (θ = 2·atan2(|v|, w)) and recovers
    # ω to round-off.
    theta = math.pi - 1e-6
    omega = torch.tensor([[0.0, 0.0, theta]], dtype=torch.float64)
    R = so3.exp(omega)
    ours = so3.log(R)
    assert _max_err(ours, omega) <= 1e-12
    assert abs(float(ours.norm()) - theta) <= 1e-12
    pk = so3_log_map(R)
    # The documented failure, recorded (not asserted, so a fixed pytorch-kinematics passes).
    print(f"pytorch_kinematics so3_log_map at θ = π − 1e-6: {pk.tolist()}; ours: {ours.tolist()}")
    # Same on random axes for a band of angles just below π.
    axes = torch.randn(64, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    axes = axes / axes.norm(dim=-1, keepdim=True)
    angles = math.pi - torch.logspace(-9, -2, 64, dtype=torch.float64)
    omega = axes * angles[:, None]
    assert _max_err(so3.log(so3.exp(omega)), omega) <= 1e-12


# --------------------------------------------------------------------------- group identities


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_inverse_and_compose(shape, dtype, generator):
    R1 = so3.exp(_random_omega(shape, generator, dtype))
    R2 = so3.exp(_random_omega(shape, generator, dtype))
    eye = torch.eye(3, dtype=dtype)
    assert _max_err(R1 @ so3.inverse(R1), eye) <= TOL[dtype]
    assert _max_err(so3.inverse(R1 @ R2), so3.inverse(R2) @ so3.inverse(R1)) <= TOL[dtype]
    omega = _random_omega(shape, generator, dtype)
    # Exp(−ω) = Exp(ω)⁻¹ and Exp(aω) Exp(bω) = Exp((a + b)ω) (one-parameter subgroup).
    assert _max_err(so3.exp(-omega), so3.inverse(so3.exp(omega))) <= TOL[dtype]
    assert _max_err(so3.exp(0.3 * omega) @ so3.exp(0.7 * omega), so3.exp(omega)) <= TOL[dtype]


def test_act_broadcasting(dtype, generator):
    R = so3.exp(_random_omega((4,), generator, dtype))
    points = torch.randn(4, 5, 3, generator=generator, dtype=torch.float64).to(dtype)
    out = so3.act(R[:, None], points)
    assert out.shape == (4, 5, 3)
    expected = torch.einsum("bij,bnj->bni", R, points)
    assert _max_err(out, expected) <= TOL[dtype]
    # One rotation against many points, and many rotations against one point.
    assert so3.act(R[0], points).shape == (4, 5, 3)
    assert so3.act(R, points[0, 0]).shape == (4, 3)
    # Rotation keeps norms.
    assert _max_err(out.norm(dim=-1), points.norm(dim=-1)) <= 10 * TOL[dtype]


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_adjoint_identity(shape, dtype, generator):
    # R Exp(d) Rᵀ = Exp(Ad_R d).
    R = so3.exp(_random_omega(shape, generator, dtype))
    d = _random_omega(shape, generator, dtype)
    Ad = so3.adjoint(R)
    lhs = R @ so3.exp(d) @ so3.inverse(R)
    rhs = so3.exp((Ad @ d[..., None]).squeeze(-1))
    assert _max_err(lhs, rhs) <= TOL[dtype]


def test_jacobian_identities_at_hard_angles(dtype, generator):
    omega = rotation_vectors_with_angles(HARD_ANGLES, generator, per_angle=4, dtype=dtype)
    omega = torch.cat((omega, _random_omega((16,), generator, dtype)))
    eye = torch.eye(3, dtype=dtype)
    Jl, Jr = so3.jl(omega), so3.jr(omega)
    Jl_inv, Jr_inv = so3.jl_inv(omega), so3.jr_inv(omega)
    for J in (Jl, Jr, Jl_inv, Jr_inv):
        assert bool(torch.isfinite(J).all())  # jl_inv is finite at θ = π
    tol = 5 * TOL[dtype]
    # Ad(Exp(ω)) · Jr(ω) = Jl(ω).
    assert _max_err(so3.adjoint(so3.exp(omega)) @ Jr, Jl) <= tol
    # Jr(−ω) = Jl(ω), Jr = Jlᵀ.
    assert _max_err(so3.jr(-omega), Jl) <= tol
    assert _max_err(Jr, Jl.transpose(-1, -2)) <= tol
    # J · J⁻¹ = I, both sides.
    assert _max_err(Jl @ Jl_inv, eye) <= tol
    assert _max_err(Jl_inv @ Jl, eye) <= tol
    assert _max_err(Jr @ Jr_inv, eye) <= tol
    assert _max_err(Jr_inv @ Jr, eye) <= tol
    # Jl(ω) ω = ω (the axis is fixed).
    assert _max_err((Jl @ omega[..., None]).squeeze(-1), omega) <= tol


# --------------------------------------------------------------------------- Jacobians


def _defining_jr(omega):
    return lambda d: so3.log(so3.inverse(so3.exp(omega)) @ so3.exp(omega + d))


def _defining_jl(omega):
    return lambda d: so3.log(so3.exp(omega + d) @ so3.inverse(so3.exp(omega)))


def _defining_jr_inv(omega):
    return lambda d: so3.log(so3.exp(omega) @ so3.exp(d))


def _defining_jl_inv(omega):
    return lambda d: so3.log(so3.exp(d) @ so3.exp(omega))


def _defining_adjoint(R):
    return lambda d: so3.log(R @ so3.exp(d) @ so3.inverse(R))


def _check_against_jacrev_and_central(defining, analytic, inputs, eps, tol_central):
    """For each input x: analytic(x) = jacrev(defining(x))(0) = central differences at 0."""
    zero = inputs.new_zeros(3)
    # jacrev of the defining expression, batched with vmap over the inputs.
    J_jacrev = vmap(lambda x: jacrev(defining(x))(zero))(inputs)
    J_analytic = analytic(inputs)
    assert bool(torch.isfinite(J_jacrev).all())
    assert _max_err(J_jacrev, J_analytic) <= 1e-12
    for x, J in zip(inputs, J_analytic, strict=True):
        J_central = central_difference(defining(x), zero, eps=eps)
        assert _max_err(J_central, J) <= tol_central


def _jacobian_inputs(generator, angles):
    hard = rotation_vectors_with_angles(angles, generator, per_angle=2)
    return torch.cat((hard, _random_omega((6,), generator, torch.float64)))


@pytest.mark.parametrize(
    ("defining", "analytic"),
    [(_defining_jr, so3.jr), (_defining_jl, so3.jl)],
    ids=["jr", "jl"],
)
def test_jacobians_equal_jacrev_and_central_differences(defining, analytic, generator):
    # The result of the defining expression stays near the identity, so θ = π is included.
    inputs = _jacobian_inputs(generator, HARD_ANGLES)
    _check_against_jacrev_and_central(defining, analytic, inputs, eps=1e-6, tol_central=1e-8)


@pytest.mark.parametrize(
    ("defining", "analytic"),
    [(_defining_jr_inv, so3.jr_inv), (_defining_jl_inv, so3.jl_inv)],
    ids=["jr_inv", "jl_inv"],
)
def test_inverse_jacobians_equal_jacrev_and_central_differences(defining, analytic, generator):
    # These differentiate Log at Exp(ω), which jumps (ω → −ω) at θ = π: use θ ≤ π − 1e-6 and
    # a step of 1e-7 so that the central differences never cross π.
    inputs = _jacobian_inputs(generator, ANGLES_BELOW_PI)
    _check_against_jacrev_and_central(defining, analytic, inputs, eps=1e-7, tol_central=1e-7)


def test_adjoint_equals_jacrev_and_central_differences(generator):
    omega = _jacobian_inputs(generator, HARD_ANGLES)
    R = so3.exp(omega)
    _check_against_jacrev_and_central(_defining_adjoint, so3.adjoint, R, eps=1e-6, tol_central=1e-8)


def test_exp_first_order_expansion(generator):
    # Exp(ω + d) ≈ Exp(ω) Exp(jr(ω) d), error O(|d|²).
    omega = rotation_vectors_with_angles(HARD_ANGLES, generator, per_angle=2)
    d = 1e-5 * _random_omega(omega.shape[:1], generator, torch.float64)
    lhs = so3.exp(omega + d)
    rhs = so3.exp(omega) @ so3.exp((so3.jr(omega) @ d[..., None]).squeeze(-1))
    assert _max_err(lhs, rhs) <= 1e-9


# --------------------------------------------------------------------------- autograd


def _angle_points(angles, generator):
    return rotation_vectors_with_angles(angles, generator, per_angle=1)


GRAD_ANGLES = (0.0, 1e-8, math.pi / 2, math.pi - 1e-6)


@pytest.mark.parametrize("fn", [so3.exp, so3.jl, so3.jr, so3.jl_inv, so3.jr_inv], ids=str)
def test_gradcheck_at_zero_and_near_pi(fn, generator):
    for omega in _angle_points((*GRAD_ANGLES, math.pi), generator):
        x = omega.clone().requires_grad_(True)
        assert torch.autograd.gradcheck(fn, (x,))


def test_gradgradcheck_exp_at_zero():
    x = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradgradcheck(so3.exp, (x,))


def test_log_gradients_at_zero_and_near_pi(generator):
    # log is checked as a function of R in the ambient 3×3 space (validation off, since
    # gradcheck's steps leave SO(3)); at θ = π − 1e-6 a step of 1e-8 keeps θ below π.
    for omega in _angle_points(GRAD_ANGLES, generator):
        R = so3.exp(omega).requires_grad_(True)
        with torchslam.validation(False):
            assert torch.autograd.gradcheck(so3.log, (R,), eps=1e-8, atol=1e-6)
    # Along the manifold: d log(exp(ω)) / dω = I, with finite gradients at 0 and near π.
    for omega in _angle_points(GRAD_ANGLES, generator):
        J = torch.autograd.functional.jacobian(lambda w: so3.log(so3.exp(w)), omega)
        assert _max_err(J, EYE) <= 1e-9


@pytest.mark.parametrize("fn", [so3.exp, so3.jl, so3.jr, so3.jl_inv], ids=str)
def test_autograd_equals_central_differences(fn, generator):
    for omega in _angle_points(GRAD_ANGLES, generator):
        J_autograd = torch.autograd.functional.jacobian(fn, omega).reshape(9, 3)
        assert bool(torch.isfinite(J_autograd).all())
        J_central = central_difference(fn, omega, eps=1e-6)
        assert _max_err(J_autograd, J_central) <= 1e-8


# --------------------------------------------------------------------------- shapes, vmap


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_batch_shapes_dtype_device(shape, dtype, device, generator):
    omega = _random_omega(shape, generator, dtype).to(device)
    for fn in (so3.exp, so3.hat, so3.jl, so3.jr, so3.jl_inv, so3.jr_inv):
        out = fn(omega)
        assert out.shape == (*shape, 3, 3)
        assert out.dtype == dtype and out.device == omega.device
    R = so3.exp(omega)
    for fn in (so3.inverse, so3.adjoint, so3.project):
        out = fn(R)
        assert out.shape == (*shape, 3, 3) and out.dtype == dtype and out.device == R.device
    for out in (so3.log(R), so3.vee(so3.hat(omega)), so3.act(R, omega)):
        assert out.shape == (*shape, 3) and out.dtype == dtype and out.device == R.device


def test_empty_batch():
    omega = torch.zeros(0, 3, dtype=torch.float64)
    assert so3.exp(omega).shape == (0, 3, 3)
    assert so3.log(so3.exp(omega)).shape == (0, 3)


def test_functions_run_inside_vmap(generator):
    omega = _random_omega((5,), generator, torch.float64)
    R = so3.exp(omega)
    for fn, x in [
        (so3.exp, omega),
        (so3.log, R),
        (so3.jl, omega),
        (so3.jr, omega),
        (so3.jl_inv, omega),
        (so3.jr_inv, omega),
        (so3.hat, omega),
        (so3.adjoint, R),
    ]:
        assert _max_err(vmap(fn)(x), fn(x)) <= 1e-15
    assert _max_err(vmap(so3.act)(R, omega), so3.act(R, omega)) <= 1e-15


def test_project_returns_nearest_rotation(generator):
    R = so3.exp(_random_omega((8,), generator, torch.float64))
    noisy = R + 1e-3 * torch.randn(8, 3, 3, generator=generator, dtype=torch.float64)
    P = so3.project(noisy)
    assert _max_err(P.transpose(-1, -2) @ P, EYE) <= 1e-13
    assert bool((torch.linalg.det(P) > 0).all())
    assert _max_err(so3.project(R), R) <= 1e-13
    # A reflection is mapped to a proper rotation.
    assert float(torch.linalg.det(so3.project(-R[0]))) == pytest.approx(1.0)


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("fn", "name", "bad_shape"),
    [
        (so3.exp, "omega", (4, 2)),
        (so3.hat, "omega", (3, 4)),
        (so3.jl, "omega", (6,)),
        (so3.jr, "omega", (2, 6)),
        (so3.jl_inv, "omega", (4,)),
        (so3.jr_inv, "omega", (1, 2)),
        (so3.log, "R", (4, 4)),
        (so3.vee, "Omega", (3,)),
        (so3.inverse, "R", (2, 3, 4)),
        (so3.adjoint, "R", (3, 2)),
        (so3.project, "M", (2, 3)),
    ],
)
def test_wrong_shape_names_function_argument_and_shape(fn, name, bad_shape):
    x = torch.zeros(bad_shape, dtype=torch.float64)
    with pytest.raises(ValueError) as info:
        fn(x)
    message = str(info.value)
    assert message.startswith(f"so3.{fn.__name__}: argument '{name}'")
    assert f"got {bad_shape}" in message


def test_wrong_dtype_and_type():
    with pytest.raises(TypeError, match=r"so3\.exp: argument 'omega' must be float32 or float64"):
        so3.exp(torch.zeros(3, dtype=torch.int64))
    with pytest.raises(
        TypeError, match=r"so3\.log: argument 'R' must be a torch\.Tensor, got list"
    ):
        so3.log([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    with pytest.raises(TypeError, match=r"so3\.act: 'R' is torch\.float64 but 'points'"):
        so3.act(torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float32))
    with pytest.raises(
        ValueError, match=r"so3\.act: argument 'points' must have shape \(\.\.\., 3\)"
    ):
        so3.act(torch.eye(3, dtype=torch.float64), torch.zeros(2, 4, dtype=torch.float64))


def test_non_finite_and_non_rotation_rejected():
    omega = torch.zeros(2, 3, dtype=torch.float64)
    omega[1, 2] = float("nan")
    with pytest.raises(ValueError, match=r"so3\.exp: argument 'omega' contains 1 non-finite"):
        so3.exp(omega)
    R = torch.eye(3, dtype=torch.float64).repeat(2, 1, 1)
    R[1] *= 1.01
    with pytest.raises(ValueError, match=r"so3\.log: argument 'R' must hold rotation matrices"):
        so3.log(R)
    reflection = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64))
    with pytest.raises(ValueError, match=r"det = -1"):
        so3.log(reflection)
    R_nan = torch.eye(3, dtype=torch.float64)
    R_nan[0, 0] = float("inf")
    with pytest.raises(ValueError, match=r"so3\.log: argument 'R' contains 1 non-finite"):
        so3.log(R_nan)


def test_validation_false_disables_value_checks():
    R = 1.01 * torch.eye(3, dtype=torch.float64)
    with torchslam.validation(False):
        assert so3.log(R).shape == (3,)
        omega = torch.full((3,), float("nan"), dtype=torch.float64)
        assert bool(torch.isnan(so3.exp(omega)).all())
        # Shape checks stay on.
        with pytest.raises(ValueError, match=r"so3\.log"):
            so3.log(torch.eye(4, dtype=torch.float64))
    with pytest.raises(ValueError):
        so3.log(R)
