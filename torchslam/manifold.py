"""Manifolds in the spirit of Ceres' ``Manifold`` (formerly ``LocalParameterization``).

A manifold couples an *ambient* representation of a variable (what is stored: a 4×4 matrix, a
unit quaternion, a 6-vector) with a *tangent* space of the right dimension (what the solver
steps in). Following the second seed (Ceres-style local parameterization):

- ``plus(x, δ)``, the retraction x ⊞ δ, e.g. T·Exp(δ) (seed eq. L1);
- ``minus(y, x)``, its inverse y ⊟ x, with ``minus(plus(x, δ), x) = δ`` for small δ and
  ``plus(x, minus(y, x)) = y``;
- ``plus_jacobian(x)`` = ∂plus(x, δ)/∂δ at δ = 0, the seed's J_GL, shape (..., ambient, tangent);
- ``minus_jacobian(x)`` = ∂minus(y, x)/∂y at y = x, shape (..., tangent, ambient); it is a left
  inverse of ``plus_jacobian(x)``;
- ``right_multiply_by_plus_jacobian(x, J_r_ambient)`` = J_rG · J_GL = J_rL (the seed's chain
  rule), shape (..., rows, tangent), computed without forming J_GL where it is structured.

Ambient coordinates are the entries of a point flattened row-major: for a point of shape
``point_shape`` the ambient index of ``x[..., i, j]`` is ``i * point_shape[1] + j``, i.e.
``x.flatten(-2)`` for matrices. A Jacobian w.r.t. a 4×4 matrix of shape (..., rows, 4, 4) (as
``torch.func.jacrev`` returns it) becomes the (..., rows, 16) that this module takes with
``.flatten(-2)``.

Implementations: :class:`Euclidean`, :class:`SE3Matrix` (4×4 rigid transforms),
:class:`SO3Quaternion` (unit quaternions) and :class:`SE3Tangent` (the design card's parameter
form, a twist ξ). Conventions: ξ = (ω, v), rotation first; right perturbation x·Exp(δ) unless
``perturbation="left"`` (Exp(δ)·x); quaternions are Hamilton, stored (w, x, y, z).

:func:`right_jacobian_jacrev` is the one ``torch.func.jacrev``-at-zero helper: the Jacobians of
any function of poses (right perturbations T·Exp(δ)) and vectors, for terms without analytic
blocks and for tests. :meth:`SE3Tangent.retract` is the solver's step on twists: the solver
(:func:`torchslam.solver.loop.retract`) steps the matrices T ← T·Exp(δ) and takes ξ = Log(T)
once at the end, the same twists bit for bit.

Every method takes arbitrary leading batch dims (leading dims of the arguments broadcast), keeps
dtype and device, is differentiable and ``torch.func`` (jacrev/vmap) compatible. Shapes and
dtypes are checked at every public method; the value checks (finite, unit norm, rigid) follow
:func:`torchslam.validation`.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from torchslam import _checks
from torchslam._batched import matmul
from torchslam.lie import convert, se3, so3

__all__ = [
    "Euclidean",
    "Manifold",
    "SE3Matrix",
    "SE3Tangent",
    "SO3Quaternion",
    "right_jacobian_jacrev",
]

Perturbation = Literal["right", "left"]
_PERTURBATIONS = ("right", "left")


def _check_perturbation(owner: str, perturbation: object) -> None:
    if perturbation not in _PERTURBATIONS:
        raise ValueError(
            f"{owner}: argument 'perturbation' must be 'right' or 'left', got {perturbation!r}"
        )


def _unchecked(f: Callable[..., Tensor], *args: Tensor) -> Tensor:
    """f(*args) with value checks off: the private math runs after the public checks, and the
    public ``lie`` functions it calls need not check (and sync) again."""
    if not _checks.value_checks_active():
        return f(*args)
    with _checks.validation(False):
        return f(*args)


def _broadcast_batch(fn: str, **batch_shapes: tuple[int, ...]) -> tuple[int, ...]:
    """Broadcast the leading (batch) shapes of named arguments; ValueError naming them if not."""
    return _checks.check_broadcast(fn, **batch_shapes)


class Manifold(abc.ABC):
    """A manifold with a retraction, in the spirit of Ceres' ``Manifold``.

    Subclasses define ``point_shape``, ``tangent_size`` and the private math (``_plus``,
    ``_minus``, ``_plus_jacobian``, ``_minus_jacobian`` and optionally a structured
    ``_right_multiply_by_plus_jacobian``); the public methods check their arguments first.

    Points have shape (..., *point_shape), tangent vectors (..., tangent_size); the ambient
    coordinates are the point's entries flattened row-major (see the module docstring).
    """

    @property
    @abc.abstractmethod
    def point_shape(self) -> tuple[int, ...]:
        """Trailing shape of one point, e.g. (4, 4) for :class:`SE3Matrix`."""

    @property
    @abc.abstractmethod
    def tangent_size(self) -> int:
        """Dimension of the tangent space (Ceres' TangentSize, the seed's local size)."""

    @property
    def ambient_size(self) -> int:
        """Number of ambient coordinates, prod(point_shape) (Ceres' AmbientSize)."""
        return math.prod(self.point_shape)

    # ----------------------------------------------------------------- public API

    def plus(self, x: Tensor, delta: Tensor) -> Tensor:
        """The retraction x ⊞ δ (Ceres' Plus; seed eq. L1 for poses).

        Args:
            x: points, shape (..., *point_shape).
            delta: tangent vectors, shape (..., tangent_size); leading dims broadcast with x's.

        Returns:
            Points, shape (broadcast batch, *point_shape).
        """
        fn = self._fn("plus")
        self._check_plus_arguments(fn, x, delta)
        result = _unchecked(self._plus, x, delta)
        _checks.check_result_finite(fn, result, x=x, delta=delta)
        return result

    def minus(self, y: Tensor, x: Tensor) -> Tensor:
        """The inverse retraction y ⊟ x (Ceres' Minus): ``plus(x, minus(y, x)) = y``.

        Args:
            y: points, shape (..., *point_shape).
            x: points, shape (..., *point_shape); leading dims broadcast with y's.

        Returns:
            Tangent vectors δ with x ⊞ δ = y, shape (broadcast batch, tangent_size).
        """
        fn = self._fn("minus")
        self._check_point_metadata(fn, "y", y)
        self._check_point_metadata(fn, "x", x)
        _checks.check_same_kind(fn, y=y, x=x)
        _broadcast_batch(fn, y=self._batch_shape(y), x=self._batch_shape(x))
        self._check_point_values(fn, "y", y)
        self._check_point_values(fn, "x", x)
        result = _unchecked(self._minus, y, x)
        _checks.check_result_finite(fn, result, y=y, x=x)
        return result

    def plus_jacobian(self, x: Tensor) -> Tensor:
        """J_GL = ∂plus(x, δ)/∂δ at δ = 0, w.r.t. δ, at x (Ceres' PlusJacobian).

        Args:
            x: points, shape (..., *point_shape).

        Returns:
            Jacobians, shape (..., ambient_size, tangent_size); rows index the row-major
            flattened point.
        """
        fn = self._fn("plus_jacobian")
        self._check_point_metadata(fn, "x", x)
        self._check_point_values(fn, "x", x)
        result = _unchecked(self._plus_jacobian, x)
        _checks.check_result_finite(fn, result, x=x)
        return result

    def minus_jacobian(self, x: Tensor) -> Tensor:
        """∂minus(y, x)/∂y at y = x, w.r.t. y, at x (Ceres' MinusJacobian).

        ``minus_jacobian(x) @ plus_jacobian(x)`` is the identity of the tangent space.

        Args:
            x: points, shape (..., *point_shape).

        Returns:
            Jacobians, shape (..., tangent_size, ambient_size); columns index the row-major
            flattened point.
        """
        fn = self._fn("minus_jacobian")
        self._check_point_metadata(fn, "x", x)
        self._check_point_values(fn, "x", x)
        result = _unchecked(self._minus_jacobian, x)
        _checks.check_result_finite(fn, result, x=x)
        return result

    def right_multiply_by_plus_jacobian(self, x: Tensor, J_r_ambient: Tensor) -> Tensor:
        """The seed's chain rule J_rL = J_rG · J_GL (Ceres' RightMultiplyByPlusJacobian).

        Turns the Jacobian of a residual w.r.t. the ambient coordinates of x into the Jacobian
        w.r.t. the tangent perturbation δ of x ⊞ δ at δ = 0, without forming J_GL where it is
        structured.

        Args:
            x: points, shape (..., *point_shape).
            J_r_ambient: ∂r/∂x, shape (..., rows, ambient_size), columns indexing the row-major
                flattened point (``jacobian.flatten(-2)`` for a (..., rows, 4, 4) one);
                leading dims broadcast with x's.

        Returns:
            ∂r(x ⊞ δ)/∂δ at δ = 0, shape (broadcast batch, rows, tangent_size).
        """
        fn = self._fn("right_multiply_by_plus_jacobian")
        self._check_point_metadata(fn, "x", x)
        _checks.check_tensor(fn, "J_r_ambient", J_r_ambient, (self.ambient_size,))
        if J_r_ambient.dim() < 2:
            raise ValueError(
                f"{fn}: argument 'J_r_ambient' must have shape (..., rows, {self.ambient_size}),"
                f" got {tuple(J_r_ambient.shape)}"
            )
        _checks.check_same_kind(fn, x=x, J_r_ambient=J_r_ambient)
        _broadcast_batch(fn, x=self._batch_shape(x), J_r_ambient=tuple(J_r_ambient.shape[:-2]))
        self._check_point_values(fn, "x", x)
        _checks.check_finite(fn, "J_r_ambient", J_r_ambient)
        result = _unchecked(self._right_multiply_by_plus_jacobian, x, J_r_ambient)
        _checks.check_result_finite(fn, result, x=x, J_r_ambient=J_r_ambient)
        return result

    # ------------------------------------------------------------- private math

    @abc.abstractmethod
    def _plus(self, x: Tensor, delta: Tensor) -> Tensor: ...

    @abc.abstractmethod
    def _minus(self, y: Tensor, x: Tensor) -> Tensor: ...

    @abc.abstractmethod
    def _plus_jacobian(self, x: Tensor) -> Tensor: ...

    @abc.abstractmethod
    def _minus_jacobian(self, x: Tensor) -> Tensor: ...

    def _right_multiply_by_plus_jacobian(self, x: Tensor, J_r_ambient: Tensor) -> Tensor:
        # Generic fallback: form J_GL and multiply.
        return J_r_ambient @ self._plus_jacobian(x)

    # ----------------------------------------------------------------- helpers

    def _fn(self, method: str) -> str:
        return f"{type(self).__name__}.{method}"

    def _check_plus_arguments(self, fn: str, x: Tensor, delta: Tensor) -> None:
        self._check_point_metadata(fn, "x", x)
        self._check_tangent_metadata(fn, "delta", delta)
        _checks.check_same_kind(fn, x=x, delta=delta)
        _broadcast_batch(fn, x=self._batch_shape(x), delta=delta.shape[:-1])
        self._check_point_values(fn, "x", x)
        _checks.check_finite(fn, "delta", delta)

    def _batch_shape(self, x: Tensor) -> tuple[int, ...]:
        return tuple(x.shape[: x.dim() - len(self.point_shape)])

    def _check_point_metadata(self, fn: str, name: str, x: object) -> None:
        _checks.check_tensor(fn, name, x, self.point_shape)

    def _check_tangent_metadata(self, fn: str, name: str, delta: object) -> None:
        _checks.check_tensor(fn, name, delta, (self.tangent_size,))

    def _check_point_values(self, fn: str, name: str, x: Tensor) -> None:
        """Value checks of a point (only when value checks are active); finite by default."""
        _checks.check_finite(fn, name, x)


# --------------------------------------------------------------------------- Euclidean


@dataclass(frozen=True)
class Euclidean(Manifold):
    """Euclidean space R^n: plus(x, δ) = x + δ, minus(y, x) = y − x, J_GL = I.

    Used for the 3D points of the ICP-SLAM problem (the seed's X_j ← X_j + δX_j).

    Args:
        n: dimension, a positive int; points and tangent vectors have shape (..., n).
    """

    n: int

    def __post_init__(self) -> None:
        if isinstance(self.n, bool) or not isinstance(self.n, int):
            raise TypeError(f"Euclidean: argument 'n' must be an int, got {type(self.n).__name__}")
        if self.n < 1:
            raise ValueError(f"Euclidean: argument 'n' must be positive, got {self.n}")

    @property
    def point_shape(self) -> tuple[int, ...]:
        return (self.n,)

    @property
    def tangent_size(self) -> int:
        return self.n

    def _plus(self, x: Tensor, delta: Tensor) -> Tensor:
        return x + delta

    def _minus(self, y: Tensor, x: Tensor) -> Tensor:
        return y - x

    def _identity(self, x: Tensor) -> Tensor:
        eye = torch.eye(self.n, dtype=x.dtype, device=x.device)
        return eye.expand(*x.shape[:-1], self.n, self.n)

    def _plus_jacobian(self, x: Tensor) -> Tensor:
        return self._identity(x)

    def _minus_jacobian(self, x: Tensor) -> Tensor:
        return self._identity(x)

    def _right_multiply_by_plus_jacobian(self, x: Tensor, J_r_ambient: Tensor) -> Tensor:
        # J_GL = I: only broadcast the batch dims.
        batch = _checks.broadcast_shapes(x.shape[:-1], J_r_ambient.shape[:-2])
        return J_r_ambient.expand(*batch, *J_r_ambient.shape[-2:])


# --------------------------------------------------------------------------- SE(3) matrices


def _se3_generators(like: Tensor) -> Tensor:
    """The six se(3) generators G_k = hat(e_k) in (ω, v) order, shape (6, 4, 4)."""
    return se3.hat(torch.eye(6, dtype=like.dtype, device=like.device))


def _two_vee(M: Tensor) -> Tensor:
    """⟨M, hat(e_k)⟩_F = (M21 − M12, M02 − M20, M10 − M01)_k; (..., 3, 3) → (..., 3)."""
    return 2.0 * so3.vee(M)


@dataclass(frozen=True)
class SE3Matrix(Manifold):
    """SE(3) stored as 4×4 rigid transforms T = [[R, t], [0, 1]], tangent ξ = (ω, v) ∈ R⁶.

    Ambient coordinates: the 16 entries of T flattened row-major (``T.flatten(-2)``), so
    ambient index 4·i + j is T[i, j]; ambient_size = 16, tangent_size = 6.

    - right (default): plus(T, δ) = T·Exp(δ) (seed eq. L1), minus(Y, T) = Log(T⁻¹·Y);
      J_GL has columns vec(T·G_k) for the generators G_k = hat(e_k) of se(3).
    - left: plus(T, δ) = Exp(δ)·T, minus(Y, T) = Log(Y·T⁻¹); columns vec(G_k·T).

    ``minus`` reads only the top 3×4 block [R_Y | t_Y] of Y (the bottom row of a rigid
    transform is constant), so ``minus_jacobian`` has zero columns for the bottom row. For right
    perturbation it is diag(½I₃, I₃)·J_GLᵀ, the pseudo-inverse of J_GL.

    Args:
        perturbation: "right" (T·Exp(δ), torchslam's default) or "left" (Exp(δ)·T).
    """

    perturbation: Perturbation = "right"

    def __post_init__(self) -> None:
        _check_perturbation("SE3Matrix", self.perturbation)

    @property
    def point_shape(self) -> tuple[int, ...]:
        return (4, 4)

    @property
    def tangent_size(self) -> int:
        return 6

    def _check_point_values(self, fn: str, name: str, x: Tensor) -> None:
        _checks.check_pose_matrix(fn, name, x)

    def _plus(self, x: Tensor, delta: Tensor) -> Tensor:
        if self.perturbation == "right":
            return x @ se3.exp(delta)
        return se3.exp(delta) @ x

    def _minus(self, y: Tensor, x: Tensor) -> Tensor:
        R, t = x[..., :3, :3], x[..., :3, 3:]
        R_y, t_y = y[..., :3, :3], y[..., :3, 3:]
        if self.perturbation == "right":
            # T⁻¹·Y = [[Rᵀ R_y, Rᵀ (t_y − t)], [0, 1]]
            Rt = R.transpose(-1, -2)
            R_rel, t_rel = Rt @ R_y, Rt @ (t_y - t)
        else:
            # Y·T⁻¹ = [[R_y Rᵀ, t_y − R_y Rᵀ t], [0, 1]]
            R_rel = R_y @ R.transpose(-1, -2)
            t_rel = t_y - R_rel @ t
        omega = so3.log(R_rel)
        v = (so3.jl_inv(omega, form="fast") @ t_rel).squeeze(-1)  # seed eq. L6, |ω| ≤ π
        return torch.cat((omega, v), dim=-1)

    def _plus_jacobian(self, x: Tensor) -> Tensor:
        G = _se3_generators(x)
        if self.perturbation == "right":
            columns = torch.einsum("...ij,kjl->...ilk", x, G)  # T·G_k
        else:
            columns = torch.einsum("kij,...jl->...ilk", G, x)  # G_k·T
        return columns.reshape(*x.shape[:-2], 16, 6)

    def _minus_jacobian(self, x: Tensor) -> Tensor:
        G = _se3_generators(x)
        R, t = x[..., :3, :3], x[..., :3, 3]
        if self.perturbation == "right":
            # dω = vee(Rᵀ dR_y) = ½⟨R·hat(e_k), dR_y⟩, dv = Rᵀ dt_y.
            rows = torch.einsum("...ij,kjl->...kil", x, G)
            scale = torch.tensor([0.5, 0.5, 0.5, 1.0, 1.0, 1.0], dtype=x.dtype, device=x.device)
            return (scale[:, None, None] * rows).reshape(*x.shape[:-2], 6, 16)
        # dω = vee(dR_y Rᵀ) = ½⟨hat(e_k)·R, dR_y⟩, dv = dt_y − dR_y Rᵀ t.
        rot = 0.5 * torch.einsum("kij,...jl->...kil", G[:3, :3, :3], R)  # (..., 3, 3, 3)
        rot = torch.cat((rot, torch.zeros_like(rot[..., :1])), dim=-1)  # (..., 3, 3, 4)
        eye = torch.eye(3, dtype=x.dtype, device=x.device)
        Rt_t = (R.transpose(-1, -2) @ t[..., None]).squeeze(-1)  # (..., 3)
        # Row k: the R block is −e_k (Rᵀ t)ᵀ, the t column is e_k.
        trans_R = -eye[:, :, None] * Rt_t[..., None, None, :]  # (..., 3, 3, 3)
        trans_t = eye.expand(*trans_R.shape[:-1])[..., None]  # (..., 3, 3, 1)
        trans = torch.cat((trans_R, trans_t), dim=-1)  # (..., 3, 3, 4)
        rows = torch.cat((rot, trans), dim=-3)  # (..., 6, 3, 4)
        rows = torch.cat((rows, torch.zeros_like(rows[..., :1, :])), dim=-2)  # (..., 6, 4, 4)
        return rows.reshape(*x.shape[:-2], 6, 16)

    def _right_multiply_by_plus_jacobian(self, x: Tensor, J_r_ambient: Tensor) -> Tensor:
        # Column k of J_rL is ⟨A, T·G_k⟩ = ⟨Tᵀ A, G_k⟩ (right) or ⟨A, G_k·T⟩ = ⟨A Tᵀ, G_k⟩
        # (left), with A = ∂r/∂T reshaped to 4×4 per row: O(rows · 36) instead of a 16×6 GEMM.
        A = J_r_ambient.reshape(*J_r_ambient.shape[:-1], 4, 4)
        A_R, A_t = A[..., :3, :3], A[..., :3, 3]
        R = x[..., None, :3, :3]
        if self.perturbation == "right":
            Rt = R.transpose(-1, -2)
            J_omega = _two_vee(Rt @ A_R)
            J_v = (Rt @ A_t[..., None]).squeeze(-1)
        else:
            t = x[..., None, :3, 3]
            M = A_R @ R.transpose(-1, -2) + A_t[..., :, None] * t[..., None, :]
            J_omega = _two_vee(M)
            J_v = A_t.expand_as(J_omega)
        return torch.cat(torch.broadcast_tensors(J_omega, J_v), dim=-1)


# --------------------------------------------------------------------------- SO(3) quaternions


@dataclass(frozen=True)
class SO3Quaternion(Manifold):
    """SO(3) stored as unit quaternions q = (w, x, y, z) (Hamilton, as in Ceres), tangent R³.

    Ambient coordinates: (w, x, y, z); ambient_size = 4, tangent_size = 3. With the quaternion
    exponential Exp(δ) = (cos(θ/2), sin(θ/2) δ/θ), θ = |δ|:

    - right (default): plus(q, δ) = q ⊗ Exp(δ), minus(p, q) = Log(q* ⊗ p), and
      J_GL = [q]_L · ½[0; I₃], the seed's Q_δθ;
    - left: plus(q, δ) = Exp(δ) ⊗ q, minus(p, q) = Log(p ⊗ q*), J_GL = [q]_R · ½[0; I₃].

    ``minus`` returns the shortest rotation (angle ≤ π) since q and −q are the same rotation, so
    ``plus(q, minus(p, q))`` equals p or −p. ``minus_jacobian`` is 2·[q*]_L[1:4, :] (right) or
    2·[q*]_R[1:4, :] (left), the pseudo-inverse of J_GL. ``plus`` keeps |q| = 1 up to
    round-off; it does not renormalize.

    Args:
        perturbation: "right" (q ⊗ Exp(δ), torchslam's default) or "left" (Exp(δ) ⊗ q).
    """

    perturbation: Perturbation = "right"

    def __post_init__(self) -> None:
        _check_perturbation("SO3Quaternion", self.perturbation)

    @property
    def point_shape(self) -> tuple[int, ...]:
        return (4,)

    @property
    def tangent_size(self) -> int:
        return 3

    def _check_point_values(self, fn: str, name: str, x: Tensor) -> None:
        _checks.check_unit_quaternion(fn, name, x)

    def _plus(self, x: Tensor, delta: Tensor) -> Tensor:
        if self.perturbation == "right":
            return convert.quaternion_multiply(x, convert.axis_angle_to_quaternion(delta))
        return convert.quaternion_multiply(convert.axis_angle_to_quaternion(delta), x)

    def _minus(self, y: Tensor, x: Tensor) -> Tensor:
        if self.perturbation == "right":
            relative = convert.quaternion_multiply(convert.quaternion_conjugate(x), y)
        else:
            relative = convert.quaternion_multiply(y, convert.quaternion_conjugate(x))
        return convert.quaternion_to_axis_angle(relative)  # angle ≤ π (q ≡ −q)

    def _plus_jacobian(self, x: Tensor) -> Tensor:
        # ∂(q ⊗ δq)/∂δq · ∂δq/∂δ = [q]_L · ½[0; I₃]: columns 1..3 of [q]_L, halved.
        if self.perturbation == "right":
            return 0.5 * convert.quaternion_product_matrix(x, "left")[..., :, 1:]
        return 0.5 * convert.quaternion_product_matrix(x, "right")[..., :, 1:]

    def _minus_jacobian(self, x: Tensor) -> Tensor:
        # Log(u) = 2 v/w + O(|v|²) at u = (1, 0): d minus = 2 · (vector rows of d(q* ⊗ y)).
        x_conjugate = convert.quaternion_conjugate(x)
        if self.perturbation == "right":
            return 2.0 * convert.quaternion_product_matrix(x_conjugate, "left")[..., 1:, :]
        return 2.0 * convert.quaternion_product_matrix(x_conjugate, "right")[..., 1:, :]


# --------------------------------------------------------------------------- SE(3) twists


@dataclass(frozen=True)
class SE3Tangent(Manifold):
    """SE(3) stored as a twist ξ = (ω, v), rotation first (the design card's parameter form).

    Ambient and tangent are both R⁶ (ambient_size = tangent_size = 6), and the retraction is
    taken on the group, returning the principal logarithm (|ω| ≤ π):

    - right (default): plus(ξ, δ) = Log(Exp(ξ)·Exp(δ)), minus(η, ξ) = Log(Exp(ξ)⁻¹·Exp(η)),
      plus_jacobian(ξ) = jr_inv(ξ) and minus_jacobian(ξ) = jr(ξ), since
      Exp(ξ + jr_inv(ξ) δ) ≈ Exp(ξ)·Exp(δ);
    - left: plus(ξ, δ) = Log(Exp(δ)·Exp(ξ)), minus(η, ξ) = Log(Exp(η)·Exp(ξ)⁻¹),
      plus_jacobian(ξ) = jl_inv(ξ), minus_jacobian(ξ) = jl(ξ).

    Points must lie in the principal domain |ω| ≤ π (checked when validation is on): there
    ``plus(ξ, 0) = ξ`` (for |ω| < π; at |ω| = π, ±ω are the same rotation). ``plus`` may wrap a
    step across |ω| = π to the equivalent twist on the other side; ``minus`` is taken on the
    group and is unaffected.

    Args:
        perturbation: "right" (Exp(ξ)·Exp(δ), torchslam's default) or "left" (Exp(δ)·Exp(ξ)).
    """

    perturbation: Perturbation = "right"

    def __post_init__(self) -> None:
        _check_perturbation("SE3Tangent", self.perturbation)

    @property
    def point_shape(self) -> tuple[int, ...]:
        return (6,)

    @property
    def tangent_size(self) -> int:
        return 6

    def _check_point_values(self, fn: str, name: str, x: Tensor) -> None:
        _checks.check_finite(fn, name, x)
        if not _checks.value_checks_active() or x.numel() == 0:
            return
        angle = torch.linalg.vector_norm(x.detach()[..., :3], dim=-1)
        limit = math.pi + _checks.orthonormality_tolerance(x.dtype)
        bad = ~(angle <= limit)  # NaN-safe
        if bool(bad.any()):
            idx = tuple(int(i) for i in bad.nonzero()[0].tolist())
            raise ValueError(
                f"{fn}: argument '{name}' must have rotation angle |ω| ≤ π (the principal "
                f"logarithm); at batch index {idx} |ω| = {float(angle[idx]):.6g}. Wrap it first "
                "with se3.log(se3.exp(xi))"
            )

    def retract(
        self, x: Tensor, delta: Tensor, *, exp_x: Tensor | None = None, with_exp: bool = False
    ) -> Tensor | tuple[Tensor, Tensor]:
        """The solver's step on twists, ξ ← Log(Exp(ξ)·Exp(δ)) (left: Log(Exp(δ)·Exp(ξ))), seed
        eq. L1/L2 (the solver steps Exp(ξ) and takes the Log once, with the same result).

        The same values as :meth:`plus` (bit for bit for |ω|, |δω| ≤ 2²⁰ and translations up
        to 2⁵¹², float64; 2¹⁰ and 2⁶⁴ in float32), computed with the cheaper θ-power forms
        (``se3.exp(..., form="fast")``), except that a row whose δ is exactly zero keeps ξ bit
        for bit (a fixed pose; the Log∘Exp round trip would move it by a few ulps). Its
        derivative with respect to δ on such a row is therefore zero: differentiate
        :meth:`plus` for the chart's Jacobian. Checks as :meth:`plus` (under
        ``torchslam.validation(False)`` only the cheap shape and dtype checks run).

        Args:
            x: twists ξ = (ω, v), rotation first, |ω| ≤ π, shape (..., 6).
            delta: steps δ = (δω, δv), shape (..., 6); leading dims broadcast with x's.
            exp_x: ``se3.exp(x, form="fast")`` when the caller has it already (the solver's
                linearization does), shape (..., 4, 4); it is used as given.
            with_exp: also return the moved pose matrices Exp(ξ)·Exp(δ) (exp_x itself on the
                rows whose δ is zero), whose Log the twists are: the solver linearizes at them
                instead of taking Exp of the twists again.

        Returns:
            Twists, shape (broadcast batch, 6); with ``with_exp`` the pair (twists, matrices
            (broadcast batch, 4, 4)).
        """
        fn = "SE3Tangent.retract"
        self._check_plus_arguments(fn, x, delta)
        if exp_x is not None:
            _checks.check_tensor(fn, "exp_x", exp_x, (4, 4))
            if exp_x.shape[:-2] != x.shape[:-1]:
                raise ValueError(
                    f"{fn}: argument 'exp_x' must be Exp(x), shape {tuple(x.shape[:-1])} + "
                    f"(4, 4), got {tuple(exp_x.shape)}"
                )
        result, moved = _unchecked(self._retract, x, delta, exp_x)
        _checks.check_result_finite(fn, result, x=x, delta=delta)
        return (result, moved) if with_exp else result

    def _retract(
        self, x: Tensor, delta: Tensor, exp_x: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        T = se3.exp(x, form="fast") if exp_x is None else exp_x
        step = se3.exp(delta, form="fast")
        moved = matmul(T, step) if self.perturbation == "right" else matmul(step, T)
        keep = (delta == 0).all(dim=-1, keepdim=True)
        return torch.where(keep, x, se3.log(moved)), torch.where(keep[..., None], T, moved)

    def _plus(self, x: Tensor, delta: Tensor) -> Tensor:
        if self.perturbation == "right":
            return se3.log(matmul(se3.exp(x), se3.exp(delta)))
        return se3.log(matmul(se3.exp(delta), se3.exp(x)))

    def _minus(self, y: Tensor, x: Tensor) -> Tensor:
        if self.perturbation == "right":
            return se3.log(se3.inverse(se3.exp(x)) @ se3.exp(y))
        return se3.log(se3.exp(y) @ se3.inverse(se3.exp(x)))

    def _plus_jacobian(self, x: Tensor) -> Tensor:
        if self.perturbation == "right":
            return se3.jr_inv(x)
        return se3.jl_inv(x)

    def _minus_jacobian(self, x: Tensor) -> Tensor:
        if self.perturbation == "right":
            return se3.jr(x)
        return se3.jl(x)


# --------------------------------------------------------------------------- jacrev at zero


def right_jacobian_jacrev(
    fn: Callable[..., Tensor],
    poses: Sequence[Tensor],
    euclidean: Sequence[Tensor] = (),
    constants: Sequence[Tensor] | Mapping[str, Tensor] = (),
    *,
    batch_dims: int | None = None,
) -> tuple[Tensor, ...]:
    """Jacobians of ``fn`` w.r.t. right pose perturbations and vector increments, at zero.

    For each instance (one index into the leading ``batch_dims`` dims) this differentiates

        fn(T_1·Exp(δ_1), …, T_p·Exp(δ_p), x_1 + d_1, …, x_e + d_e, *constants)

    (``**constants`` when ``constants`` is a mapping) with ``torch.func.jacrev`` w.r.t. every
    δ_k and d_k at δ = 0, d = 0 (seed eq. L1: right perturbation T·Exp(δ); δ = (ω, v),
    rotation first), ``torch.func.vmap``-ed over the instances. This is the seed's "Jacobian
    w.r.t. the error state"; the solver's analytic blocks follow the same convention.

    Shapes: the first ``batch_dims`` dims of every argument index the instances (they
    broadcast); the dims after them belong to one instance. A pose argument has shape
    (*batch, *inner, 4, 4) (``inner`` may be empty, or e.g. (a,) for a term that touches a
    poses per instance), a vector argument (*batch, *inner, n), a constant (*batch, *any).
    ``fn`` is called with one instance's slices, (*inner, 4, 4), (*inner, n), (*any), and
    returns shape (*out) (e.g. (d,) for a residual); a function written batched over leading
    dims (``...``) works as is.

    Args:
        fn: the function, e.g. a residual; called as described above.
        poses: pose arguments, each (*batch, *inner, 4, 4), rigid transforms [[R, t], [0, 1]].
        euclidean: vector arguments, each (*batch, *inner, n).
        constants: further arguments passed as they are: a sequence (positional, after the
            vectors) or a mapping of names to tensors (keyword arguments), each (*batch, …).
        batch_dims: the number of leading instance dims; default: those of ``poses[0]``
            (``poses[0].dim() - 2``), or of ``euclidean[0]`` (``dim() - 1``) without poses.

    Returns:
        One Jacobian per pose, shape (*batch, *out, *inner, 6), then one per vector, shape
        (*batch, *out, *inner, n); float, with the poses' dtype and device.
    """
    name = "right_jacobian_jacrev"
    if not callable(fn):
        raise TypeError(f"{name}: argument 'fn' must be callable, got {_checks.describe(fn)}")
    poses = _checks.check_sequence(name, "poses", poses, Tensor, "tensors")
    euclidean = _checks.check_sequence(name, "euclidean", euclidean, Tensor, "tensors")
    keyword = isinstance(constants, Mapping)
    constant_names = tuple(constants) if keyword else ()
    if keyword and not all(isinstance(k, str) for k in constant_names):
        raise TypeError(f"{name}: the keys of argument 'constants' must be str")
    constant_values = _checks.check_sequence(
        name,
        "constants",
        tuple(constants.values()) if keyword else constants,
        Tensor,
        "tensors",
    )
    if not poses and not euclidean:
        raise ValueError(
            f"{name}: there is nothing to differentiate: 'poses' and 'euclidean' are empty"
        )
    if batch_dims is None:
        batch_dims = poses[0].dim() - 2 if poses else euclidean[0].dim() - 1
    batch_dims = _checks.check_int(name, "batch_dims", batch_dims, minimum=0)
    for k, T in enumerate(poses):
        _checks.check_tensor(name, f"poses[{k}]", T, (4, 4), min_batch_dims=batch_dims)
    for k, x in enumerate(euclidean):
        _checks.check_tensor(name, f"euclidean[{k}]", x)
        if x.dim() < batch_dims + 1:
            raise ValueError(
                f"{name}: argument 'euclidean[{k}]' must have shape (*batch, *inner, n) with "
                f"{batch_dims} batch dim(s), got {tuple(x.shape)}"
            )
    for k, c in enumerate(constant_values):
        _checks.check_tensor(
            name, f"constants[{k}]", c, (), min_batch_dims=batch_dims, floating=False
        )
    variables = {f"poses[{k}]": T for k, T in enumerate(poses)}
    variables.update({f"euclidean[{k}]": x for k, x in enumerate(euclidean)})
    _checks.check_same_kind(name, **variables)
    first = next(iter(variables.values()))
    for k, c in enumerate(constant_values):
        if c.device != first.device:
            raise ValueError(
                f"{name}: 'constants[{k}]' is on {c.device} but the variables are on "
                f"{first.device}; move one of them first"
            )
    arguments = (*poses, *euclidean, *constant_values)
    names = (*variables, *(f"constants[{k}]" for k in range(len(constant_values))))
    batch = _checks.check_broadcast(
        name, **{n: a.shape[:batch_dims] for n, a in zip(names, arguments, strict=True)}
    )
    for n, value in variables.items():
        _checks.check_finite(name, n, value)

    def perturbed(
        deltas: tuple[Tensor, ...], vectors: tuple[Tensor, ...], Ts: tuple[Tensor, ...], cs: tuple
    ) -> Tensor:
        moved = tuple(T @ se3.exp(d, form="fast") for T, d in zip(Ts, deltas, strict=True))
        if keyword:
            return fn(*moved, *vectors, **dict(zip(constant_names, cs, strict=True)))
        return fn(*moved, *vectors, *cs)

    def instance(a: Tensor) -> Tensor:  # (*batch, *rest) → (N, *rest)
        return a.expand(*batch, *a.shape[batch_dims:]).reshape(-1, *a.shape[batch_dims:])

    Ts = tuple(instance(T) for T in poses)
    vectors = tuple(instance(x) for x in euclidean)
    cs = tuple(instance(c) for c in constant_values)
    deltas = tuple(T.new_zeros(*T.shape[:-2], 6) for T in Ts)
    jacobian = torch.func.jacrev(perturbed, argnums=(0, 1))
    if math.prod(batch) == 0:
        # vmap cannot map over zero instances: learn the shapes from one dummy instance
        # (identity poses, zero vectors and constants), then return empty blocks.
        J_delta, J_vector = jacobian(
            tuple(d.new_zeros(d.shape[1:]) for d in deltas),
            tuple(x.new_zeros(x.shape[1:]) for x in vectors),
            tuple(_identity(T.shape[1:-2], T) for T in Ts),
            tuple(c.new_zeros(c.shape[1:]) for c in cs),
        )
        return tuple(J.new_zeros(*batch, *J.shape) for J in (*J_delta, *J_vector))
    J_delta, J_vector = torch.func.vmap(jacobian)(deltas, vectors, Ts, cs)
    return tuple(J.reshape(*batch, *J.shape[1:]) for J in (*J_delta, *J_vector))


def _identity(batch: Sequence[int], like: Tensor) -> Tensor:
    return torch.eye(4, dtype=like.dtype, device=like.device).expand(*batch, 4, 4).clone()
