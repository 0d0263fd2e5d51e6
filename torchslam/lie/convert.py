"""Rotation and pose conversions, quaternion algebra, and ``Transform3d`` interop.

This module holds all of torchslam's quaternion code: ``so3.log`` goes through
:func:`matrix_to_quaternion` and :func:`quaternion_to_axis_angle`, and the
``manifold.SO3Quaternion`` manifold through the quaternion algebra below (Hamilton product,
conjugate, the product matrices).

Conventions (kept across torchslam):
- Quaternions are Hamilton, stored (w, x, y, z), real part first, unit norm. q and −q are the
  same rotation; every function here that returns a quaternion returns the one with w ≥ 0.
- Axis-angle is the rotation vector ω = θ·axis (radians), the same ω as ``so3.exp``/``so3.log``.
- Poses are T = [[R, t], [0, 1]] with p' = R p + t, shape (..., 4, 4).

What comes from pytorch-kinematics and what does not (checked by ``tests/lie/test_convert.py``):
- ``quaternion_to_matrix`` is pytorch-kinematics' (a polynomial in q, exact, w-first order).
- pytorch-kinematics' ``matrix_to_quaternion``, ``axis_angle_to_quaternion`` and
  ``quaternion_to_axis_angle`` give correct values but NaN gradients at the identity rotation
  (sqrt of 0 and sin θ / θ evaluated at θ = 0), so torchslam's own gradient-safe versions are
  used instead: Shepperd's method and the series-backed coefficients of
  ``torchslam.lie._series``, below.
- ``Transform3d`` (pytorch-kinematics ≥ 0.7) stores the ordinary column-vector matrix: its
  ``get_matrix()`` is exactly T = [[R, t], [0, 1]] and ``transform_points(p)`` = R p + t (its
  class docstring draws the rotation block transposed; the code does not transpose). A
  ``Transform3d`` holds a flat batch (N, 4, 4), so leading batch dims are flattened on the way in.
"""

from __future__ import annotations

import functools
import importlib
import importlib.util
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import torch
from torch import Tensor

from torchslam import _checks
from torchslam.lie import _series, se3, so3

if TYPE_CHECKING:
    from pytorch_kinematics.transforms import Transform3d

__all__ = [
    "axis_angle_to_matrix",
    "axis_angle_to_quaternion",
    "from_transform3d",
    "matrix_to_axis_angle",
    "matrix_to_quaternion",
    "pose_from_translation_quaternion",
    "pose_to_translation_quaternion",
    "quaternion_conjugate",
    "quaternion_multiply",
    "quaternion_product_matrix",
    "quaternion_to_axis_angle",
    "quaternion_to_matrix",
    "to_transform3d",
]


@functools.cache
def _pk_rotation():
    """pytorch-kinematics' ``transforms.rotation_conversions`` (it imports only torch), loaded
    from its file on first use: importing the package runs its ``__init__``, which pulls in
    matplotlib.pyplot, lxml and absl (about 1.2 s) that no conversion needs. The ordinary
    import when the file is not where pytorch-kinematics ≥ 0.7 keeps it."""
    spec = importlib.util.find_spec("pytorch_kinematics")
    locations = [] if spec is None else list(spec.submodule_search_locations or [])
    path = Path(locations[0], "transforms", "rotation_conversions.py") if locations else None
    if path is None or not path.is_file():
        return importlib.import_module("pytorch_kinematics.transforms.rotation_conversions")
    file_spec = importlib.util.spec_from_file_location(
        "torchslam.lie._pytorch_kinematics_rotation_conversions", path
    )
    module = importlib.util.module_from_spec(file_spec)
    try:
        file_spec.loader.exec_module(module)
    except ImportError:  # a release whose file imports its package: the ordinary import
        return importlib.import_module("pytorch_kinematics.transforms.rotation_conversions")
    return module


def _transform3d_class() -> type:
    from pytorch_kinematics.transforms import Transform3d  # the whole package: lazily

    return Transform3d


def _canonical(q: Tensor) -> Tensor:
    """The representative of ±q with w ≥ 0."""
    return torch.where(q[..., :1] < 0, -q, q)


