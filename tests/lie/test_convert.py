"""Conversions: rotation matrix ⇄ quaternion (w, x, y, z) ⇄ axis-angle, poses, Transform3d."""

from __future__ import annotations

import math

import pytest
import torch
from pytorch_kinematics import transforms as pk
from torch.func import vmap

import torchslam
from tests.helpers import HARD_ANGLES, TOL, rotation_vectors_with_angles
from torchslam.lie import convert, se3, so3

BATCH_SHAPES = [(), (1,), (3, 1, 2)]


def _max_err(a, b) -> float:
    return float((a - b).abs().max())


def _random_unit_quaternions(shape, generator, dtype=torch.float64):
    q = torch.randn(*shape, 4, generator=generator, dtype=torch.float64)
    return (q / q.norm(dim=-1, keepdim=True)).to(dtype)


def _quaternion_close(a, b, tol) -> bool:
    """q ≡ −q: compare up to sign, per quaternion."""
    err = torch.minimum((a - b).abs().amax(-1), (a + b).abs().amax(-1))
    return float(err.max()) <= tol


def _hamilton_product(a, b):
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


# --------------------------------------------------------------------------- conventions


def test_quaternion_order_is_w_first_hamilton():
    # A rotation by θ about z is (cos θ/2, 0, 0, sin θ/2) in (w, x, y, z).
    theta = 0.7
    q = torch.tensor([math.cos(theta / 2), 0.0, 0.0, math.sin(theta / 2)], dtype=torch.float64)
    R = convert.quaternion_to_matrix(q)
    c, s = math.cos(theta), math.sin(theta)
    expected = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    assert _max_err(R, expected) <= 1e-15
    assert _max_err(convert.matrix_to_quaternion(expected), q) <= 1e-15
    omega = torch.tensor([0.0, 0.0, theta], dtype=torch.float64)
    assert _max_err(convert.axis_angle_to_quaternion(omega), q) <= 1e-15
    assert _max_err(convert.quaternion_to_axis_angle(q), omega) <= 1e-15


def test_hamilton_product_composes_like_matrices(generator):
    # Hamilton convention: R(q1 ⊗ q2) = R(q1) R(q2) (JPL would give the reverse order).
    q1, q2 = _random_unit_quaternions((2, 8), generator)
    lhs = convert.quaternion_to_matrix(_hamilton_product(q1, q2))
    rhs = convert.quaternion_to_matrix(q1) @ convert.quaternion_to_matrix(q2)
    assert _max_err(lhs, rhs) <= 1e-14


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_quaternion_matrix_round_trip(shape, dtype, generator):
    q = _random_unit_quaternions(shape, generator, dtype)
    R = convert.quaternion_to_matrix(q)
    assert R.shape == (*shape, 3, 3) and R.dtype == dtype
    q_back = convert.matrix_to_quaternion(R)
    assert q_back.shape == (*shape, 4) and q_back.dtype == dtype
    assert _quaternion_close(q_back, q, 5 * TOL[dtype])
    assert bool((q_back[..., 0] >= 0).all())
    assert _max_err(convert.quaternion_to_matrix(q_back), R) <= 5 * TOL[dtype]


def test_sign_ambiguity(generator, dtype):
    # q and −q are the same rotation; conversions return the w ≥ 0 representative.
    q = _random_unit_quaternions((16,), generator, dtype)
    assert (
        _max_err(convert.quaternion_to_matrix(-q), convert.quaternion_to_matrix(q)) <= (TOL[dtype])
    )
    omega_pos = convert.quaternion_to_axis_angle(q)
    omega_neg = convert.quaternion_to_axis_angle(-q)
    assert _max_err(omega_pos, omega_neg) <= TOL[dtype]
    assert float(omega_pos.norm(dim=-1).max()) <= math.pi + TOL[dtype]
    q_canonical = convert.matrix_to_quaternion(convert.quaternion_to_matrix(-q))
    assert bool((q_canonical[..., 0] >= 0).all())
    assert _quaternion_close(q_canonical, q, 5 * TOL[dtype])


