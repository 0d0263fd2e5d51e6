"""Between and prior residuals: analytic Jacobians vs jacrev vs central differences."""

from __future__ import annotations

import math

import pytest
import torch

from tests.helpers import (
    HARD_ANGLES,
    TOL,
    central_difference,
    rotation_vectors_with_angles,
    twists_with_hard_inputs,
)
from torchslam import validation
from torchslam.lie import se3
from torchslam.posegraph import between

# Exactly π is excluded: Log jumps between ±ω there, so no derivative exists.
ANGLES_BELOW_PI = tuple(a for a in HARD_ANGLES if a < math.pi)


def _random_poses(count: int, generator: torch.Generator, scale: float = 1.0) -> torch.Tensor:
    xi = torch.randn(count, 6, generator=generator, dtype=torch.float64)
    xi[:, 3:] *= scale
    return se3.exp(xi)


def _hard_twists(generator: torch.Generator) -> torch.Tensor:
    """Twists over every hard angle below π × every hard translation magnitude."""
    xi = twists_with_hard_inputs(generator)
    return xi[xi[:, :3].norm(dim=-1) < math.pi]


def _edges(kind: str, generator: torch.Generator) -> tuple[torch.Tensor, ...]:
    """(T_i, T_j, Z_ij) batches whose residual or relative pose has a hard angle/translation.

    - "residual": Z = T_i⁻¹ T_j Exp(−ξ), so r = ξ exactly has the hard angle and translation.
    - "relative": T_j = T_i Exp(ξ) with the hard ξ, Z = Exp(ξ) Exp(small noise).
    - "random": everything random, world translations up to 1e4.
    """
    if kind == "residual":
        xi = _hard_twists(generator)
        T_i = _random_poses(xi.shape[0], generator)
        T_j = _random_poses(xi.shape[0], generator, scale=3.0)
        Z = se3.inverse(T_i) @ T_j @ se3.exp(-xi)
    elif kind == "relative":
        xi = _hard_twists(generator)
        T_i = _random_poses(xi.shape[0], generator, scale=100.0)
        T_j = T_i @ se3.exp(xi)
        noise = 1e-3 * torch.randn(xi.shape[0], 6, generator=generator, dtype=torch.float64)
        Z = se3.exp(xi) @ se3.exp(noise)
    else:
        T_i = _random_poses(32, generator, scale=1e4)
        T_j = _random_poses(32, generator, scale=1e4)
        Z = _random_poses(32, generator, scale=10.0)
    return T_i, T_j, Z


