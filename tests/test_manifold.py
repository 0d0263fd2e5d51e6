"""Tests of torchslam.manifold: axioms, Jacobians (jacrev, central differences), chain rule."""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor

from tests.helpers import (
    HARD_ANGLES,
    HARD_TRANSLATIONS,
    TOL,
    central_difference,
    random_unit_vectors,
)
from torchslam import validation
from torchslam.lie import se3
from torchslam.manifold import Euclidean, Manifold, SE3Matrix, SE3Tangent, SO3Quaternion

F64 = torch.float64

MANIFOLDS = [
    Euclidean(5),
    SE3Matrix("right"),
    SE3Matrix("left"),
    SO3Quaternion("right"),
    SO3Quaternion("left"),
    SE3Tangent("right"),
    SE3Tangent("left"),
]
IDS = [repr(m) for m in MANIFOLDS]
parametrize_manifold = pytest.mark.parametrize("manifold", MANIFOLDS, ids=IDS)


# --------------------------------------------------------------------------- inputs


def _quaternions(axes: Tensor, angles: Tensor) -> Tensor:
    """Unit quaternions (w, x, y, z) rotating by ``angles`` about unit ``axes``."""
    half = 0.5 * angles[:, None]
    return torch.cat((torch.cos(half), torch.sin(half) * axes), dim=-1)


def _twists(
    angles: tuple[float, ...], translations: tuple[float, ...], generator: torch.Generator
) -> Tensor:
    """Twists over every angle × translation magnitude, two random axes per angle (float64)."""
    axes = random_unit_vectors(2 * len(angles), generator)
    theta = torch.tensor(angles, dtype=F64).repeat_interleave(2)
    omega = axes * theta[:, None]
    rows = []
    for scale in translations:
        v = torch.randn(omega.shape[0], 3, generator=generator, dtype=F64) * scale
        rows.append(torch.cat((omega, v), dim=-1))
    return torch.cat(rows)


def hard_points(
    manifold: Manifold,
    generator: torch.Generator,
    dtype: torch.dtype = F64,
    *,
    include_pi: bool = True,
    max_translation: float = math.inf,
) -> Tensor:
    """Points of ``manifold`` over the hard inputs of tests/helpers.py, shape (N, *point_shape).

    Rotation angles run over HARD_ANGLES (π optional), translations over HARD_TRANSLATIONS (up
    to ``max_translation``); quaternions come with both signs (w < 0 too).
    """
    angles = tuple(a for a in HARD_ANGLES if include_pi or a != math.pi)
    translations = tuple(t for t in HARD_TRANSLATIONS if t <= max_translation)
    if isinstance(manifold, Euclidean):
        scales = torch.tensor(translations, dtype=F64).repeat_interleave(3)
        x = torch.randn(scales.shape[0], manifold.n, generator=generator, dtype=F64)
        x = x * scales[:, None]
    elif isinstance(manifold, SO3Quaternion):
        axes = random_unit_vectors(2 * len(angles), generator)
        theta = torch.tensor(angles, dtype=F64).repeat_interleave(2)
        q = _quaternions(axes, theta)
        x = torch.cat((q, -q))
    else:
        xi = _twists(angles, translations, generator)
        x = se3.exp(xi) if isinstance(manifold, SE3Matrix) else xi
    return x.to(dtype)


def random_points(
    manifold: Manifold, generator: torch.Generator, count: int, dtype: torch.dtype = F64
) -> Tensor:
    """Generic random points (rotation angles in [0, 3] < π), shape (count, *point_shape)."""
    if isinstance(manifold, Euclidean):
        return torch.randn(count, manifold.n, generator=generator, dtype=F64).to(dtype)
    axes = random_unit_vectors(count, generator)
    theta = 3.0 * torch.rand(count, generator=generator, dtype=F64)
    if isinstance(manifold, SO3Quaternion):
        return _quaternions(axes, theta).to(dtype)
    v = 2.0 * torch.randn(count, 3, generator=generator, dtype=F64)
    xi = torch.cat((axes * theta[:, None], v), dim=-1)
    return (se3.exp(xi) if isinstance(manifold, SE3Matrix) else xi).to(dtype)


def random_tangents(
    manifold: Manifold, generator: torch.Generator, count: int, scale: float, dtype=F64
) -> Tensor:
    k = manifold.tangent_size
    return (scale * torch.randn(count, k, generator=generator, dtype=F64)).to(dtype)


