"""Seeded fuzz of the public Lie-group, conversion and manifold surface, and the boundary fixes.

Every public function of ``torchslam.lie.so3``, ``se3``, ``convert`` and every public method of
the ``torchslam.manifold`` classes is called with malformed arguments: wrong Python types,
integer / half / complex tensors, wrong trailing shapes, mismatched batch dims, mixed dtypes,
NaN/Inf, huge (1e300; 1e38 in float32) and tiny (1e-300; 1e-40 in float32) values,
non-rotations, scaled rotations, reflections and non-unit quaternions. The contract (the
project's developer notes): a ValueError/TypeError whose message names the function and the
argument, or, for finite input, a finite result. Inputs that the documentation says are
checked (rotations, rigid transforms, unit quaternions, non-finite values) must raise.

The targeted tests below pin each reported failure (rotation checks that let 1e300·R pass,
NaN from exp of 1e300, unchecked NaN, non-inverses of non-rigid input, torch errors for
mismatched batches and negative sizes, the |q| message).
"""

from __future__ import annotations

import math
import random
import re
from collections.abc import Callable
from dataclasses import dataclass

import pytest
import torch
from pytorch_kinematics.transforms import Transform3d
from torch import Tensor

import torchslam
from torchslam import manifold as mf
from torchslam.lie import convert, se3, so3

F64, F32 = torch.float64, torch.float32
HUGE = {F64: 1e300, F32: 1e38}
TINY = {F64: 1e-300, F32: 1e-40}  # float32: a subnormal

# ----------------------------------------------------------------------------- the API table

# Argument kinds: vec3 (rotation vectors, points), vec4 (any quaternion), twist (…, 6), mat3 /
# mat4 (any matrix), rot (a rotation), pose (a rigid transform), quat (a unit quaternion), t3d
# (a Transform3d); manifold kinds are resolved per manifold (point, tangent, jac).
STRICT_KINDS = {"rot", "pose", "quat"}


@dataclass(frozen=True)
class Api:
    name: str  # as it must appear in messages, e.g. "so3.exp" or "SE3Matrix.plus"
    call: Callable
    args: tuple[tuple[str, str], ...]  # (argument name, kind)
    manifold: mf.Manifold | None = None


_LIE_ARGS: dict[str, tuple[tuple[str, str], ...]] = {
    "so3.act": (("R", "rot"), ("points", "vec3")),
    "so3.adjoint": (("R", "rot"),),
    "so3.exp": (("omega", "vec3"),),
    "so3.hat": (("omega", "vec3"),),
    "so3.inverse": (("R", "rot"),),
    "so3.jl": (("omega", "vec3"),),
    "so3.jl_inv": (("omega", "vec3"),),
    "so3.jr": (("omega", "vec3"),),
    "so3.jr_inv": (("omega", "vec3"),),
    "so3.log": (("R", "rot"),),
    "so3.project": (("M", "mat3"),),
    "so3.vee": (("Omega", "mat3"),),
    "se3.act": (("T", "pose"), ("points", "vec3")),
    "se3.adjoint": (("T", "pose"),),
    "se3.compose": (("T1", "pose"), ("T2", "pose")),
    "se3.exp": (("xi", "twist"),),
    "se3.from_rotation_translation": (("R", "rot"), ("t", "vec3")),
    "se3.hat": (("xi", "twist"),),
    "se3.inverse": (("T", "pose"),),
    "se3.jl": (("xi", "twist"),),
    "se3.jl_inv": (("xi", "twist"),),
    "se3.jr": (("xi", "twist"),),
    "se3.jr_inv": (("xi", "twist"),),
    "se3.log": (("T", "pose"),),
    "se3.vee": (("Xi", "mat4"),),
    "convert.axis_angle_to_matrix": (("omega", "vec3"),),
    "convert.axis_angle_to_quaternion": (("omega", "vec3"),),
    "convert.from_transform3d": (("transform", "t3d"),),
    "convert.matrix_to_axis_angle": (("R", "rot"),),
    "convert.matrix_to_quaternion": (("R", "rot"),),
    "convert.pose_from_translation_quaternion": (("t", "vec3"), ("q", "quat")),
    "convert.pose_to_translation_quaternion": (("T", "pose"),),
    "convert.quaternion_conjugate": (("q", "vec4"),),
    "convert.quaternion_multiply": (("q", "vec4"), ("p", "vec4")),
    "convert.quaternion_product_matrix": (("q", "vec4"),),
    "convert.quaternion_to_axis_angle": (("q", "quat"),),
    "convert.quaternion_to_matrix": (("q", "quat"),),
    "convert.to_transform3d": (("T", "pose"),),
}
_MODULES = {"so3": so3, "se3": se3, "convert": convert}
# se3.identity takes sizes and keywords, fuzzed separately below.
_NOT_TENSOR_FUNCTIONS = {"se3.identity"}

