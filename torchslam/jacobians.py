"""Jacobians of the ICP-SLAM residual, three ways: analytic, ``torch.func.jacrev``, dense.

Residual of one observation e = (i, j):  r = X_ij − T_i0 X_j = X_ij − (R_i X_j + t_i).

Derivation of the analytic pose block (right perturbation, the torchslam default).
Perturb the pose on the manifold, T_i0 ← T_i0 · Exp(δ) with δ = (δω, δv) (seed eq. L1):

    T Exp(δ) X ≈ T (I + [δ]^) X = R (X + δω × X + δv) + t = R X + t + R (−[X]× δω + δv)

so  ∂r/∂δ = −R [ −[X]× | I ] = [ R [X]× | −R ]   (3 × 6, columns in the seed's (ω, v) order)
and ∂r/∂X = −R                                  (3 × 3).

The seed's eq. 1.5.1 is the LEFT-perturbation form, Exp(δ) · T: there the derivative of
T X is [ −[T X]× | I ] (its blocks written in (v, ω) order as [ I | −[TX]× ]). The two are
related by the adjoint, J_right = J_left · Ad(T), since T Exp(δ) = Exp(Ad(T) δ) T.

Note the structure J_pose = J_point · G_j with G_j = [ −[X_j]× | I ]: both blocks share the
factor −R, which the solver does not need to know about but which the tests check.

The ``jacrev`` path differentiates the residual of x ⊞ δ at δ = 0 — the seed's "Jacobian
w.r.t. the error state" — with ``torch.func.jacrev`` vmapped over observations; it must agree
with the analytic blocks to round-off.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from torchslam import _checks, manifold
from torchslam.lie import se3, so3

__all__ = [
    "DENSE_JACOBIAN_MAX_ENTRIES",
    "analytic_blocks",
    "central_difference_blocks",
    "dense_jacobian",
    "jacrev_blocks",
    "observation_residual",
]

# dense_jacobian refuses to build more entries than this (400 MB in float64): it is for small
# problems and debugging only; the solver never builds it.
DENSE_JACOBIAN_MAX_ENTRIES = 50_000_000


def observation_residual(
    pose_tangent: Tensor, delta: Tensor, point: Tensor, observation: Tensor
) -> Tensor:
    """Residual of observations under the right perturbation: X_obs − (Exp(ξ) Exp(δ)) X.

    Args:
        pose_tangent: pose ξ = (ω, v) of the observing frame, shape (..., 6).
        delta: right perturbation δ = (δω, δv), shape (..., 6).
        point: world point X, shape (..., 3).
        observation: observed point in the frame, shape (..., 3).

    Returns:
        Residuals, shape (..., 3).
    """
    T = se3.exp(pose_tangent, form="fast") @ se3.exp(delta, form="fast")
    return observation - se3.act(T, point)


def analytic_blocks(R: Tensor, points: Tensor) -> tuple[Tensor, Tensor]:
    """Analytic Jacobian blocks of r = X_obs − (R X + t) (right perturbation, (ω, v) order).

    Args:
        R: rotation of the observing pose per observation, shape (..., 3, 3).
        points: world point per observation, shape (..., 3).

    Returns:
        (J_r_xi, J_r_point): ∂r/∂δ = [R [X]× | −R], shape (..., 3, 6), and ∂r/∂X = −R,
        shape (..., 3, 3).
    """
    fn = "jacobians.analytic_blocks"
    _checks.check_tensor(fn, "R", R, (3, 3))
    _checks.check_tensor(fn, "points", points, (3,))
    _checks.check_same_kind(fn, R=R, points=points)
    _check_lead(fn, R=R.shape[:-2], points=points.shape[:-1])
    J_r_point = -R
    J_r_xi = torch.cat((R @ so3.hat(points), J_r_point), dim=-1)
    return J_r_xi, J_r_point


def jacrev_blocks(
    pose_tangent: Tensor, points: Tensor, observations: Tensor
) -> tuple[Tensor, Tensor]:
    """The same blocks as :func:`analytic_blocks` from ``torch.func.jacrev`` at δ = 0.

    Differentiates r(Exp(ξ)·Exp(δ), X) w.r.t. δ and X with
    :func:`torchslam.manifold.right_jacobian_jacrev`, vmapped over observations.

    Args:
        pose_tangent: pose ξ of the observing frame per observation, shape (..., 6).
        points: world point per observation, shape (..., 3).
        observations: observed points, shape (..., 3).

    Returns:
        (J_r_xi (..., 3, 6), J_r_point (..., 3, 3)).
    """
    fn = "jacobians.jacrev_blocks"
    _check_observation_args(fn, pose_tangent, points, observations)
    return _jacrev_blocks_at(se3.exp(pose_tangent, form="fast"), points, observations)


def _jacrev_blocks_at(T: Tensor, points: Tensor, observations: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`jacrev_blocks` at pose matrices T (..., 4, 4) instead of twists (the solver's
    iterate), unchecked."""
    return manifold.right_jacobian_jacrev(
        _residual_at, (T,), (points,), (observations,), batch_dims=points.dim() - 1
    )