def point_scale(manifold: Manifold, x: Tensor) -> Tensor:
    """1 + max |entry| per point, shape (N, 1): absolute tolerances grow with translation."""
    flat = x.reshape(x.shape[0], -1).abs().amax(dim=-1, keepdim=True)
    return 1.0 + flat.to(F64)


def assert_points_close(manifold: Manifold, a: Tensor, b: Tensor, atol: Tensor | float) -> None:
    """Per-point max-abs comparison; quaternions compare up to sign (q ≡ −q)."""
    error = (a - b).reshape(a.shape[0], -1).abs().amax(dim=-1, keepdim=True)
    if isinstance(manifold, SO3Quaternion):
        flipped = (a + b).reshape(a.shape[0], -1).abs().amax(dim=-1, keepdim=True)
        error = torch.minimum(error, flipped)
    bound = torch.as_tensor(atol, dtype=F64)
    assert bool((error.to(F64) <= bound).all()), f"max error {error.max().item():.3g}"


# --------------------------------------------------------------------------- axioms


@parametrize_manifold
def test_sizes(manifold):
    sizes = {
        Euclidean: (5, 5),
        SE3Matrix: (16, 6),
        SO3Quaternion: (4, 3),
        SE3Tangent: (6, 6),
    }[type(manifold)]
    assert (manifold.ambient_size, manifold.tangent_size) == sizes
    assert math.prod(manifold.point_shape) == manifold.ambient_size


@parametrize_manifold
def test_plus_zero_is_identity(manifold, generator, dtype):
    # At |ω| = π exactly, Log(Exp(ξ)) may return −ω: SE3Tangent is checked there separately.
    include_pi = not isinstance(manifold, SE3Tangent)
    huge = math.inf if dtype == F64 else 1.0
    x = hard_points(manifold, generator, dtype, include_pi=include_pi, max_translation=huge)
    zero = x.new_zeros(x.shape[0], manifold.tangent_size)
    y = manifold.plus(x, zero)
    assert y.shape == x.shape and y.dtype == dtype
    assert_points_close(manifold, y, x, TOL[dtype] * point_scale(manifold, x))


@pytest.mark.parametrize("step", [1e-3, 0.3])
@parametrize_manifold
def test_minus_of_plus_is_delta(manifold, generator, dtype, step):
    huge = math.inf if dtype == F64 else 1.0
    x = hard_points(manifold, generator, dtype, max_translation=huge)
    delta = random_tangents(manifold, generator, x.shape[0], step, dtype)
    recovered = manifold.minus(manifold.plus(x, delta), x)
    assert recovered.shape == delta.shape and recovered.dtype == dtype
    error = (recovered - delta).abs().amax(dim=-1, keepdim=True).to(F64)
    assert bool((error <= 10 * TOL[dtype] * point_scale(manifold, x)).all()), error.max()


@parametrize_manifold
def test_plus_of_minus_is_y(manifold, generator, dtype):
    huge = math.inf if dtype == F64 else 1.0
    x = hard_points(manifold, generator, dtype, max_translation=huge)
    y = random_points(manifold, generator, x.shape[0], dtype)
    z = manifold.plus(x, manifold.minus(y, x))
    scale = torch.maximum(point_scale(manifold, x), point_scale(manifold, y))
    assert_points_close(manifold, z, y, 10 * TOL[dtype] * scale)


def test_se3_tangent_at_pi_stays_on_the_group(generator):
    xi = _twists((math.pi,), (0.0, 1.0), generator)
    for manifold in (SE3Tangent("right"), SE3Tangent("left")):
        y = manifold.plus(xi, torch.zeros_like(xi))
        torch.testing.assert_close(se3.exp(y), se3.exp(xi), rtol=0, atol=1e-12)
        assert bool((y[:, :3].norm(dim=-1) - math.pi).abs().max() < 1e-12)


