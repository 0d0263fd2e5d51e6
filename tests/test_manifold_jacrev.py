"""Tests of manifold.right_jacobian_jacrev (the one jacrev-at-zero helper) and SE3Tangent.retract.

Hard inputs (tests/helpers.py): every pose angle θ ∈ {0, 1e-12, 1e-8, 1e-4, 0.3, 0.5, π/2,
π − 1e-6, π} with tiny and huge translations. Jacobians are compared with the analytic blocks
(to round-off) and with central differences on the manifold, T·Exp(±ε e_k).
"""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor

from tests.helpers import HARD_ANGLES, HARD_TRANSLATIONS, rotation_vectors_with_angles
from torchslam import jacobians, validation
from torchslam.lie import se3
from torchslam.manifold import SE3Tangent, right_jacobian_jacrev
from torchslam.posegraph.between import between_jacobians

F64 = torch.float64


def _principal_twists(generator: torch.Generator) -> Tensor:
    """Twists over every hard angle (≤ π) × translation magnitude, shape (N, 6), float64."""
    omega = rotation_vectors_with_angles(HARD_ANGLES, generator, per_angle=2)
    rows = []
    for scale in HARD_TRANSLATIONS:
        v = scale * torch.randn(omega.shape[0], 3, generator=generator, dtype=F64)
        rows.append(torch.cat((omega, v), dim=-1))
    return torch.cat(rows)


def _hard_poses(generator: torch.Generator) -> Tensor:
    """Poses over every hard angle × translation magnitude, shape (N, 4, 4), float64."""
    return se3.exp(_principal_twists(generator))


def _between(T_i: Tensor, T_j: Tensor, Z: Tensor) -> Tensor:
    return se3.log(se3.inverse(Z) @ (se3.inverse(T_i) @ T_j))


def _between_setup(generator: torch.Generator) -> tuple[Tensor, Tensor, Tensor]:
    """T_i over the hard inputs, T_j a shuffled copy, Z within ~0.3 rad of T_i⁻¹ T_j (a residual
    away from π, where Log would wrap under the finite-difference steps)."""
    T_i = _hard_poses(generator)
    T_j = T_i[torch.randperm(T_i.shape[0], generator=generator)]
    noise = 0.1 * torch.randn(T_i.shape[0], 6, generator=generator, dtype=F64)
    return T_i, T_j, se3.inverse(T_i) @ T_j @ se3.exp(noise)


def _central_differences(f, poses: list[Tensor], k: int, eps: float) -> Tensor:
    """∂f(…, T_k·Exp(δ), …)/∂δ at 0 by central differences, batched: (N, d, 6)."""
    columns = []
    for e in torch.eye(6, dtype=F64):
        plus = [T @ se3.exp(eps * e) if j == k else T for j, T in enumerate(poses)]
        minus = [T @ se3.exp(-eps * e) if j == k else T for j, T in enumerate(poses)]
        columns.append((f(*plus) - f(*minus)) / (2 * eps))
    return torch.stack(columns, dim=-1)


def test_between_blocks_equal_the_analytic_ones_on_hard_inputs(generator):
    T_i, T_j, Z = _between_setup(generator)
    J_i, J_j = right_jacobian_jacrev(_between, (T_i, T_j), constants=(Z,))
    _, A_i, A_j = between_jacobians(T_i, T_j, Z)
    assert J_i.shape == J_j.shape == (T_i.shape[0], 6, 6)
    # The same chain rule evaluated in another order. The residual's translation is a
    # difference of the poses' translations (up to 1e4): its round-off, ε·(1 + Σ|t|), enters
    # both blocks through Jr⁻¹(r); the huge translations also enter Ad(T_j⁻¹ T_i) linearly.
    eps = torch.finfo(F64).eps
    size = 1 + sum(T[..., :3, 3].norm(dim=-1) for T in (T_i, T_j, Z))[:, None, None]
    scale = A_i.abs().amax(dim=(-1, -2), keepdim=True).clamp_min(1.0)
    assert bool(((J_i - A_i) / scale).abs().le(16 * eps * size).all())
    assert bool((J_j - A_j).abs().le(16 * eps * size).all())