def test_axis_angle_agrees_with_so3_exp_at_hard_angles(dtype, generator):
    omega = rotation_vectors_with_angles(HARD_ANGLES, generator, per_angle=4, dtype=dtype)
    R = so3.exp(omega)
    q = convert.axis_angle_to_quaternion(omega)
    assert _max_err(q.norm(dim=-1), torch.ones_like(q[..., 0])) <= TOL[dtype]
    assert _max_err(convert.quaternion_to_matrix(q), R) <= TOL[dtype]
    assert torch.equal(convert.axis_angle_to_matrix(omega), R)
    assert torch.equal(convert.matrix_to_axis_angle(R), so3.log(R))
    # Round trip ω → q → ω, exact below π; at π only up to sign.
    omega_back = convert.quaternion_to_axis_angle(q)
    below_pi = omega.double().norm(dim=-1) < math.pi - 1e-7
    assert _max_err(omega_back[below_pi], omega[below_pi]) <= TOL[dtype]
    at_pi = ~below_pi
    sign_err = torch.minimum(
        (omega_back[at_pi] - omega[at_pi]).abs().amax(-1),
        (omega_back[at_pi] + omega[at_pi]).abs().amax(-1),
    )
    assert float(sign_err.max()) <= 10 * TOL[dtype]
    # Through the matrix: q → R → q.
    assert _quaternion_close(convert.matrix_to_quaternion(R), q, 5 * TOL[dtype])


def test_quaternion_to_axis_angle_exact_for_tiny_and_near_pi():
    omega = rotation_vectors_with_angles(
        (1e-12, 1e-8, math.pi - 1e-6), torch.Generator().manual_seed(5), per_angle=4
    )
    q = convert.axis_angle_to_quaternion(omega)
    assert _max_err(convert.quaternion_to_axis_angle(q), omega) <= 1e-15


def test_agrees_with_pytorch_kinematics_values(generator):
    # pytorch-kinematics computes the same values away from the identity (its weakness is
    # gradients at the identity, tested below).
    omega = rotation_vectors_with_angles((0.3, 1.0, 2.5), generator, per_angle=4)
    q_ours = convert.axis_angle_to_quaternion(omega)
    assert _max_err(pk.axis_angle_to_quaternion(omega), q_ours) <= 1e-15
    R = so3.exp(omega)
    assert _quaternion_close(pk.matrix_to_quaternion(R), convert.matrix_to_quaternion(R), 1e-15)
    assert _max_err(pk.quaternion_to_axis_angle(q_ours), omega) <= 1e-14


# --------------------------------------------------------------------------- gradients