@parametrize_manifold
def test_plus_matches_group_definition(manifold, generator):
    """plus is x·Exp(δ) (right) or Exp(δ)·x (left) on the group, whatever the storage."""
    if isinstance(manifold, Euclidean):
        x = random_points(manifold, generator, 4)
        d = random_tangents(manifold, generator, 4, 0.5)
        torch.testing.assert_close(manifold.plus(x, d), x + d, rtol=0, atol=0)
        return
    x = random_points(manifold, generator, 6)
    d = random_tangents(manifold, generator, 6, 0.5)
    if isinstance(manifold, SO3Quaternion):
        # Compare as rotation matrices: R(q ⊞ δ) = R(q)·Exp(δ) (right) or Exp(δ)·R(q) (left).
        group_x, group_y = _rotation_of(x), _rotation_of(manifold.plus(x, d))
        group_d = se3.exp(torch.cat((d, torch.zeros_like(d)), dim=-1))[..., :3, :3]
    else:
        to_group = se3.exp if isinstance(manifold, SE3Tangent) else (lambda T: T)
        group_x, group_y = to_group(x), to_group(manifold.plus(x, d))
        group_d = se3.exp(d)
    expected = group_x @ group_d if manifold.perturbation == "right" else group_d @ group_x
    torch.testing.assert_close(group_y, expected, rtol=0, atol=1e-12)


def _rotation_of(q: Tensor) -> Tensor:
    """R(q) = (w² − |v|²) I + 2 v vᵀ + 2 w [v]× (valid for unit q; a smooth extension off it)."""
    w, v = q[..., :1, None], q[..., 1:]
    eye = torch.eye(3, dtype=q.dtype, device=q.device)
    x, y, z = v.unbind(-1)
    zero = torch.zeros_like(x)
    skew = torch.stack(
        (
            torch.stack((zero, -z, y), dim=-1),
            torch.stack((z, zero, -x), dim=-1),
            torch.stack((-y, x, zero), dim=-1),
        ),
        dim=-2,
    )
    vv = (v * v).sum(-1)[..., None, None]
    return (w * w - vv) * eye + 2.0 * v[..., :, None] * v[..., None, :] + 2.0 * w * skew


# --------------------------------------------------------------------------- Jacobians


def _jacobian_points(manifold: Manifold, generator: torch.Generator) -> Tensor:
    # SE3Tangent at |ω| = π exactly is not differentiable (Log jumps between ±ω).
    return hard_points(manifold, generator, include_pi=not isinstance(manifold, SE3Tangent))


def _plus_jacobian_by_jacrev(manifold: Manifold, x: Tensor) -> Tensor:
    def one(point: Tensor) -> Tensor:
        zero = point.new_zeros(manifold.tangent_size)
        return torch.func.jacrev(lambda d: manifold.plus(point, d).reshape(-1))(zero)

    return torch.func.vmap(one)(x)


def _minus_jacobian_by_jacrev(manifold: Manifold, x: Tensor) -> Tensor:
    def one(point: Tensor) -> Tensor:
        jac = torch.func.jacrev(lambda y: manifold.minus(y, point))(point)
        return jac.reshape(manifold.tangent_size, manifold.ambient_size)

    return torch.func.vmap(one)(x)


@parametrize_manifold
def test_plus_jacobian_matches_jacrev(manifold, generator):
    x = _jacobian_points(manifold, generator)
    J = manifold.plus_jacobian(x)
    assert J.shape == (x.shape[0], manifold.ambient_size, manifold.tangent_size)
    J_auto = _plus_jacobian_by_jacrev(manifold, x)
    scale = point_scale(manifold, x)[..., None]
    assert bool(((J - J_auto).abs() <= 1e-12 * scale).all()), (J - J_auto).abs().max()


@parametrize_manifold
def test_minus_jacobian_matches_jacrev(manifold, generator):
    x = _jacobian_points(manifold, generator)
    J = manifold.minus_jacobian(x)
    assert J.shape == (x.shape[0], manifold.tangent_size, manifold.ambient_size)
    J_auto = _minus_jacobian_by_jacrev(manifold, x)
    scale = point_scale(manifold, x)[..., None]
    assert bool(((J - J_auto).abs() <= 1e-12 * scale).all()), (J - J_auto).abs().max()


@parametrize_manifold
def test_jacobians_match_central_differences(manifold, generator):
    # One point per hard angle and translation magnitude ≤ 1 (jacrev covers the rest).
    x = _jacobian_points(manifold, generator)
    x = x[point_scale(manifold, x)[:, 0] <= 4.0][::2]
    # SE3Tangent near π: keep the step small enough that Log does not wrap across π.
    eps = 1e-7 if isinstance(manifold, SE3Tangent) else 1e-6
    J_plus = manifold.plus_jacobian(x)
    J_minus = manifold.minus_jacobian(x)
    scale = point_scale(manifold, x)
    zero = x.new_zeros(manifold.tangent_size)
    # Central differences step off the manifold in ambient coordinates: no value checks.
    with validation(False):
        for i in range(x.shape[0]):
            point = x[i]
            fd_plus = central_difference(lambda d, p=point: manifold.plus(p, d), zero, eps)
            fd_minus = central_difference(
                lambda y, p=point: manifold.minus(y.reshape(p.shape), p), point.reshape(-1), eps
            )
            tol = 1e-6 * float(scale[i])
            torch.testing.assert_close(J_plus[i], fd_plus, rtol=0, atol=tol)
            torch.testing.assert_close(J_minus[i], fd_minus, rtol=0, atol=tol)