MANIFOLDS = [
    mf.Euclidean(3),
    mf.Euclidean(1),
    mf.SE3Matrix(),
    mf.SE3Matrix("left"),
    mf.SO3Quaternion(),
    mf.SO3Quaternion("left"),
    mf.SE3Tangent(),
    mf.SE3Tangent("left"),
]
_METHOD_ARGS = {
    "plus": (("x", "point"), ("delta", "tangent")),
    "minus": (("y", "point"), ("x", "point")),
    "plus_jacobian": (("x", "point"),),
    "minus_jacobian": (("x", "point"),),
    "right_multiply_by_plus_jacobian": (("x", "point"), ("J_r_ambient", "jac")),
}


def _apis() -> list[Api]:
    apis = []
    for name, args in _LIE_ARGS.items():
        module, function = name.split(".")
        apis.append(Api(name, getattr(_MODULES[module], function), args))
    for manifold in MANIFOLDS:
        for method, args in _METHOD_ARGS.items():
            apis.append(
                Api(
                    f"{type(manifold).__name__}.{method}", getattr(manifold, method), args, manifold
                )
            )
    return apis


APIS = _apis()


def test_the_table_covers_the_whole_public_surface():
    for module_name, module in _MODULES.items():
        public = {f"{module_name}.{f}" for f in module.__all__}
        assert public == {n for n in _LIE_ARGS if n.startswith(module_name + ".")} | (
            public & _NOT_TENSOR_FUNCTIONS
        )
    public_methods = {
        n for n in vars(mf.Manifold) if not n.startswith("_") and callable(vars(mf.Manifold)[n])
    }
    assert public_methods == set(_METHOD_ARGS)
    classes = {getattr(mf, n) for n in mf.__all__ if isinstance(getattr(mf, n), type)}
    assert {type(m) for m in MANIFOLDS} == classes - {mf.Manifold}


# ----------------------------------------------------------------------------- valid inputs


def _randn(rng: random.Random, shape, dtype) -> Tensor:
    g = torch.Generator().manual_seed(rng.randrange(2**31))
    return torch.randn(*shape, generator=g, dtype=F64).to(dtype)


def _rotations(rng, batch, dtype) -> Tensor:
    return so3._exp(_randn(rng, (*batch, 3), F64)).to(dtype)  # unchecked: fast and valid


def _point_kind(manifold: mf.Manifold) -> str:
    return {
        mf.Euclidean: "vec",
        mf.SE3Matrix: "pose",
        mf.SO3Quaternion: "quat",
        mf.SE3Tangent: "principal_twist",
    }[type(manifold)]


def _resolve(kind: str, manifold: mf.Manifold | None) -> str:
    if kind == "point":
        return _point_kind(manifold)
    return kind