# Shepperd's candidates from the flattened R (row-major, m_rc at 3r + c): the diagonal
# (m00, m11, m22), then m21, m02, m10 and m12, m20, m01 (the skew differences a, b, c are
# the first minus the second), then m01, m02, m12 and m10, m20, m21 (the symmetric sums d,
# e, f are the sum of the two); the 4 × 4 candidate matrix is symmetric in them (see below).
_ENTRIES = (0, 4, 8, 7, 2, 3, 5, 6, 1, 1, 2, 5, 3, 6, 7)
# 1 + s_k · (m00, m11, m22) for the candidates k = w, x, y, z.
_DIAGONAL_SIGNS = ((1.0, 1.0, -1.0, -1.0), (1.0, -1.0, 1.0, -1.0), (1.0, -1.0, -1.0, 1.0))
# Entry (k, c) of the candidate matrix in u = (r_w², r_x², r_y², r_z², skew (3), sym (3)).
_CANDIDATES = (0, 4, 5, 6, 4, 1, 7, 8, 5, 7, 2, 9, 6, 8, 9, 3)


def _matrix_to_quaternion(R: Tensor) -> Tensor:
    """Shepperd's method, (w, x, y, z), w ≥ 0; vmap-safe and gradient-safe.

    All four candidates are computed; the one built from the largest of
    (1 + tr, 1 + 2R00 − tr, …) is selected. That value is ≥ 1 for a rotation, so clamping
    the square root's argument at 0.25 changes only the discarded candidates (and keeps
    their gradients finite). Candidate k is row k of the symmetric matrix

        [[r_w², a, b, c], [a, r_x², d, e], [b, d, r_y², f], [c, e, f, r_z²]] / (2 r_k)

    with (a, b, c) = (m21 − m12, m02 − m20, m10 − m01), (d, e, f) = (m01 + m10, m02 + m20,
    m12 + m21) and r_k² the diagonal values: a few whole-tensor operations (small batches
    are bound by their number).
    """
    entries = R.reshape(*R.shape[:-2], 9).index_select(
        -1, _series.constant("shepperd entries", _ENTRIES, torch.long, R.device)
    )
    signs = _series.constant("shepperd signs", _DIAGONAL_SIGNS, R.dtype, R.device)
    diag = 1.0 + entries[..., :3] @ signs
    root = torch.sqrt(diag.clamp_min(0.25))  # = 2·|component| for the selected candidate
    skew = entries[..., 3:6] - entries[..., 6:9]
    symmetric = entries[..., 9:12] + entries[..., 12:15]
    u = torch.cat((root * root, skew, symmetric), dim=-1)
    matrix = u.index_select(
        -1, _series.constant("shepperd candidates", _CANDIDATES, torch.long, R.device)
    )
    candidates = matrix.reshape(*u.shape[:-1], 4, 4) / (2.0 * root[..., :, None])
    best = diag.argmax(dim=-1)
    q = torch.gather(candidates, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    return _canonical(q)


def _axis_angle_to_quaternion(omega: Tensor) -> Tensor:
    """Unit quaternion (cos(θ/2), sin(θ/2)·ω/θ) of rotation vectors (..., 3), exact at θ = 0."""
    p = so3._polar(omega)
    # With x = θ/2: sin(x)/x and (1 − cos x)/x² are the Rodrigues coefficients at x².
    half2 = 0.25 * p.theta2
    a, b = _series.sinc_coefficients(half2)
    w = torch.where(p.large, p.cos_half, 1.0 - half2 * b)
    scale = torch.where(p.large, p.sin_half, 0.5 * a)
    return torch.cat((w[..., None], scale[..., None] * p.w), dim=-1)


def _quaternion_to_axis_angle(q: Tensor) -> Tensor:
    """Rotation vector of unit quaternions (..., 4), angle θ = 2·atan2(|v|, |w|) ∈ [0, π]."""
    # q ≡ −q: the representative with w ≥ 0 gives θ ≤ π.
    return _canonical_quaternion_to_axis_angle(_canonical(q))


def _canonical_quaternion_to_axis_angle(q: Tensor) -> Tensor:
    """:func:`_quaternion_to_axis_angle` of unit quaternions (..., 4) that have w ≥ 0 already
    (those of :func:`_matrix_to_quaternion`)."""
    w, v = q[..., 0], q[..., 1:]
    # ω = θ v / |v|; the ratio atan2(|v|, w)/|v| is exact at |v| = 0 and at w = 0 (θ = π). It
    # is read off |v|², never |v| (whose derivative is 0/0 at v = 0), so that second
    # derivatives (a double backward, e.g. a Hessian-vector product through the solver) are
    # finite at the identity.
    return (2.0 * _series.atan_ratio_squared((v * v).sum(-1), w))[..., None] * v


def quaternion_to_matrix(q: Tensor) -> Tensor:
    """Rotation matrix of a unit quaternion (Hamilton, stored (w, x, y, z)).

    Uses ``pytorch_kinematics.transforms.quaternion_to_matrix``. q and −q give the same R.

    Args:
        q: unit quaternions (w, x, y, z), shape (..., 4). Checked (|q| = 1) when validation is
            on; with validation off the formula divides by |q|², i.e. it uses q / |q|.

    Returns:
        Rotation matrices, shape (..., 3, 3), same dtype and device as ``q``.
    """
    _checks.check_tensor("convert.quaternion_to_matrix", "q", q, (4,))
    _checks.check_unit_quaternion("convert.quaternion_to_matrix", "q", q)
    return _pk_rotation().quaternion_to_matrix(q)


def matrix_to_quaternion(R: Tensor) -> Tensor:
    """Unit quaternion (Hamilton, stored (w, x, y, z), w ≥ 0) of a rotation matrix.

    Shepperd's method (the best-conditioned of four candidates), gradient-safe at R = I.

    Args:
        R: rotation matrices, shape (..., 3, 3). Checked (orthonormal, det +1) when validation
            is on; use ``so3.project`` first for approximately orthonormal input.

    Returns:
        Quaternions (w, x, y, z) with w ≥ 0, shape (..., 4).
    """
    _checks.check_tensor("convert.matrix_to_quaternion", "R", R, (3, 3))
    _checks.check_rotation("convert.matrix_to_quaternion", "R", R)
    return _matrix_to_quaternion(R)


def axis_angle_to_quaternion(omega: Tensor) -> Tensor:
    """Unit quaternion (w, x, y, z) of a rotation vector: (cos(θ/2), sin(θ/2) ω/θ).

    Exact and differentiable at θ = 0 (series coefficients). w ≥ 0 for θ ≤ π; for θ > π the
    quaternion is returned as computed (w < 0), which is the same rotation as −q. Finite for
    every finite ω; beyond |ω| = 2²⁰ (float64) / 2¹⁰ (float32) the angle is reduced modulo 2π
    and the sign of q is arbitrary.

    Args:
        omega: rotation vectors ω = θ·axis (radians), shape (..., 3).

    Returns:
        Quaternions (w, x, y, z), shape (..., 4).
    """
    _checks.check_tensor("convert.axis_angle_to_quaternion", "omega", omega, (3,))
    _checks.check_finite("convert.axis_angle_to_quaternion", "omega", omega)
    return _axis_angle_to_quaternion(omega)


def quaternion_to_axis_angle(q: Tensor) -> Tensor:
    """Rotation vector of a unit quaternion (w, x, y, z), angle θ ∈ [0, π].

    θ = 2·atan2(|v|, |w|) for q = (w, v), q replaced by −q when w < 0; exact and differentiable
    at θ = 0 and near π. At exactly θ = π (w = 0) either ±ω may be returned.

    Args:
        q: unit quaternions (w, x, y, z), shape (..., 4); checked when validation is on.

    Returns:
        Rotation vectors, shape (..., 3).
    """
    _checks.check_tensor("convert.quaternion_to_axis_angle", "q", q, (4,))
    _checks.check_unit_quaternion("convert.quaternion_to_axis_angle", "q", q)
    return _quaternion_to_axis_angle(q)


def axis_angle_to_matrix(omega: Tensor) -> Tensor:
    """Rotation matrix of a rotation vector; the same as ``so3.exp`` (Rodrigues, seed eq. L4.1).

    Args:
        omega: rotation vectors ω = θ·axis (radians), shape (..., 3).

    Returns:
        Rotation matrices, shape (..., 3, 3).
    """
    _checks.check_tensor("convert.axis_angle_to_matrix", "omega", omega, (3,))
    _checks.check_finite("convert.axis_angle_to_matrix", "omega", omega)
    return so3._exp_robust(omega)


def matrix_to_axis_angle(R: Tensor) -> Tensor:
    """Rotation vector of a rotation matrix; the same as ``so3.log`` (angle θ ∈ [0, π]).

    Args:
        R: rotation matrices, shape (..., 3, 3); checked when validation is on.

    Returns:
        Rotation vectors, shape (..., 3).
    """
    _checks.check_tensor("convert.matrix_to_axis_angle", "R", R, (3, 3))
    _checks.check_rotation("convert.matrix_to_axis_angle", "R", R)
    return so3._log(R)


def pose_from_translation_quaternion(t: Tensor, q: Tensor) -> Tensor:
    """Pose T = [[R(q), t], [0, 1]] from a translation and a unit quaternion.

    Takes translation first, then the quaternion in (w, x, y, z) order (TUM files store
    (x, y, z, w): reorder with ``q[..., [3, 0, 1, 2]]``). Leading dims broadcast.

    Args:
        t: translations, shape (..., 3).
        q: unit quaternions (w, x, y, z), shape (..., 4); checked when validation is on.

    Returns:
        Poses, shape broadcast(t.shape[:-1], q.shape[:-1]) + (4, 4).
    """
    fn = "convert.pose_from_translation_quaternion"
    _checks.check_tensor(fn, "t", t, (3,))
    _checks.check_tensor(fn, "q", q, (4,))
    _checks.check_same_kind(fn, t=t, q=q)
    batch = _checks.check_broadcast(fn, t=t.shape[:-1], q=q.shape[:-1])
    _checks.check_finite(fn, "t", t)
    _checks.check_unit_quaternion(fn, "q", q)
    R = _pk_rotation().quaternion_to_matrix(q)
    return se3._assemble(R.expand(*batch, 3, 3), t.expand(*batch, 3))


def pose_to_translation_quaternion(T: Tensor) -> tuple[Tensor, Tensor]:
    """Translation and unit quaternion (w, x, y, z), w ≥ 0, of a pose T = [[R, t], [0, 1]].

    Returns translation first, then the quaternion; inverse of
    :func:`pose_from_translation_quaternion` (up to q ≡ −q).

    Args:
        T: poses, shape (..., 4, 4); checked (rigid, bottom row [0, 0, 0, 1]) when validation
            is on.

    Returns:
        ``(t, q)`` with t of shape (..., 3) and q of shape (..., 4).
    """
    fn = "convert.pose_to_translation_quaternion"
    _checks.check_tensor(fn, "T", T, (4, 4))
    _checks.check_pose_matrix(fn, "T", T)
    return T[..., :3, 3], _matrix_to_quaternion(T[..., :3, :3])


def quaternion_multiply(q: Tensor, p: Tensor) -> Tensor:
    """Hamilton product q ⊗ p of quaternions stored (w, x, y, z); leading dims broadcast.

    (q_w, q_v) ⊗ (p_w, p_v) = (q_w p_w − q_v·p_v, q_w p_v + p_w q_v + q_v × p_v), so that
    R(q ⊗ p) = R(q) R(p) for unit quaternions. Any quaternions (not only unit ones).

    Args:
        q: quaternions (w, x, y, z), shape (..., 4).
        p: quaternions (w, x, y, z), shape (..., 4).

    Returns:
        q ⊗ p, shape broadcast(q.shape[:-1], p.shape[:-1]) + (4,).
    """
    fn = "convert.quaternion_multiply"
    _checks.check_tensor(fn, "q", q, (4,))
    _checks.check_tensor(fn, "p", p, (4,))
    _checks.check_same_kind(fn, q=q, p=p)
    _checks.check_broadcast(fn, q=q.shape[:-1], p=p.shape[:-1])
    _checks.check_finite(fn, "q", q)
    _checks.check_finite(fn, "p", p)
    q_w, q_v = q[..., :1], q[..., 1:]
    p_w, p_v = p[..., :1], p[..., 1:]
    q_v, p_v = torch.broadcast_tensors(q_v, p_v)
    w = q_w * p_w - (q_v * p_v).sum(-1, keepdim=True)
    v = q_w * p_v + p_w * q_v + torch.linalg.cross(q_v, p_v, dim=-1)
    result = torch.cat((w, v), dim=-1)
    _checks.check_result_finite(fn, result, q=q, p=p)
    return result


def quaternion_conjugate(q: Tensor) -> Tensor:
    """Conjugate q* = (w, −x, −y, −z); the inverse of a unit quaternion, R(q*) = R(q)ᵀ.

    Args:
        q: quaternions (w, x, y, z), shape (..., 4).

    Returns:
        q*, shape (..., 4).
    """
    _checks.check_tensor("convert.quaternion_conjugate", "q", q, (4,))
    _checks.check_finite("convert.quaternion_conjugate", "q", q)
    return torch.cat((q[..., :1], -q[..., 1:]), dim=-1)


def quaternion_product_matrix(q: Tensor, side: Literal["left", "right"] = "left") -> Tensor:
    """The matrix of multiplication by q: [q]_L with q ⊗ p = [q]_L p (``side="left"``), or
    [q]_R with p ⊗ q = [q]_R p (``side="right"``) (Solà, eqs. 18-19).

    [q]_L = w·I + [[0, −vᵀ], [v, [v]×]] and [q]_R = w·I + [[0, −vᵀ], [v, −[v]×]] for q = (w, v).

    Args:
        q: quaternions (w, x, y, z), shape (..., 4).
        side: "left" or "right".

    Returns:
        Matrices, shape (..., 4, 4), acting on (w, x, y, z) column vectors.
    """
    fn = "convert.quaternion_product_matrix"
    _checks.check_tensor(fn, "q", q, (4,))
    if side != "left" and side != "right":
        raise ValueError(f"{fn}: argument 'side' must be 'left' or 'right', got {side!r}")
    _checks.check_finite(fn, "q", q)
    w, x, y, z = q.unbind(-1)
    sign = 1.0 if side == "left" else -1.0
    sx, sy, sz = sign * x, sign * y, sign * z
    return torch.stack(
        (
            torch.stack((w, -x, -y, -z), dim=-1),
            torch.stack((x, w, -sz, sy), dim=-1),
            torch.stack((y, sz, w, -sx), dim=-1),
            torch.stack((z, -sy, sx, w), dim=-1),
        ),
        dim=-2,
    )


def to_transform3d(T: Tensor) -> Transform3d:
    """Wrap poses T = [[R, t], [0, 1]] in a ``pytorch_kinematics.transforms.Transform3d``.

    The matrix is passed as is (``Transform3d`` uses the same column-vector convention:
    ``transform_points(p)`` = R p + t). ``Transform3d`` holds a flat batch, so T of shape
    (..., 4, 4) becomes a batch of N = prod(...) transforms (N = 1 for a single pose); keep
    ``T.shape[:-2]`` to reshape the result of :func:`from_transform3d`.

    Args:
        T: poses, shape (..., 4, 4); checked (rigid) when validation is on.

    Returns:
        A ``Transform3d`` of length N with T's dtype and device.
    """
    _checks.check_tensor("convert.to_transform3d", "T", T, (4, 4))
    _checks.check_pose_matrix("convert.to_transform3d", "T", T)
    return _transform3d_class()(matrix=T.reshape(-1, 4, 4), dtype=T.dtype, device=T.device)


def from_transform3d(transform: Transform3d) -> Tensor:
    """Poses T = [[R, t], [0, 1]] of a ``pytorch_kinematics.transforms.Transform3d``.

    Args:
        transform: a ``Transform3d`` of length N; it must be rigid (no scale or shear),
            checked when validation is on.

    Returns:
        Poses, shape (N, 4, 4), with the transform's dtype and device.
    """
    if not isinstance(transform, _transform3d_class()):
        raise TypeError(
            "convert.from_transform3d: argument 'transform' must be a "
            f"pytorch_kinematics.transforms.Transform3d, got {type(transform).__name__}"
        )
    T = transform.get_matrix()
    _checks.check_tensor("convert.from_transform3d", "transform.get_matrix()", T, (4, 4))
    _checks.check_pose_matrix("convert.from_transform3d", "transform", T)
    return T