def test_between_blocks_equal_central_differences_on_hard_inputs(generator):
    T_i, T_j, Z = _between_setup(generator)
    J_i, J_j = right_jacobian_jacrev(_between, (T_i, T_j), constants=(Z,))
    # ε = 1e-6: truncation O(ε²) ≈ 1e-12 relative, round-off ≈ 1e-16·|r|/ε ≈ 1e-10·|r| with
    # |r| up to ~1e4 (huge translations), so 1e-5 relative to max(1, |J|) holds on every IEEE
    # machine with a wide margin.
    for k, J in enumerate((J_i, J_j)):
        reference = _central_differences(lambda a, b: _between(a, b, Z), [T_i, T_j], k, eps=1e-6)
        scale = reference.abs().amax(dim=(-1, -2), keepdim=True).clamp_min(1.0)
        assert float(((J - reference) / scale).abs().max()) <= 1e-5


def test_point_blocks_equal_the_analytic_ones_on_hard_inputs(generator):
    T = _hard_poses(generator)
    X = 100.0 * torch.randn(T.shape[0], 3, generator=generator, dtype=F64)
    observed = torch.randn(T.shape[0], 3, generator=generator, dtype=F64)
    J_pose, J_point = right_jacobian_jacrev(
        lambda T, X, o: o - se3.act(T, X), (T,), (X,), (observed,)
    )
    A_pose, A_point = jacobians.analytic_blocks(T[..., :3, :3], X)
    # Products of O(1) rotations with |X| ≤ ~400: round-off ≤ ~1e-13 absolute.
    assert float((J_pose - A_pose).abs().max()) <= 1e-12
    assert float((J_point - A_point).abs().max()) <= 1e-14


@pytest.mark.parametrize("batch", [(), (1,), (3, 1, 2)], ids=str)
def test_batch_shapes_and_broadcast_constants(batch, generator):
    xi = torch.randn(*batch, 2, 6, generator=generator, dtype=F64)
    T = se3.exp(xi)
    Z = se3.exp(torch.randn(6, generator=generator, dtype=F64))
    # One prior per instance and a constant broadcast over the batch (leading dims of size 1).
    Z = Z.expand(*(1 for _ in batch), 4, 4) if batch else Z
    (J,) = right_jacobian_jacrev(
        lambda P, Z: se3.log(se3.inverse(Z) @ P[..., 0, :, :] @ P[..., 1, :, :]),
        (T,),
        constants=(Z,),
        batch_dims=len(batch),
    )
    assert J.shape == (*batch, 6, 2, 6)
    flat_T, flat_J = T.reshape(-1, 2, 4, 4), J.reshape(-1, 6, 2, 6)
    for n in range(flat_T.shape[0]):
        (one,) = right_jacobian_jacrev(
            lambda P: se3.log(se3.inverse(Z.reshape(4, 4)) @ P[0] @ P[1]),
            (flat_T[n],),
            batch_dims=0,
        )
        assert torch.allclose(flat_J[n], one, rtol=0, atol=1e-14)


def test_term_layout_with_keyword_constants(generator):
    # A term over a = 2 poses per instance, batch (B, K) = (2, 3): poses (B, K, a, 4, 4) and
    # keyword constants (B, K, …), as the solver's term layer calls it.
    B, K = 2, 3
    P = se3.exp(torch.randn(B, K, 2, 6, generator=generator, dtype=F64))
    noise = 0.1 * torch.randn(B, K, 6, generator=generator, dtype=F64)
    Z = se3.inverse(P[..., 0, :, :]) @ P[..., 1, :, :] @ se3.exp(noise)

    def residual(poses: Tensor, measurements: Tensor) -> Tensor:
        return _between(poses[..., 0, :, :], poses[..., 1, :, :], measurements)

    (J,) = right_jacobian_jacrev(residual, (P,), constants={"measurements": Z}, batch_dims=2)
    assert J.shape == (B, K, 6, 2, 6)
    _, A_i, A_j = between_jacobians(P[..., 0, :, :], P[..., 1, :, :], Z)
    assert float((J[..., 0, :] - A_i).abs().max()) <= 1e-12
    assert float((J[..., 1, :] - A_j).abs().max()) <= 1e-12


def test_empty_batch_gives_empty_blocks_of_the_right_shape():
    P = torch.eye(4, dtype=F64).expand(2, 0, 2, 4, 4)
    X = torch.zeros(2, 0, 3, dtype=F64)
    J_pose, J_point = right_jacobian_jacrev(
        lambda P, X: se3.act(P[0], X) - se3.act(P[1], X)[..., :2].sum(-1, keepdim=True),
        (P,),
        (X,),
        batch_dims=2,
    )
    assert J_pose.shape == (2, 0, 3, 2, 6) and J_point.shape == (2, 0, 3, 3)