def _valid(kind: str, batch, dtype, rng, manifold=None):
    if kind == "vec3":
        return _randn(rng, (*batch, 3), dtype)
    if kind == "twist":
        return _randn(rng, (*batch, 6), dtype)
    if kind == "mat3":
        return _randn(rng, (*batch, 3, 3), dtype)
    if kind == "mat4":
        return _randn(rng, (*batch, 4, 4), dtype)
    if kind == "rot":
        return _rotations(rng, batch, dtype)
    if kind == "pose":
        return se3._exp(_randn(rng, (*batch, 6), F64)).to(dtype)
    if kind == "vec4":  # any quaternion
        return _randn(rng, (*batch, 4), dtype)
    if kind == "quat":
        q = _randn(rng, (*batch, 4), F64)
        return (q / q.norm(dim=-1, keepdim=True)).to(dtype)
    if kind == "t3d":
        T = _valid("pose", batch or (1,), dtype, rng)
        return Transform3d(matrix=T.reshape(-1, 4, 4), dtype=dtype)
    if kind == "vec":
        return _randn(rng, (*batch, manifold.point_shape[0]), dtype)
    if kind == "principal_twist":
        axis = _randn(rng, (*batch, 3), F64)
        axis = axis / axis.norm(dim=-1, keepdim=True)
        angle = 3.0 * torch.rand(*batch, 1, generator=torch.Generator().manual_seed(7), dtype=F64)
        return torch.cat((axis * angle, _randn(rng, (*batch, 3), F64)), dim=-1).to(dtype)
    if kind == "tangent":
        return 0.5 * _randn(rng, (*batch, manifold.tangent_size), dtype)
    if kind == "jac":
        return _randn(rng, (*batch, 2, manifold.ambient_size), dtype)
    raise AssertionError(kind)


# ----------------------------------------------------------------------------- malformations
# Each returns (bad value, expectation): "type" → TypeError, "value" → ValueError, "either" →
# ValueError/TypeError naming the function and argument, or a finite result.


def _set_entry(x: Tensor, rng: random.Random, value: float) -> tuple[Tensor, int]:
    x = x.clone()
    flat = x.view(-1)
    i = rng.randrange(flat.numel())
    flat[i] = value
    return x, i


def _in_translation(kind: str, x: Tensor, i: int) -> bool:
    """Whether flat index i of a pose (…, 4, 4) lies in its translation column."""
    r, c = divmod(i % 16, 4)
    return kind == "pose" and c == 3 and r < 3


def _strict(kind):
    return "value" if kind in STRICT_KINDS else "either"


# Malformations of the value of a tensor; for a Transform3d they apply to its matrix.
TYPE_LEVEL = {
    "python_list",
    "python_int",
    "none",
    "int_tensor",
    "float16",
    "complex",
    "trailing_shape",
    "scalar",
}


def _m_python_list(x, kind, dtype, rng):
    return (x.tolist() if isinstance(x, Tensor) else [1.0, 2.0]), "type"


def _m_int(x, kind, dtype, rng):
    return 3, "type"


def _m_none(x, kind, dtype, rng):
    return None, "type"


def _m_int_tensor(x, kind, dtype, rng):
    return torch.ones(3, dtype=torch.int64), "type"


def _m_half(x, kind, dtype, rng):
    return (x.get_matrix() if kind == "t3d" else x).to(torch.float16), "type"


def _m_complex(x, kind, dtype, rng):
    return (x.get_matrix() if kind == "t3d" else x).to(torch.complex128), "type"


def _m_trailing(x, kind, dtype, rng):
    if kind == "t3d":
        return torch.eye(3, dtype=dtype), "type"
    if rng.random() < 0.5:
        return x[..., :-1], "value"
    return torch.cat((x, x[..., :1]), dim=-1), "value"


def _m_scalar(x, kind, dtype, rng):
    return torch.tensor(1.0, dtype=dtype), "type" if kind == "t3d" else "value"


def _non_finite(value):
    def malform(x, kind, dtype, rng):
        return _set_entry(x, rng, value)[0], "value"

    return malform


def _m_huge_entry(x, kind, dtype, rng):
    bad, i = _set_entry(x, rng, HUGE[dtype] * rng.choice((1.0, -1.0)))
    return bad, "either" if _in_translation(kind, x, i) else _strict(kind)


def _scaled(factor):
    def malform(x, kind, dtype, rng):
        return x * factor[dtype], _strict(kind)

    return malform


def _m_scaled_rotation(x, kind, dtype, rng):
    if kind == "rot" or kind == "quat":
        return x * 1.5, "value"
    if kind == "pose":
        x = x.clone()
        x[..., :3, :3] *= 0.5
        return x, "value"
    return x * 1.5, "either"


def _m_non_rotation(x, kind, dtype, rng):
    if kind == "rot":
        return _randn(rng, x.shape, dtype), "value"
    if kind == "pose":
        x = x.clone()
        x[..., :3, :3] = _randn(rng, x[..., :3, :3].shape, dtype)
        return x, "value"
    if kind == "quat":
        return x * 0.5, "value"
    if kind == "principal_twist":  # |ω| > π: outside the principal domain
        x = x.clone()
        x[..., :3] = 4.0 * x[..., :3] / x[..., :3].norm(dim=-1, keepdim=True)
        return x, "value"
    return _randn(rng, x.shape, dtype) if isinstance(x, Tensor) else x, "either"