def test_gradients_finite_at_identity():
    # pytorch-kinematics' matrix_to_quaternion / axis-angle conversions give NaN gradients here;
    # ours must not.
    omega = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(convert.axis_angle_to_quaternion, (omega,))
    q = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64, requires_grad=True)
    with torchslam.validation(False):  # gradcheck's steps leave the unit sphere
        assert torch.autograd.gradcheck(convert.quaternion_to_axis_angle, (q,))
        R = torch.eye(3, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(convert.matrix_to_quaternion, (R,))
        assert torch.autograd.gradcheck(convert.quaternion_to_matrix, (q,))
    # d(q → ω)/dq at the identity along the sphere's tangent is [0 | 2I].
    J = torch.autograd.functional.jacobian(convert.quaternion_to_axis_angle, q.detach())
    assert _max_err(J[:, 1:], 2 * torch.eye(3, dtype=torch.float64)) <= 1e-15


def test_gradients_near_pi(generator):
    omega = rotation_vectors_with_angles((math.pi - 1e-6,), generator, per_angle=2)
    for w in omega:
        x = w.clone().requires_grad_(True)
        assert torch.autograd.gradcheck(convert.axis_angle_to_quaternion, (x,))
        J = torch.autograd.functional.jacobian(
            lambda v: convert.quaternion_to_axis_angle(convert.axis_angle_to_quaternion(v)), w
        )
        assert _max_err(J, torch.eye(3, dtype=torch.float64)) <= 1e-9


def test_vmap_compatible(generator):
    q = _random_unit_quaternions((5,), generator)
    for fn, x in [
        (convert.quaternion_to_matrix, q),
        (convert.quaternion_to_axis_angle, q),
        (convert.axis_angle_to_quaternion, q[:, 1:]),
        (convert.matrix_to_quaternion, convert.quaternion_to_matrix(q)),
    ]:
        assert _max_err(vmap(fn)(x), fn(x)) <= 1e-15


# --------------------------------------------------------------------------- poses


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_pose_translation_quaternion_round_trip(shape, dtype, generator):
    t = torch.randn(*shape, 3, generator=generator, dtype=torch.float64).to(dtype)
    q = _random_unit_quaternions(shape, generator, dtype)
    T = convert.pose_from_translation_quaternion(t, q)
    assert T.shape == (*shape, 4, 4) and T.dtype == dtype
    assert torch.equal(T[..., :3, 3], t)
    assert _max_err(T[..., :3, :3], convert.quaternion_to_matrix(q)) <= TOL[dtype]
    t_back, q_back = convert.pose_to_translation_quaternion(T)
    assert torch.equal(t_back, t)
    assert _quaternion_close(q_back, q, 5 * TOL[dtype])
    # A valid pose for se3.
    assert se3.log(T).shape == (*shape, 6)


def test_pose_from_translation_quaternion_broadcasts(generator):
    t = torch.randn(4, 3, generator=generator, dtype=torch.float64)
    q = _random_unit_quaternions((), generator)
    T = convert.pose_from_translation_quaternion(t, q)
    assert T.shape == (4, 4, 4)
    assert _max_err(T[:, :3, :3], convert.quaternion_to_matrix(q).expand(4, 3, 3)) == 0.0


# --------------------------------------------------------------------------- Transform3d


def test_transform3d_stores_column_vector_matrix(generator):
    # Checked numerically: Transform3d's matrix is T itself (not the transpose), so
    # transform_points(p) = R p + t = se3.act(T, p).
    xi = torch.randn(6, generator=generator, dtype=torch.float64)
    T = se3.exp(xi)
    t3d = pk.Transform3d(matrix=T)
    points = torch.randn(7, 3, generator=generator, dtype=torch.float64)
    assert _max_err(t3d.transform_points(points), se3.act(T, points)) <= 1e-14
    assert torch.equal(t3d.get_matrix()[0], T)


@pytest.mark.parametrize("shape", [(), (1,), (5,), (3, 1, 2)])
def test_transform3d_round_trip_and_transform_points(shape, dtype, generator):
    xi = torch.randn(*shape, 6, generator=generator, dtype=torch.float64).to(dtype)
    T = se3.exp(xi)
    t3d = convert.to_transform3d(T)
    n = math.prod(shape)
    assert isinstance(t3d, pk.Transform3d) and len(t3d) == n and t3d.dtype == dtype
    T_back = convert.from_transform3d(t3d)
    assert T_back.shape == (n, 4, 4) and T_back.dtype == dtype
    assert torch.equal(T_back.reshape(T.shape), T)
    # transform_points agrees with se3.act, pose by pose.
    points = torch.randn(n, 9, 3, generator=generator, dtype=torch.float64).to(dtype)
    expected = se3.act(T.reshape(n, 1, 4, 4), points)
    assert _max_err(t3d.transform_points(points), expected) <= 10 * TOL[dtype]
    # Composition agrees: Transform3d.compose multiplies matrices in the same order.
    composed = convert.from_transform3d(t3d.compose(t3d.inverse()))
    assert _max_err(composed, torch.eye(4, dtype=dtype).expand(n, 4, 4)) <= 10 * TOL[dtype]


def test_from_transform3d_built_by_pytorch_kinematics(generator):
    # A Transform3d built from (rot = quaternion w-first, pos) gives the same pose as ours.
    q = _random_unit_quaternions((3,), generator)
    t = torch.randn(3, 3, generator=generator, dtype=torch.float64)
    t3d = pk.Transform3d(rot=q, pos=t, dtype=torch.float64)
    T = convert.from_transform3d(t3d)
    assert _max_err(T, convert.pose_from_translation_quaternion(t, q)) <= 1e-15


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("fn", "name", "bad_shape"),
    [
        (convert.quaternion_to_matrix, "q", (3,)),
        (convert.quaternion_to_axis_angle, "q", (2, 5)),
        (convert.matrix_to_quaternion, "R", (4, 4)),
        (convert.axis_angle_to_quaternion, "omega", (4,)),
        (convert.axis_angle_to_matrix, "omega", (2, 2)),
        (convert.matrix_to_axis_angle, "R", (3,)),
        (convert.pose_to_translation_quaternion, "T", (3, 4)),
        (convert.to_transform3d, "T", (2, 3, 3)),
    ],
)
def test_wrong_shape_names_function_argument_and_shape(fn, name, bad_shape):
    with pytest.raises(ValueError) as info:
        fn(torch.zeros(bad_shape, dtype=torch.float64))
    message = str(info.value)
    assert message.startswith(f"convert.{fn.__name__}: argument '{name}'")
    assert f"got {bad_shape}" in message