def _residual_at(T: Tensor, point: Tensor, observation: Tensor) -> Tensor:
    """r = X_obs − T X for one observation: T (4, 4), X and X_obs (3,)."""
    return observation - se3.act(T, point)


def central_difference_blocks(
    pose_tangent: Tensor, points: Tensor, observations: Tensor, eps: float = 1e-6
) -> tuple[Tensor, Tensor]:
    """The same blocks by central differences on the manifold (for tests and debugging).

    Perturbs δ (6 directions) and X (3 directions) by ±eps, vectorized over observations.

    Returns:
        (J_r_xi (..., 3, 6), J_r_point (..., 3, 3)).
    """
    fn = "jacobians.central_difference_blocks"
    _check_observation_args(fn, pose_tangent, points, observations)
    if isinstance(eps, bool) or not isinstance(eps, (int, float)) or not (0 < eps < 1):
        raise ValueError(f"{fn}: 'eps' must be a number in (0, 1), got {eps!r}")
    delta0 = torch.zeros_like(pose_tangent)

    def columns(f: Callable[[Tensor], Tensor], base: Tensor) -> Tensor:
        eye = torch.eye(base.shape[-1], dtype=base.dtype, device=base.device)
        cols = [(f(base + eps * e) - f(base - eps * e)) / (2 * eps) for e in eye]
        return torch.stack(cols, dim=-1)

    J_xi = columns(lambda d: observation_residual(pose_tangent, d, points, observations), delta0)
    J_point = columns(lambda X: observation_residual(pose_tangent, delta0, X, observations), points)
    return J_xi, J_point