def _m_reflection(x, kind, dtype, rng):
    if kind == "rot":
        return -x, "value"
    if kind == "pose":
        x = x.clone()
        x[..., :3, :3] = -x[..., :3, :3]
        return x, "value"
    return -x if isinstance(x, Tensor) else x, "either"


def _m_bottom_row(x, kind, dtype, rng):
    if kind == "pose":
        x = x.clone()
        x[..., 3, 3] = 2.0
        return x, "value"
    return x, "either"


MALFORMATIONS = {
    "python_list": _m_python_list,
    "python_int": _m_int,
    "none": _m_none,
    "int_tensor": _m_int_tensor,
    "float16": _m_half,
    "complex": _m_complex,
    "trailing_shape": _m_trailing,
    "scalar": _m_scalar,
    "nan": _non_finite(math.nan),
    "inf": _non_finite(math.inf),
    "minus_inf": _non_finite(-math.inf),
    "huge_entry": _m_huge_entry,
    "huge_scale": _scaled(HUGE),
    "tiny_scale": _scaled(TINY),
    "scaled_rotation": _m_scaled_rotation,
    "non_rotation": _m_non_rotation,
    "reflection": _m_reflection,
    "bottom_row": _m_bottom_row,
}
# Malformations of the relation between arguments (functions with two tensor arguments).
PAIR_MALFORMATIONS = ("mixed_dtype", "batch_mismatch")


# ----------------------------------------------------------------------------- the contract


def _tensors(result) -> list[Tensor]:
    if isinstance(result, Tensor):
        return [result]
    if isinstance(result, Transform3d):
        return [result.get_matrix()]
    if isinstance(result, tuple):
        return [t for r in result for t in _tensors(r)]
    raise AssertionError(f"unexpected result type {type(result)}")


def _names_argument(message: str, name: str) -> bool:
    return re.search(rf"'{re.escape(name)}['.]", message) is not None


def _check_call(api: Api, args: list, bad: tuple[str, ...], expect: str, context: str) -> str:
    """Call ``api`` and check the contract; returns "raised" or "finite"."""
    try:
        result = api.call(*args)
    except (ValueError, TypeError) as error:
        message = str(error)
        assert api.name in message, f"{context}: message lacks the function name: {message}"
        assert any(_names_argument(message, name) for name in bad), (
            f"{context}: message lacks the argument name {bad}: {message}"
        )
        if expect == "type":
            assert isinstance(error, TypeError), f"{context}: expected TypeError, got {error!r}"
        if expect == "value":
            assert isinstance(error, ValueError), f"{context}: expected ValueError, got {error!r}"
        return "raised"
    assert expect == "either", f"{context}: expected a {expect} error, got a result"
    for t in _tensors(result):
        assert bool(torch.isfinite(t).all()), f"{context}: finite input gave a non-finite result"
    return "finite"


def _case(api: Api, malformation: str, position: int, dtype, batch, rng) -> str:
    kinds = [_resolve(kind, api.manifold) for _, kind in api.args]
    names = [name for name, _ in api.args]
    args = [_valid(kind, batch, dtype, rng, api.manifold) for kind in kinds]
    context = f"{api.name} {malformation} of '{names[position]}' ({dtype}, batch {batch})"
    if malformation == "mixed_dtype":
        other = F32 if dtype == F64 else F64
        args[position] = args[position].to(other)
        return _check_call(api, args, tuple(names), "type", context)
    if malformation == "batch_mismatch":
        args = [_valid(kind, (3,), dtype, rng, api.manifold) for kind in kinds]
        args[position] = _valid(kinds[position], (4,), dtype, rng, api.manifold)
        return _check_call(api, args, tuple(names), "value", context)
    malform = MALFORMATIONS[malformation]
    if kinds[position] == "t3d" and malformation not in TYPE_LEVEL:
        T, expect = malform(args[position].get_matrix(), "pose", dtype, rng)
        args[position] = Transform3d(matrix=T, dtype=dtype)
    else:
        args[position], expect = malform(args[position], kinds[position], dtype, rng)
    return _check_call(api, args, (names[position],), expect, context)