def test_bad_types_and_values_rejected():
    with pytest.raises(TypeError, match=r"convert\.quaternion_to_matrix: argument 'q'"):
        convert.quaternion_to_matrix(torch.tensor([1, 0, 0, 0]))
    with pytest.raises(TypeError, match=r"convert\.from_transform3d: argument 'transform'"):
        convert.from_transform3d(torch.eye(4))
    with pytest.raises(ValueError, match=r"must hold unit quaternions.*\|q\| = 2"):
        convert.quaternion_to_matrix(torch.tensor([2.0, 0.0, 0.0, 0.0], dtype=torch.float64))
    with pytest.raises(ValueError, match=r"convert\.quaternion_to_axis_angle.*non-finite"):
        convert.quaternion_to_axis_angle(torch.full((4,), float("nan"), dtype=torch.float64))
    with pytest.raises(ValueError, match=r"convert\.matrix_to_quaternion: .*rotation matrices"):
        convert.matrix_to_quaternion(2 * torch.eye(3, dtype=torch.float64))
    with pytest.raises(TypeError, match=r"'t' is torch\.float64 but 'q' is torch\.float32"):
        convert.pose_from_translation_quaternion(
            torch.zeros(3, dtype=torch.float64), torch.tensor([1.0, 0.0, 0.0, 0.0])
        )
    # A scaled Transform3d is not a rigid pose.
    scaled = pk.Transform3d(dtype=torch.float64).scale(2.0)
    with pytest.raises(ValueError, match=r"convert\.from_transform3d: argument 'transform'"):
        convert.from_transform3d(scaled)
    bad_bottom = se3.identity()
    bad_bottom[3, 0] = 1.0
    with pytest.raises(ValueError, match=r"convert\.to_transform3d: .*bottom row"):
        convert.to_transform3d(bad_bottom)