def test_jacrev_blocks_use_the_helper_and_match_analytic(generator):
    xi = torch.randn(4, 5, 6, generator=generator, dtype=F64)
    X = torch.randn(4, 5, 3, generator=generator, dtype=F64)
    J_xi, J_point = jacobians.jacrev_blocks(xi, X, torch.zeros_like(X))
    A_xi, A_point = jacobians.analytic_blocks(se3.exp(xi)[..., :3, :3], X)
    assert float((J_xi - A_xi).abs().max()) <= 1e-13
    assert float((J_point - A_point).abs().max()) <= 1e-15


def test_bad_arguments_are_named():
    T = torch.eye(4, dtype=F64).expand(3, 4, 4)
    f = lambda T: se3.log(T)  # noqa: E731
    with pytest.raises(TypeError, match=r"right_jacobian_jacrev: argument 'fn' must be callable"):
        right_jacobian_jacrev(None, (T,))
    with pytest.raises(TypeError, match=r"right_jacobian_jacrev: argument 'poses' must be a"):
        right_jacobian_jacrev(f, T)
    with pytest.raises(ValueError, match=r"right_jacobian_jacrev: argument 'poses\[0\]'"):
        right_jacobian_jacrev(f, (T[..., :3, :],))
    with pytest.raises(TypeError, match=r"right_jacobian_jacrev: 'poses\[0\]' is torch.float64"):
        right_jacobian_jacrev(f, (T,), (torch.zeros(3, 2, dtype=torch.float32),))
    with pytest.raises(ValueError, match=r"right_jacobian_jacrev: there is nothing"):
        right_jacobian_jacrev(f, ())
    with pytest.raises(ValueError, match=r"right_jacobian_jacrev: the leading \(batch\) dims"):
        right_jacobian_jacrev(f, (T,), constants=(torch.zeros(2, 1),))
    with pytest.raises(ValueError, match=r"right_jacobian_jacrev: argument 'poses\[0\]' contains"):
        right_jacobian_jacrev(f, (torch.full((3, 4, 4), math.nan, dtype=F64),))


# --------------------------------------------------------------------------- SE3Tangent.retract


@pytest.mark.parametrize("perturbation", ["right", "left"])
def test_retract_equals_plus_bitwise_and_keeps_zero_steps(perturbation, generator):
    manifold = SE3Tangent(perturbation)
    xi = _principal_twists(generator)
    delta = 0.3 * torch.randn(xi.shape, generator=generator, dtype=F64)
    delta[::3] = 0.0  # fixed poses: a step of exactly zero
    moved = manifold.retract(xi, delta)
    step = (delta != 0).any(-1)
    # Same operations as plus on ordinary input (|ω| ≤ π, |v| ≤ ~1e5): equal bits.
    assert torch.equal(moved[step], manifold.plus(xi, delta)[step])
    assert torch.equal(moved[~step], xi[~step])
    with validation(False):
        assert torch.equal(manifold.retract(xi, delta), moved)


def test_retract_broadcasts_and_names_itself():
    xi = torch.zeros(3, 1, 6, dtype=F64)
    delta = torch.zeros(4, 6, dtype=F64)
    delta[1, 0] = 0.5
    out = SE3Tangent().retract(xi, delta)
    assert out.shape == (3, 4, 6) and float(out[:, 1, 0].sub(0.5).abs().max()) <= 1e-15
    with pytest.raises(ValueError, match=r"SE3Tangent\.retract: the leading \(batch\) dims"):
        SE3Tangent().retract(torch.zeros(3, 6, dtype=F64), torch.zeros(4, 6, dtype=F64))
    with pytest.raises(TypeError, match=r"SE3Tangent\.retract: 'x' is torch.float64"):
        SE3Tangent().retract(torch.zeros(6, dtype=F64), torch.zeros(6, dtype=torch.float32))
    with pytest.raises(ValueError, match=r"SE3Tangent\.retract: argument 'delta' contains"):
        SE3Tangent().retract(torch.zeros(6, dtype=F64), torch.full((6,), math.inf, dtype=F64))