@parametrize_manifold
def test_minus_jacobian_is_left_inverse_of_plus_jacobian(manifold, generator):
    x = _jacobian_points(manifold, generator)
    product = manifold.minus_jacobian(x) @ manifold.plus_jacobian(x)
    eye = torch.eye(manifold.tangent_size, dtype=F64).expand_as(product)
    torch.testing.assert_close(product, eye, rtol=0, atol=1e-10)


def test_se3_tangent_jacobians_are_the_inverse_lie_jacobians(generator):
    xi = _jacobian_points(SE3Tangent(), generator)
    right, left = SE3Tangent("right"), SE3Tangent("left")
    torch.testing.assert_close(right.plus_jacobian(xi), se3.jr_inv(xi), rtol=0, atol=0)
    torch.testing.assert_close(left.plus_jacobian(xi), se3.jl_inv(xi), rtol=0, atol=0)
    torch.testing.assert_close(right.minus_jacobian(xi), se3.jr(xi), rtol=0, atol=0)
    torch.testing.assert_close(left.minus_jacobian(xi), se3.jl(xi), rtol=0, atol=0)


def test_se3_matrix_right_minus_jacobian_is_pseudo_inverse(generator):
    manifold = SE3Matrix("right")
    T = hard_points(manifold, generator)
    J = manifold.plus_jacobian(T)
    torch.testing.assert_close(manifold.minus_jacobian(T), torch.linalg.pinv(J), rtol=0, atol=1e-10)


# --------------------------------------------------------------------------- the seed's Q_δθ


def _seed_left_matrix(q: Tensor) -> Tensor:
    """[q]_L of the seed (Solà's eq. 18): q ⊗ p = [q]_L p."""
    w, x, y, z = q.unbind(-1)
    rows = [[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]]
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def _seed_right_matrix(q: Tensor) -> Tensor:
    """[q]_R (Solà's eq. 19): p ⊗ q = [q]_R p."""
    w, x, y, z = q.unbind(-1)
    rows = [[w, -x, -y, -z], [x, w, z, -y], [y, -z, w, x], [z, y, -x, w]]
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def _hamilton_product(q: Tensor, p: Tensor) -> Tensor:
    """q ⊗ p from the scalar/vector form (q_w p_w − q_v·p_v, q_w p_v + p_w q_v + q_v × p_v)."""
    qw, qv, pw, pv = q[..., 0], q[..., 1:], p[..., 0], p[..., 1:]
    w = qw * pw - (qv * pv).sum(-1)
    v = qw[..., None] * pv + pw[..., None] * qv + torch.linalg.cross(qv, pv, dim=-1)
    return torch.cat((w[..., None], v), dim=-1)


def test_seed_quaternion_jacobian_q_delta_theta(generator):
    """Seed: Q_δθ = ∂(q ⊗ δq)/∂δθ = [q]_L · ½[0; I₃] is the right-perturbation plus_jacobian."""
    q = hard_points(SO3Quaternion(), generator)
    p = random_points(SO3Quaternion(), generator, q.shape[0])
    # The matrices of the seed really are the Hamilton product.
    torch.testing.assert_close(
        _seed_left_matrix(q) @ p[..., None], _hamilton_product(q, p)[..., None]
    )
    torch.testing.assert_close(
        _seed_right_matrix(q) @ p[..., None], _hamilton_product(p, q)[..., None]
    )

    half_lift = 0.5 * torch.cat((torch.zeros(1, 3, dtype=F64), torch.eye(3, dtype=F64)))  # ½[0; I₃]
    Q_right = _seed_left_matrix(q) @ half_lift
    Q_left = _seed_right_matrix(q) @ half_lift
    torch.testing.assert_close(SO3Quaternion("right").plus_jacobian(q), Q_right, rtol=0, atol=0)
    torch.testing.assert_close(SO3Quaternion("left").plus_jacobian(q), Q_left, rtol=0, atol=0)
    # ... and both equal the derivative of the implemented retraction.
    torch.testing.assert_close(
        _plus_jacobian_by_jacrev(SO3Quaternion("right"), q), Q_right, rtol=0, atol=1e-15
    )
    torch.testing.assert_close(
        _plus_jacobian_by_jacrev(SO3Quaternion("left"), q), Q_left, rtol=0, atol=1e-15
    )