def test_validation_false_skips_unit_norm_check():
    q = torch.tensor([2.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    with torchslam.validation(False):
        # Documented: quaternion_to_matrix then uses q / |q|.
        assert _max_err(convert.quaternion_to_matrix(q), torch.eye(3, dtype=torch.float64)) == 0


def test_quaternion_log_second_derivatives_are_finite_and_exact_at_the_identity():
    # The angle is read from |v|², never |v| (whose derivative is 0/0 at v = 0): the double
    # backward of quaternion → rotation vector, and of SO3Quaternion.minus, is finite at the
    # identity and equals the exact Hessian of the test function.
    from torchslam import manifold

    omega = torch.tensor([1e-300, 0.0, 0.0], dtype=torch.float64)
    for f in (
        lambda x: convert.quaternion_to_axis_angle(convert.axis_angle_to_quaternion(x)),
        lambda x: manifold.SO3Quaternion().minus(
            manifold.SO3Quaternion().plus(
                torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64), x
            ),
            torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64),
        ),
    ):
        for x0 in (torch.zeros(3, dtype=torch.float64), omega):
            # f(x) = x near 0, so ½|f(x)|² has Hessian I.
            H = torch.autograd.functional.hessian(lambda x, f=f: 0.5 * f(x).square().sum(), x0)
            assert torch.isfinite(H).all()
            torch.testing.assert_close(H, torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-12)


# --------------------------------------------------------------------------- quaternion algebra


@pytest.mark.parametrize("shape", BATCH_SHAPES, ids=str)
def test_quaternion_algebra_matches_rotation_matrices(shape, generator):
    q = _random_unit_quaternions(shape, generator)
    p = _random_unit_quaternions(shape, generator)
    R = convert.quaternion_to_matrix
    # Products of O(1) entries: round-off ~1e-16 per operation.
    assert _max_err(R(convert.quaternion_multiply(q, p)), R(q) @ R(p)) <= 1e-14
    assert _max_err(convert.quaternion_multiply(q, p), _hamilton_product(q, p)) <= 1e-15
    assert _max_err(R(convert.quaternion_conjugate(q)), R(q).transpose(-1, -2)) <= 1e-14
    left = (convert.quaternion_product_matrix(q, "left") @ p[..., None])[..., 0]
    right = (convert.quaternion_product_matrix(p, "right") @ q[..., None])[..., 0]
    assert _max_err(left, convert.quaternion_multiply(q, p)) <= 1e-15
    assert _max_err(right, convert.quaternion_multiply(q, p)) <= 1e-15


def test_quaternion_multiply_broadcasts_and_names_itself():
    q = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    p = torch.randn(3, 2, 4, dtype=torch.float64)
    assert torch.equal(convert.quaternion_multiply(q, p), p)
    with pytest.raises(ValueError, match=r"convert\.quaternion_multiply: argument 'p' must have"):
        convert.quaternion_multiply(q, p[..., :3])
    with pytest.raises(ValueError, match=r"convert\.quaternion_multiply: the leading \(batch\)"):
        convert.quaternion_multiply(p, torch.zeros(4, 4, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"quaternion_product_matrix: argument 'side' must be"):
        convert.quaternion_product_matrix(q, "up")


def test_one_quaternion_log_for_so3_log_and_the_quaternion_manifold(generator):
    # so3.log is the quaternion route (Shepperd, then θ = 2·atan2(|v|, w)); the same bits.
    omega = rotation_vectors_with_angles(HARD_ANGLES, generator)
    R = so3.exp(omega)
    route = convert.quaternion_to_axis_angle(convert.matrix_to_quaternion(R))
    assert torch.equal(so3.log(R), route)
    # q ≡ −q: both signs give the angle ≤ π, exactly the same vector.
    q = convert.axis_angle_to_quaternion(omega)
    assert torch.equal(convert.quaternion_to_axis_angle(-q), convert.quaternion_to_axis_angle(q))
    # θ → π: w = cos(θ/2) ≈ 5e-7; atan2 keeps the angle to round-off (an acos of w would not).
    near_pi = rotation_vectors_with_angles((math.pi - 1e-6,), generator)
    back = convert.quaternion_to_axis_angle(convert.axis_angle_to_quaternion(near_pi))
    assert _max_err(back, near_pi) <= 4e-15