def _all_cases() -> list[tuple[Api, str, int]]:
    cases = []
    for api in APIS:
        for position in range(len(api.args)):
            cases.extend((api, m, position) for m in MALFORMATIONS)
            if len(api.args) == 2:
                cases.extend((api, m, position) for m in PAIR_MALFORMATIONS)
    return cases


def test_seeded_fuzz_of_the_public_surface():
    # A seeded sample of 700 of the ~2000 (function, argument, malformation) triples, each with
    # a random dtype, batch shape and position of the bad entry (~1.5 s). Every function and
    # every malformation is in the sample (checked below).
    rng = random.Random(20261201)
    cases = rng.sample(_all_cases(), 700)
    assert {api.name for api, _, _ in cases} == {api.name for api in APIS}
    assert {m for _, m, _ in cases} == set(MALFORMATIONS) | set(PAIR_MALFORMATIONS)
    outcomes = {"raised": 0, "finite": 0}
    for api, malformation, position in cases:
        dtype = rng.choice((F64, F32))
        batch = rng.choice(((), (2,), (3, 1)))
        outcomes[_case(api, malformation, position, dtype, batch, rng)] += 1
    # Both branches of the contract are exercised (most malformations must raise).
    assert outcomes["raised"] > 400 and outcomes["finite"] > 50, outcomes


def test_seeded_fuzz_of_identity_sizes_and_keywords():
    cases = [
        ((-1,), {}, ValueError, "batch_shape"),
        ((2, -3), {}, ValueError, "batch_shape"),
        ((2.0,), {}, TypeError, "batch_shape"),
        ((True,), {}, TypeError, "batch_shape"),
        (("2",), {}, TypeError, "batch_shape"),
        ((None,), {}, TypeError, "batch_shape"),
        ((torch.ones(2),), {}, TypeError, "batch_shape"),
        ((2,), {"dtype": torch.int64}, TypeError, "dtype"),
        ((2,), {"dtype": torch.float16}, TypeError, "dtype"),
        ((2,), {"dtype": "float64"}, TypeError, "dtype"),
        ((2,), {"device": "not-a-device"}, ValueError, "device"),
        ((2,), {"device": 1.5}, TypeError, "device"),
    ]
    for args, kwargs, error, name in cases:
        with pytest.raises(error) as info:
            se3.identity(*args, **kwargs)
        assert "se3.identity" in str(info.value) and f"'{name}'" in str(info.value)
    assert se3.identity().shape == (4, 4)
    assert se3.identity(0).shape == (0, 4, 4)
    assert se3.identity(torch.tensor(2), 1, dtype=F32).shape == (2, 1, 4, 4)


def test_manifold_constructors_reject_bad_arguments():
    for bad in (0, -1):
        with pytest.raises(ValueError, match=r"Euclidean.*'n'"):
            mf.Euclidean(bad)
    for bad in (2.0, True, "3", None):
        with pytest.raises(TypeError, match=r"Euclidean.*'n'"):
            mf.Euclidean(bad)
    for cls in (mf.SE3Matrix, mf.SO3Quaternion, mf.SE3Tangent):
        with pytest.raises(ValueError, match=f"{cls.__name__}.*'perturbation'"):
            cls("middle")


# ----------------------------------------------------------------------------- targeted tests


def _axis(dtype=F64) -> Tensor:
    a = torch.tensor([1.0, -2.0, 3.0], dtype=F64)
    return (a / a.norm()).to(dtype)


def _assert_rotation(R: Tensor) -> None:
    eye = torch.eye(3, dtype=R.dtype)
    # A rotation built from unit-norm entries: orthonormal to a few ulps of the dtype.
    tol = 8 * torch.finfo(R.dtype).eps
    assert bool(torch.isfinite(R).all())
    assert float((R.transpose(-1, -2) @ R - eye).abs().max()) <= tol
    assert float((torch.linalg.det(R) - 1).abs().max()) <= tol