# --------------------------------------------------------------------------- chain rule


def _sample_residual(manifold: Manifold, generator: torch.Generator):
    """A residual r(x) of the stored (ambient) representation, shape (rows,)."""
    p = torch.randn(4, 3, generator=generator, dtype=F64)
    target = torch.randn(4, 3, generator=generator, dtype=F64)
    if isinstance(manifold, Euclidean):
        A = torch.randn(7, manifold.n, generator=generator, dtype=F64)
        return lambda x: torch.cat((A @ x, x * x))
    if isinstance(manifold, SE3Matrix):
        # r(T) = T·p − q for 4 points (seed eq. 1.1 for one frame).
        return lambda T: ((T[:3, :3] @ p.T).T + T[:3, 3] - target).reshape(-1)
    if isinstance(manifold, SO3Quaternion):
        return lambda q: ((_rotation_of(q) @ p.T).T - target).reshape(-1)
    return lambda xi: (se3.act(se3.exp(xi), p) - target).reshape(-1)


@parametrize_manifold
def test_chain_rule_on_sample_residual(manifold, generator):
    """J_rL = J_rG · J_GL: jacrev of r(x ⊞ δ) at δ = 0 equals the ambient Jacobian times J_GL."""
    residual = _sample_residual(manifold, generator)
    x = _jacobian_points(manifold, generator)
    k = manifold.tangent_size

    def ambient(point: Tensor) -> Tensor:
        return torch.func.jacrev(residual)(point).reshape(-1, manifold.ambient_size)

    def tangent(point: Tensor) -> Tensor:
        zero = point.new_zeros(k)
        return torch.func.jacrev(lambda d: residual(manifold.plus(point, d)))(zero)

    J_rG = torch.func.vmap(ambient)(x)
    J_rL = torch.func.vmap(tangent)(x)
    scale = point_scale(manifold, x)[..., None]
    explicit = J_rG @ manifold.plus_jacobian(x)
    structured = manifold.right_multiply_by_plus_jacobian(x, J_rG)
    assert structured.shape == J_rL.shape == (x.shape[0], J_rG.shape[-2], k)
    assert bool(((explicit - J_rL).abs() <= 1e-11 * scale).all()), (explicit - J_rL).abs().max()
    assert bool(((structured - explicit).abs() <= 1e-11 * scale).all())

    # First order on the manifold: r(x ⊞ d) = r(x) + J_rL d + O(|d|²).
    d = random_tangents(manifold, generator, x.shape[0], 1e-5)
    predicted = torch.func.vmap(residual)(x) + (J_rL @ d[..., None]).squeeze(-1)
    actual = torch.func.vmap(residual)(manifold.plus(x, d))
    assert bool(((actual - predicted).abs() <= 1e-8 * scale[..., 0]).all())


@parametrize_manifold
def test_right_multiply_matches_explicit_product_on_random_matrices(manifold, generator):
    x = random_points(manifold, generator, 5)
    J = torch.randn(5, 7, manifold.ambient_size, generator=generator, dtype=F64)
    expected = J @ manifold.plus_jacobian(x)
    torch.testing.assert_close(manifold.right_multiply_by_plus_jacobian(x, J), expected)
    # Leading dims broadcast: one x against a stack of Jacobians, and the other way round.
    out = manifold.right_multiply_by_plus_jacobian(x[0], J)
    torch.testing.assert_close(out, J @ manifold.plus_jacobian(x[0]))
    out = manifold.right_multiply_by_plus_jacobian(x, J[0])
    torch.testing.assert_close(out, J[0] @ manifold.plus_jacobian(x))


# --------------------------------------------------------------------------- batching, torch.func