def dense_jacobian(
    J_r_xi: Tensor,
    J_r_point: Tensor,
    pose_index: Tensor,
    point_index: Tensor,
    num_poses: int,
    num_points: int,
) -> Tensor:
    """Assemble the seed's overall Jacobian, shape (B, 3E, 6m + 3n): small problems only.

    Row triple e holds J_r_xi[e] in the columns 6·i(e) … 6·i(e)+5 of its pose and
    J_r_point[e] in the columns 6m + 3·j(e) … of its point; everything else is zero.

    Args:
        J_r_xi: pose blocks, shape (B, E, 3, 6).
        J_r_point: point blocks, shape (B, E, 3, 3).
        pose_index: pose of each observation, shape (B, E).
        point_index: point of each observation, shape (B, E).
        num_poses: m.
        num_points: n.

    Raises:
        ValueError: above DENSE_JACOBIAN_MAX_ENTRIES entries.
    """
    fn = "jacobians.dense_jacobian"
    for name, size in (("num_poses", num_poses), ("num_points", num_points)):
        if isinstance(size, bool) or not isinstance(size, int) or size < 0:
            raise ValueError(f"{fn}: '{name}' must be an int ≥ 0, got {size!r}")
    for name, index in (("pose_index", pose_index), ("point_index", point_index)):
        if not isinstance(index, Tensor):
            raise TypeError(f"{fn}: '{name}' must be a torch.Tensor, got {_checks.describe(index)}")
        if index.dtype.is_floating_point or index.dtype.is_complex or index.dtype == torch.bool:
            raise TypeError(f"{fn}: '{name}' must be an integer tensor, got {index.dtype}")
        if index.dim() != 2:
            raise ValueError(f"{fn}: '{name}' must have shape (B, E), got {tuple(index.shape)}")
    if pose_index.shape != point_index.shape:
        raise ValueError(
            f"{fn}: 'pose_index' {tuple(pose_index.shape)} and 'point_index' "
            f"{tuple(point_index.shape)} must have the same shape (B, E)"
        )
    B, E = pose_index.shape
    _checks.check_batched(fn, "J_r_xi", J_r_xi, ("B", "E"), (3, 6), (B, E), against="the indices")
    _checks.check_batched(
        fn, "J_r_point", J_r_point, ("B", "E"), (3, 3), (B, E), against="the indices"
    )
    _checks.check_same_kind(fn, J_r_xi=J_r_xi, J_r_point=J_r_point)
    cols = 6 * num_poses + 3 * num_points
    if B * 3 * E * cols > DENSE_JACOBIAN_MAX_ENTRIES:
        raise ValueError(
            f"dense_jacobian: a dense Jacobian of shape ({B}, {3 * E}, {cols}) has "
            f"{B * 3 * E * cols:,} entries, above the limit of {DENSE_JACOBIAN_MAX_ENTRIES:,} "
            "(torchslam.jacobians.DENSE_JACOBIAN_MAX_ENTRIES); it is meant for small problems "
            "and debugging — the solver uses the per-observation blocks instead"
        )
    if _checks.value_checks_active():
        for name, index, size in (
            ("pose_index", pose_index, num_poses),
            ("point_index", point_index, num_points),
        ):
            bad = (index < 0) | (index >= size)
            if bool(bad.any()):
                b, e = (int(i) for i in bad.nonzero()[0])
                raise ValueError(
                    f"{fn}: '{name}' out of range [0, {size}): entry ({b}, {e}) is "
                    f"{int(index[b, e])}"
                )
    pose_index = pose_index.long()
    point_index = point_index.long()
    J = J_r_xi.new_zeros(B, E, 3, cols)
    arange6 = torch.arange(6, device=J.device)
    arange3 = torch.arange(3, device=J.device)
    pose_cols = (6 * pose_index)[..., None] + arange6  # (B, E, 6)
    point_cols = (6 * num_poses + 3 * point_index)[..., None] + arange3  # (B, E, 3)
    J.scatter_(-1, pose_cols[..., None, :].expand(B, E, 3, 6), J_r_xi)
    J.scatter_(-1, point_cols[..., None, :].expand(B, E, 3, 3), J_r_point)
    return J.reshape(B, 3 * E, cols)


def _check_lead(fn: str, **shapes: torch.Size) -> None:
    """The named arguments' leading (per-observation) shapes must agree."""
    items = list(shapes.items())
    name0, lead0 = items[0]
    for name, lead in items[1:]:
        if tuple(lead) != tuple(lead0):
            raise ValueError(
                f"{fn}: '{name0}' and '{name}' must have the same leading shape, got "
                f"{tuple(lead0)} and {tuple(lead)}"
            )


def _check_observation_args(
    fn: str, pose_tangent: object, points: object, observations: object
) -> None:
    _checks.check_tensor(fn, "pose_tangent", pose_tangent, (6,))
    _checks.check_tensor(fn, "points", points, (3,))
    _checks.check_tensor(fn, "observations", observations, (3,))
    _checks.check_same_kind(fn, pose_tangent=pose_tangent, points=points, observations=observations)
    _check_lead(
        fn,
        pose_tangent=pose_tangent.shape[:-1],
        points=points.shape[:-1],
        observations=observations.shape[:-1],
    )