@pytest.mark.parametrize("scale", [1e300, 1e-300, 1e10])
def test_rotation_checks_reject_scaled_rotations(scale):
    R = so3.exp(torch.tensor([0.3, -0.2, 0.5], dtype=F64))
    T = se3.from_rotation_translation(R, torch.ones(3, dtype=F64))
    bad_T = T.clone()
    bad_T[:3, :3] *= scale
    for name, call, arg in [
        ("so3.log", lambda: so3.log(R * scale), "R"),
        ("so3.inverse", lambda: so3.inverse(R * scale), "R"),
        ("convert.matrix_to_quaternion", lambda: convert.matrix_to_quaternion(R * scale), "R"),
        ("se3.log", lambda: se3.log(bad_T), "T"),
        ("se3.inverse", lambda: se3.inverse(bad_T), "T"),
        ("SE3Matrix.plus", lambda: mf.SE3Matrix().plus(bad_T, torch.zeros(6, dtype=F64)), "x"),
    ]:
        with pytest.raises(ValueError) as info:
            call()
        assert name in str(info.value) and f"'{arg}'" in str(info.value)
        assert "nan" not in str(info.value).lower()


def test_rotation_check_message_reports_overflow_and_quaternion_norm():
    R = so3.exp(torch.tensor([0.3, -0.2, 0.5], dtype=F64)) * 1e300
    with pytest.raises(
        ValueError, match=r"too large to compute \(largest \|entry\| = [0-9.]+e\+299"
    ):
        so3.log(R)
    for norm in (0.5, 1.5, 1e300):
        q = torch.tensor([norm, 0.0, 0.0, 0.0], dtype=F64)
        with pytest.raises(ValueError) as info:
            convert.quaternion_to_matrix(q)
        assert f"|q| = {norm:.6g}." in str(info.value)
    q = torch.tensor([0.6, 0.0, 0.0, 0.0], dtype=F32)  # |q| = 0.6 must not print 1.4
    with pytest.raises(ValueError, match=r"\|q\| = 0\.6\."):
        mf.SO3Quaternion().minus(q, q)


@pytest.mark.parametrize("dtype", [F64, F32])
@pytest.mark.parametrize("magnitude", ["huge", "max"])
def test_exp_of_huge_rotation_vectors_is_a_rotation(dtype, magnitude):
    # |ω| = 1e300 (float32: 1e38), and components near the largest float, where |ω| itself
    # overflows: the angle is reduced modulo 2π, the result is still an exact rotation.
    big = HUGE[dtype] if magnitude == "huge" else torch.finfo(dtype).max / 2
    omega = torch.stack((_axis(dtype) * HUGE[dtype], torch.full((3,), big, dtype=dtype)))
    for R in (
        so3.exp(omega),
        convert.axis_angle_to_matrix(omega),
        convert.quaternion_to_matrix(convert.axis_angle_to_quaternion(omega)),
        se3.exp(torch.cat((omega, omega), dim=-1))[..., :3, :3],
    ):
        _assert_rotation(R)
    for J in (so3.jl(omega), so3.jr(omega), se3.jl(torch.cat((omega, omega), dim=-1))):
        assert bool(torch.isfinite(J).all())
    # Far beyond 2π, J_l(θu) tends to u uᵀ (the 1/θ terms vanish).
    u = _axis(dtype)
    assert float((so3.jl(u * HUGE[dtype]) - torch.outer(u, u)).abs().max()) <= 1e-6
    # The manifold retractions stay on their manifolds.
    q = mf.SO3Quaternion().plus(torch.tensor([1.0, 0, 0, 0], dtype=dtype), omega)
    assert float((q.norm(dim=-1) - 1).abs().max()) <= 8 * torch.finfo(dtype).eps
    T = mf.SE3Matrix().plus(se3.identity(dtype=dtype), torch.cat((omega, omega), dim=-1))
    _assert_rotation(T[..., :3, :3])


def test_exp_angle_reduction_matches_exact_trigonometry():
    # Beyond the unit-axis threshold (2²⁰) the rotation equals Rodrigues' formula with Python's
    # sin/cos (exact argument reduction) of θ = math.hypot(ω) (< 1 ulp), to within the angle's
    # resolution: |ω| in floating point is off by a few ε·θ on either side (≤ 6e-16·θ in all),
    # and reducing by fl(2π) instead of 2π moves the angle by ≤ 4e-17·θ; rounding adds ~1e-15.
    u = _axis()
    for theta in (2.0**20 * 1.5, 1e7, 1e12):
        omega = u * theta
        theta_f = math.hypot(*omega.tolist())
        W = so3.hat(u)
        expected = torch.eye(3, dtype=F64) + math.sin(theta_f) * W + (1 - math.cos(theta_f)) * W @ W
        assert float((so3.exp(omega) - expected).abs().max()) <= theta * 6.4e-16 + 1e-14