@pytest.mark.parametrize("batch", [(), (1,), (3, 1, 2)], ids=str)
@parametrize_manifold
def test_batch_shapes_and_broadcasting(manifold, generator, batch):
    count = math.prod(batch)
    ps, k = manifold.point_shape, manifold.tangent_size
    x = random_points(manifold, generator, count).reshape(*batch, *ps)
    d = random_tangents(manifold, generator, count, 0.2).reshape(*batch, k)
    y = manifold.plus(x, d)
    assert y.shape == (*batch, *ps)
    assert manifold.minus(y, x).shape == (*batch, k)
    assert manifold.plus_jacobian(x).shape == (*batch, manifold.ambient_size, k)
    assert manifold.minus_jacobian(x).shape == (*batch, k, manifold.ambient_size)
    flat = manifold.plus(x.reshape(-1, *ps), d.reshape(-1, k)).reshape(y.shape)
    torch.testing.assert_close(y, flat, rtol=0, atol=1e-15)

    # One point against several steps broadcasts like torch.
    steps = random_tangents(manifold, generator, 4, 0.2)
    many = manifold.plus(x.reshape(-1, *ps)[0], steps)
    assert many.shape == (4, *ps)
    torch.testing.assert_close(manifold.minus(many, x.reshape(-1, *ps)[0]), steps)


@parametrize_manifold
def test_vmap_matches_batched_call(manifold, generator):
    x = random_points(manifold, generator, 6)
    d = random_tangents(manifold, generator, 6, 0.2)
    torch.testing.assert_close(torch.func.vmap(manifold.plus)(x, d), manifold.plus(x, d))
    y = manifold.plus(x, d)
    torch.testing.assert_close(torch.func.vmap(manifold.minus)(y, x), manifold.minus(y, x))
    torch.testing.assert_close(
        torch.func.vmap(manifold.plus_jacobian)(x), manifold.plus_jacobian(x)
    )


@parametrize_manifold
def test_gradcheck_plus_and_minus(manifold, generator):
    include_pi = isinstance(manifold, (Euclidean, SE3Matrix))
    x = hard_points(manifold, generator, include_pi=include_pi, max_translation=1.0)[1::13]
    d = random_tangents(manifold, generator, x.shape[0], 0.3)
    y = random_points(manifold, generator, x.shape[0])
    with validation(False):
        assert torch.autograd.gradcheck(
            manifold.plus, (x.clone().requires_grad_(), d.requires_grad_())
        )
        assert torch.autograd.gradcheck(
            manifold.minus, (y.requires_grad_(), x.clone().requires_grad_())
        )


def test_gradients_are_finite_at_identity_and_near_pi():
    """Reverse mode through plus/minus at angle 0 (double-where branches) stays finite."""
    for manifold in MANIFOLDS[1:]:
        x = hard_points(manifold, torch.Generator().manual_seed(1), include_pi=False)
        x = x.clone().requires_grad_()
        d = torch.zeros(x.shape[0], manifold.tangent_size, dtype=F64, requires_grad=True)
        out = manifold.minus(manifold.plus(x, d), x.detach())
        out.sum().backward()
        assert bool(torch.isfinite(x.grad).all()) and bool(torch.isfinite(d.grad).all())


@pytest.mark.parametrize("perturbation", ["right", "left"])
def test_quaternion_minus_at_relative_angle_pi(perturbation):
    """y ⊟ x at a relative rotation of exactly π (w = 0 exactly): angle π, finite gradients."""
    manifold = SO3Quaternion(perturbation)
    x = torch.tensor([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 0, 1.0], [0, 0, 1.0, 0]], dtype=F64)
    y = torch.tensor([[0, 0, 1.0, 0], [0, 0, 1.0, 0], [0, 0, 1.0, 0], [1.0, 0, 0, 0]], dtype=F64)
    y.requires_grad_()
    delta = manifold.minus(y, x)
    torch.testing.assert_close(delta.norm(dim=-1), torch.full((4,), math.pi, dtype=F64))
    delta.sum().backward()
    assert bool(torch.isfinite(y.grad).all())


# --------------------------------------------------------------------------- bad input