def _relative_error(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """Per-block relative Frobenius error |A − B| / |B| over the last two dims."""
    return (A - B).flatten(-2).norm(dim=-1) / B.flatten(-2).norm(dim=-1)


EDGE_KINDS = ("residual", "relative", "random")


@pytest.mark.parametrize("kind", EDGE_KINDS)
def test_between_analytic_equals_jacrev(kind, generator):
    T_i, T_j, Z = _edges(kind, generator)
    r, J_i, J_j = between.between_jacobians(T_i, T_j, Z)
    J_i_ref, J_j_ref = between.between_jacobians_jacrev(T_i, T_j, Z)
    assert r.shape == (T_i.shape[0], 6)
    assert _relative_error(J_j, J_j_ref).max() <= 1e-10
    assert _relative_error(J_i, J_i_ref).max() <= 1e-10


def test_between_residual_has_the_hard_angles(generator):
    T_i, T_j, Z = _edges("residual", generator)
    angles = between.between_residual(T_i, T_j, Z)[:, :3].norm(dim=-1)
    assert angles.max() > math.pi - 2e-6
    assert angles.min() == 0.0


@pytest.mark.parametrize("kind", EDGE_KINDS)
def test_between_analytic_equals_central_differences(kind, generator):
    T_i, T_j, Z = _edges(kind, generator)
    _, J_i, J_j = between.between_jacobians(T_i, T_j, Z)
    # Steps of 1e-7 keep the rotation angle of π − 1e-6 below π (no wrap of Log).
    eps = 1e-7
    # Central differences lose ~ε·|t|/eps to round-off where the translations are large.
    scale = torch.stack([T[:, :3, 3].norm(dim=-1) for T in (T_i, T_j, Z)]).sum(0) + 1.0
    with validation(False):
        for e in range(T_i.shape[0]):

            def f_i(d, e=e):
                return between.between_residual(T_i[e] @ se3.exp(d), T_j[e], Z[e])

            def f_j(d, e=e):
                return between.between_residual(T_i[e], T_j[e] @ se3.exp(d), Z[e])

            zero = torch.zeros(6, dtype=torch.float64)
            fd_i = central_difference(f_i, zero, eps)
            fd_j = central_difference(f_j, zero, eps)
            round_off = 1e-15 * scale[e] / eps
            assert (J_i[e] - fd_i).norm() <= 1e-6 * fd_i.norm() + round_off, e
            assert (J_j[e] - fd_j).norm() <= 1e-6 * fd_j.norm() + round_off, e


def test_between_first_order_on_the_manifold(generator):
    """r(T_i Exp(s d_i), T_j Exp(s d_j)) − r − s (J_i d_i + J_j d_j) = O(s²)."""
    T_i, T_j, Z = _edges("random", generator)
    r, J_i, J_j = between.between_jacobians(T_i, T_j, Z)
    d_i = torch.randn(T_i.shape[0], 6, generator=generator, dtype=torch.float64)
    d_j = torch.randn(T_i.shape[0], 6, generator=generator, dtype=torch.float64)
    errors = []
    for s in (1e-3, 5e-4):
        moved = between.between_residual(T_i @ se3.exp(s * d_i), T_j @ se3.exp(s * d_j), Z)
        linear = r + s * ((J_i @ d_i[..., None]) + (J_j @ d_j[..., None])).squeeze(-1)
        errors.append((moved - linear).norm(dim=-1))
    ratio = errors[0] / errors[1]
    assert ((ratio > 3.5) & (ratio < 4.5)).all()


def test_between_blocks_identities(generator):
    """J_i = −Jl⁻¹(r) Ad(Z⁻¹); at the measurement (r = 0): J_j = I and J_i = −Ad(Z⁻¹)."""
    T_i, T_j, Z = _edges("residual", generator)
    r, J_i, _ = between.between_jacobians(T_i, T_j, Z)
    expected = -se3.jl_inv(r) @ se3.adjoint(se3.inverse(Z))
    assert _relative_error(J_i, expected).max() <= 1e-9

    T_i = _random_poses(8, generator, scale=5.0)
    Z = _random_poses(8, generator, scale=5.0)
    r, J_i, J_j = between.between_jacobians(T_i, T_i @ Z, Z)
    eye = torch.eye(6, dtype=torch.float64)
    assert r.abs().max() <= 1e-12
    torch.testing.assert_close(J_j, eye.expand(8, 6, 6), rtol=0, atol=1e-11)
    torch.testing.assert_close(J_i, -se3.adjoint(se3.inverse(Z)), rtol=0, atol=1e-10)


def test_between_residual_is_zero_for_consistent_measurements_and_inverts(generator):
    T_i, T_j = _random_poses(5, generator), _random_poses(5, generator)
    Z = se3.inverse(T_i) @ T_j
    assert between.between_residual(T_i, T_j, Z).abs().max() <= 1e-13
    # Swapping the vertices and inverting the measurement negates the rotation part.
    Z2 = _random_poses(5, generator)
    r = between.between_residual(T_i, T_j, Z2)
    r_swapped = between.between_residual(T_j, T_i, se3.inverse(Z2))
    torch.testing.assert_close(
        r_swapped, -(se3.adjoint(Z2) @ r[..., None]).squeeze(-1), rtol=0, atol=1e-12
    )


def test_between_broadcasts(generator):
    T_i = _random_poses(3, generator).reshape(3, 1, 4, 4)
    T_j = _random_poses(2, generator).reshape(1, 2, 4, 4)
    Z = _random_poses(1, generator)[0]
    r, J_i, J_j = between.between_jacobians(T_i, T_j, Z)
    assert r.shape == (3, 2, 6) and J_i.shape == (3, 2, 6, 6) and J_j.shape == (3, 2, 6, 6)
    J_i_ref, J_j_ref = between.between_jacobians_jacrev(T_i, T_j, Z)
    assert J_i_ref.shape == (3, 2, 6, 6)
    assert _relative_error(J_i, J_i_ref).max() <= 1e-10
    assert _relative_error(J_j, J_j_ref).max() <= 1e-10
    empty = torch.zeros(0, 4, 4, dtype=torch.float64)
    assert between.between_jacobians_jacrev(empty, empty, empty)[0].shape == (0, 6, 6)


def test_between_float32_matches_jacrev(generator):
    T_i, T_j, Z = (t.float() for t in _edges("random", generator))
    _, J_i, J_j = between.between_jacobians(T_i, T_j, Z)
    J_i_ref, J_j_ref = between.between_jacobians_jacrev(T_i, T_j, Z)
    assert J_i.dtype == torch.float32
    # Translations of 1e4 amplify float32 round-off in the products; relative to the block.
    assert _relative_error(J_i, J_i_ref).max() <= 1e3 * TOL[torch.float32]
    assert _relative_error(J_j, J_j_ref).max() <= 1e3 * TOL[torch.float32]


def test_between_gradcheck(generator):
    T_i, T_j, Z = (t[:3] for t in _edges("random", generator))
    deltas = torch.zeros(2, 3, 6, dtype=torch.float64, requires_grad=True)

    def f(d):
        return between.between_residual(T_i @ se3.exp(d[0]), T_j @ se3.exp(d[1]), Z)

    with validation(False):
        assert torch.autograd.gradcheck(f, (deltas,))


@pytest.mark.parametrize("angle", ANGLES_BELOW_PI)
def test_prior_jacobian(angle, generator):
    omega = rotation_vectors_with_angles((angle,), generator, per_angle=4)
    xi = torch.cat((omega, torch.randn(4, 3, generator=generator, dtype=torch.float64)), dim=-1)
    xi[1, 3:] *= 1e4
    xi[2, 3:] *= 1e-9
    Z = _random_poses(4, generator, scale=10.0)
    T = Z @ se3.exp(xi)
    r, J = between.prior_jacobian(T, Z)
    torch.testing.assert_close(r, xi, rtol=0, atol=1e-9 * (1 + xi.abs().max().item()))
    assert _relative_error(J, between.prior_jacobian_jacrev(T, Z)).max() <= 1e-10
    with validation(False):
        for e in range(4):
            fd = central_difference(
                lambda d, e=e: between.prior_residual(T[e] @ se3.exp(d), Z[e]),
                torch.zeros(6, dtype=torch.float64),
                1e-7,
            )
            assert _relative_error(J[e], fd) <= 1e-6


def _random_information(count: int, generator: torch.Generator) -> torch.Tensor:
    A = torch.randn(count, 6, 6, generator=generator, dtype=torch.float64)
    return A @ A.transpose(-1, -2) + 0.5 * torch.eye(6, dtype=torch.float64)


def test_whitening_and_weighted_cost(generator):
    T_i, T_j, Z = _edges("random", generator)
    information = _random_information(T_i.shape[0], generator)
    r, _, J_j = between.between_jacobians(T_i, T_j, Z)
    U = between.sqrt_information(information)
    torch.testing.assert_close(U.transpose(-1, -2) @ U, information, rtol=1e-13, atol=1e-12)
    assert (U.tril(-1) == 0).all()
    white = between.whiten_residual(U, r)
    cost = between.weighted_cost(r, information)
    torch.testing.assert_close(cost, 0.5 * (white * white).sum(-1), rtol=1e-12, atol=0)
    explicit = torch.stack(
        [0.5 * r[e] @ information[e] @ r[e] for e in range(r.shape[0])]  # per-edge loop
    )
    torch.testing.assert_close(cost, explicit, rtol=1e-12, atol=0)
    # The whitened Jacobian is the Jacobian of the whitened residual.
    J_white = between.whiten_jacobian(U, J_j)
    J_white_ref = torch.stack(
        [
            torch.func.jacrev(
                lambda d, e=e: U[e] @ between._between(T_i[e], T_j[e] @ se3.exp(d), Z[e])
            )(torch.zeros(6, dtype=torch.float64))
            for e in range(3)
        ]
    )
    assert _relative_error(J_white[:3], J_white_ref).max() <= 1e-10


def test_sqrt_information_rejects_indefinite_matrices(generator):
    information = _random_information(3, generator)
    information[1, 2, 2] = -1.0
    with pytest.raises(ValueError, match=r"sqrt_information.*positive definite.*\(1,\)"):
        between.sqrt_information(information)


def test_between_rejects_bad_input(generator):
    T = _random_poses(2, generator)
    with pytest.raises(ValueError, match=r"between_residual: argument 'Z_ij' must have shape"):
        between.between_residual(T, T, T[..., :3, :])
    with pytest.raises(TypeError, match=r"between_jacobians: 'T_i' is torch.float64 but 'Z_ij'"):
        between.between_jacobians(T, T, T.float())
    bad = T.clone()
    bad[0, 0, 0] = 2.0
    with pytest.raises(ValueError, match=r"prior_residual: argument 'T' must hold rotation"):
        between.prior_residual(bad, T)
    with pytest.raises(ValueError, match=r"weighted_cost: argument 'information' must have"):
        between.weighted_cost(torch.zeros(2, 6, dtype=torch.float64), torch.eye(3))