def test_jacobians_of_huge_inputs_are_finite_or_raise():
    u = _axis()
    xi = torch.cat((u * 1e300, torch.ones(3, dtype=F64)))
    assert bool(torch.isfinite(se3.jl(xi)).all()) and bool(torch.isfinite(se3.jr(xi)).all())
    # J_l⁻¹(ω) grows like |ω|/2: 5e299 is representable ...
    J_inv = so3.jl_inv(u * 1e300)
    assert bool(torch.isfinite(J_inv).all()) and float(J_inv.abs().max()) > 1e299
    # ... but the SE(3) block grows like |ω|²|v|, which overflows: a clear ValueError.
    for fn, name in ((se3.jl_inv, "se3.jl_inv"), (se3.jr_inv, "se3.jr_inv")):
        with pytest.raises(ValueError, match=f"{name}: .*'xi'.*singular"):
            fn(xi)
    # Huge translations with ordinary rotations: linear in v, no intermediate overflow.
    omega = torch.tensor([2.0, -1.0, 0.5], dtype=F64)
    v = torch.tensor([0.3, 0.7, -0.2], dtype=F64)
    for s in (1e300, 2.0**900, 1e-300):
        big = torch.cat((omega, v * s))
        small = torch.cat((omega, v))
        # Relative 1e-15: s·x vs the result for s·v differ by the rounding of s·v only.
        t_big, t_small = se3.exp(big)[:3, 3], se3.exp(small)[:3, 3]
        assert float(((t_big / s) - t_small).abs().max()) <= 1e-15
        for fn in (se3.jl, se3.jr, se3.jl_inv, se3.jr_inv):
            Q_big, Q_small = fn(big)[3:, :3], fn(small)[3:, :3]
            assert float(((Q_big / s) - Q_small).abs().max()) <= 1e-14


NAN_APIS = [api for api in APIS if not api.name.startswith("convert.from_transform3d")]


@pytest.mark.parametrize("api", NAN_APIS, ids=[api.name for api in NAN_APIS])
def test_nan_and_inf_are_rejected_by_every_function(api):
    rng = random.Random(5)
    for position, (name, _) in enumerate(api.args):
        for value in (math.nan, math.inf):
            kinds = [_resolve(k, api.manifold) for _, k in api.args]
            args = [_valid(k, (2,), F64, rng, api.manifold) for k in kinds]
            args[position] = _set_entry(args[position], rng, value)[0]
            with pytest.raises(ValueError) as info:
                api.call(*args)
            assert api.name in str(info.value) and f"'{name}'" in str(info.value)


def test_nan_passes_through_unchecked_with_validation_off():
    omega = torch.tensor([math.nan, 0.0, 0.0], dtype=F64)
    with torchslam.validation(False):
        assert bool(torch.isnan(so3.hat(omega)).any())
        assert bool(torch.isnan(so3.jl(omega)).all())