def test_bad_shapes_name_method_and_argument():
    T = se3.identity()
    with pytest.raises(ValueError, match=r"SE3Matrix\.plus: argument 'x' must have shape"):
        SE3Matrix().plus(torch.eye(3, dtype=F64), torch.zeros(6, dtype=F64))
    with pytest.raises(ValueError, match=r"SE3Matrix\.plus: argument 'delta' .*\(\.\.\., 6\)"):
        SE3Matrix().plus(T, torch.zeros(3, dtype=F64))
    with pytest.raises(ValueError, match=r"SO3Quaternion\.minus: argument 'x'"):
        SO3Quaternion().minus(torch.tensor([1.0, 0, 0, 0], dtype=F64), torch.zeros(3, dtype=F64))
    with pytest.raises(ValueError, match=r"Euclidean\.plus_jacobian: argument 'x'"):
        Euclidean(3).plus_jacobian(torch.zeros(2, 4, dtype=F64))
    with pytest.raises(
        ValueError, match=r"right_multiply_by_plus_jacobian: argument 'J_r_ambient'"
    ):
        SE3Matrix().right_multiply_by_plus_jacobian(T, torch.zeros(3, 4, 4, dtype=F64))
    with pytest.raises(ValueError, match=r"'J_r_ambient' must have shape \(\.\.\., rows, 16\)"):
        SE3Matrix().right_multiply_by_plus_jacobian(T, torch.zeros(16, dtype=F64))
    with pytest.raises(ValueError, match=r"SE3Tangent\.plus: the leading \(batch\) dims"):
        SE3Tangent().plus(torch.zeros(3, 6, dtype=F64), torch.zeros(4, 6, dtype=F64))


def test_bad_types_and_dtypes():
    with pytest.raises(TypeError, match=r"SE3Matrix\.plus: argument 'x' must be a torch\.Tensor"):
        SE3Matrix().plus([[1.0]], torch.zeros(6, dtype=F64))
    with pytest.raises(
        TypeError, match=r"Euclidean\.plus: argument 'x' must be float32 or float64"
    ):
        Euclidean(3).plus(torch.zeros(3, dtype=torch.int64), torch.zeros(3, dtype=F64))
    with pytest.raises(TypeError, match=r"SO3Quaternion\.plus: 'x' is torch\.float64 but 'delta'"):
        q = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=F64)
        SO3Quaternion().plus(q, torch.zeros(3, dtype=torch.float32))


def test_non_finite_and_off_manifold_values():
    T = se3.identity()
    bad_delta = torch.tensor([0.0, 0, 0, float("nan"), 0, 0], dtype=F64)
    with pytest.raises(
        ValueError, match=r"SE3Matrix\.plus: argument 'delta' contains 1 non-finite"
    ):
        SE3Matrix().plus(T, bad_delta)
    with pytest.raises(ValueError, match=r"Euclidean\.minus: argument 'y' contains"):
        Euclidean(2).minus(torch.tensor([float("inf"), 0.0], dtype=F64), torch.zeros(2, dtype=F64))
    with pytest.raises(ValueError, match=r"SO3Quaternion\.plus: argument 'x' must hold unit"):
        SO3Quaternion().plus(torch.tensor([1.0, 0.1, 0, 0], dtype=F64), torch.zeros(3, dtype=F64))
    scaled = T.clone()
    scaled[:3, :3] *= 1.01
    with pytest.raises(ValueError, match=r"SE3Matrix\.minus: argument 'x' must hold rotation"):
        SE3Matrix().minus(T, scaled)
    bottom = T.clone()
    bottom[3, 0] = 0.5
    with pytest.raises(
        ValueError, match=r"SE3Matrix\.plus_jacobian: argument 'x' must have bottom"
    ):
        SE3Matrix().plus_jacobian(bottom)
    wrapped = torch.tensor([4.0, 0, 0, 0, 0, 0], dtype=F64)
    with pytest.raises(
        ValueError, match=r"SE3Tangent\.plus: argument 'x' must have rotation angle"
    ):
        SE3Tangent().plus(wrapped, torch.zeros(6, dtype=F64))
    # Value checks cost a reduction; validation(False) switches them off (shape checks stay).
    with validation(False):
        SO3Quaternion().plus(torch.tensor([1.0, 0.1, 0, 0], dtype=F64), torch.zeros(3, dtype=F64))


def test_bad_constructor_arguments():
    with pytest.raises(ValueError, match=r"SE3Matrix: argument 'perturbation' must be 'right'"):
        SE3Matrix("up")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"SO3Quaternion: argument 'perturbation'"):
        SO3Quaternion(perturbation="Right")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"SE3Tangent: argument 'perturbation'"):
        SE3Tangent(perturbation=None)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"Euclidean: argument 'n' must be positive"):
        Euclidean(0)
    with pytest.raises(TypeError, match=r"Euclidean: argument 'n' must be an int"):
        Euclidean(2.0)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"Euclidean: argument 'n' must be an int"):
        Euclidean(True)