def test_inverse_of_non_rigid_input_raises():
    M = torch.tensor([[1.0, 0.2, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    with pytest.raises(ValueError, match=r"so3\.inverse: argument 'R' must hold rotation"):
        so3.inverse(M)
    T = torch.eye(4, dtype=F64)
    T[:3, :3] = M
    with pytest.raises(ValueError, match=r"se3\.inverse: argument 'T' must hold rotation"):
        se3.inverse(T)
    T = torch.eye(4, dtype=F64)
    T[3, 0] = 1.0
    with pytest.raises(ValueError, match=r"se3\.inverse: argument 'T' must have bottom row"):
        se3.inverse(T)
    with torchslam.validation(False):  # unchecked: the formula, as documented
        assert torch.equal(so3.inverse(M), M.T)


@pytest.mark.parametrize(
    ("name", "call", "first", "second"),
    [
        ("so3.act", lambda a, b: so3.act(a, b), ("R", "rot"), ("points", "vec3")),
        ("se3.act", lambda a, b: se3.act(a, b), ("T", "pose"), ("points", "vec3")),
        ("se3.compose", lambda a, b: se3.compose(a, b), ("T1", "pose"), ("T2", "pose")),
        (
            "se3.from_rotation_translation",
            lambda a, b: se3.from_rotation_translation(a, b),
            ("R", "rot"),
            ("t", "vec3"),
        ),
        (
            "convert.pose_from_translation_quaternion",
            lambda a, b: convert.pose_from_translation_quaternion(a, b),
            ("t", "vec3"),
            ("q", "quat"),
        ),
    ],
    ids=lambda v: v if isinstance(v, str) else "",
)
def test_mismatched_batch_dims_name_both_arguments_and_shapes(name, call, first, second):
    rng = random.Random(3)
    a = _valid(first[1], (2, 5), F64, rng)
    b = _valid(second[1], (3,), F64, rng)
    with pytest.raises(ValueError) as info:
        call(a, b)
    message = str(info.value)
    assert name in message
    assert f"'{first[0]}' with batch shape (2, 5)" in message
    assert f"'{second[0]}' with batch shape (3,)" in message
    # Broadcastable batches still work.
    assert call(a, _valid(second[1], (1, 5), F64, rng)).shape[:2] == (2, 5)


def test_results_that_overflow_raise_naming_the_arguments():
    # A rigid transform with translations near the largest float: the composition's
    # translation is not representable.
    T = se3.identity(dtype=F64)
    T[:3, 3] = 1e308
    with pytest.raises(ValueError, match=r"se3\.compose: the result is not finite.*'T1'.*'T2'"):
        se3.compose(T, T)
    with pytest.raises(ValueError, match=r"Euclidean\.plus: the result is not finite.*'x'"):
        mf.Euclidean(3).plus(torch.full((3,), 1e308, dtype=F64), torch.full((3,), 1e308, dtype=F64))
    # |ω| itself overflows (components 1.5e308): J_l⁻¹, which grows like |ω|/2, cannot be held.
    with pytest.raises(ValueError, match=r"so3\.jl_inv: .*'omega'.*singular"):
        so3.jl_inv(torch.full((3,), 1.5e308, dtype=F64))


def test_project_handles_huge_and_tiny_scales():
    M = torch.tensor([[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    expected = so3.project(M)
    for scale in (1e300, 1e-300, 2.0**-80):
        # The nearest rotation does not depend on the scale; agreement to round-off.
        assert float((so3.project(M * scale) - expected).abs().max()) <= 1e-14


def test_huge_inputs_stay_finite_inside_vmap_and_with_validation_off():
    # The robust formulas do not depend on the (skipped) value checks.
    omega = torch.stack((_axis() * 1e300, _axis() * 0.5, torch.zeros(3, dtype=F64)))
    xi = torch.cat((omega, omega), dim=-1)
    with torchslam.validation(False):
        for R in (so3.exp(omega), torch.func.vmap(so3.exp)(omega)):
            _assert_rotation(R)
        assert bool(torch.isfinite(torch.func.vmap(se3.jl)(xi)).all())
        J = torch.func.vmap(torch.func.jacrev(so3.exp))(omega)
        assert bool(torch.isfinite(J).all())


def test_no_host_sync_with_validation_off():
    # With value checks off the public surface must stay sync-free (the solver's hot path,
    # CUDA graphs): under FakeTensorMode any read of a tensor's value raises. With checks on
    # every function reads values (each has a value check), which the mode also reveals.
    from torch._subclasses.fake_tensor import DataDependentOutputException, FakeTensorMode

    rng = random.Random(11)
    for api in APIS:
        kinds = [_resolve(kind, api.manifold) for _, kind in api.args]
        if "t3d" in kinds:
            continue
        args = [_valid(kind, (2,), F64, rng, api.manifold) for kind in kinds]
        with FakeTensorMode(allow_non_fake_inputs=True) as mode:
            fake = [mode.from_tensor(a) for a in args]
            with torchslam.validation(False):
                api.call(*fake)  # no exception: no value was read
            with pytest.raises(DataDependentOutputException):
                api.call(*fake)
