"""Weighted Kabsch: exact recovery, optimality, weights and masks, reflections, gradients."""

from __future__ import annotations

import pytest
import torch

from tests.helpers import TOL
from torchslam import validation
from torchslam.alignment import weighted_kabsch
from torchslam.lie import se3, so3

BATCH_SHAPES = [(), (1,), (3, 1, 2)]


def _random_transforms(shape, generator, dtype=torch.float64):
    xi = torch.randn(*shape, 6, generator=generator, dtype=torch.float64)
    xi[..., :3] *= 1.5
    xi[..., 3:] *= 3.0
    return se3.exp(xi).to(dtype)


@pytest.mark.parametrize("batch", BATCH_SHAPES, ids=str)
def test_recovers_exact_transform(batch, dtype, generator):
    T = _random_transforms(batch, generator, dtype)
    source = (5 * torch.randn(*batch, 25, 3, generator=generator, dtype=torch.float64)).to(dtype)
    target = se3.act(T[..., None, :, :], source)
    T_hat = weighted_kabsch(source, target)
    assert T_hat.shape == (*batch, 4, 4)
    assert T_hat.dtype == dtype
    tol = 1e-12 if dtype == torch.float64 else 1e-4
    torch.testing.assert_close(T_hat, T, atol=tol, rtol=0)


def test_large_rotations_near_pi(generator):
    axes = torch.randn(6, 3, generator=generator, dtype=torch.float64)
    omega = axes / axes.norm(dim=-1, keepdim=True) * (torch.pi - 1e-9)
    T = se3.from_rotation_translation(so3.exp(omega), torch.zeros(6, 3, dtype=torch.float64))
    source = torch.randn(6, 10, 3, generator=generator, dtype=torch.float64)
    T_hat = weighted_kabsch(source, se3.act(T[:, None], source))
    torch.testing.assert_close(T_hat, T, atol=1e-12, rtol=0)


def test_weighted_solution_is_stationary(generator):
    """With noise and random weights the weighted cost has zero gradient at the solution."""
    T = _random_transforms((4,), generator)
    source = torch.randn(4, 30, 3, generator=generator, dtype=torch.float64)
    target = se3.act(T[:, None], source) + 0.1 * torch.randn(
        4, 30, 3, generator=generator, dtype=torch.float64
    )
    weights = torch.rand(4, 30, generator=generator, dtype=torch.float64) * 3
    T_hat = weighted_kabsch(source, target, weights)

    delta = torch.zeros(4, 6, dtype=torch.float64, requires_grad=True)
    moved = T_hat @ se3.exp(delta)
    cost = (weights * (target - se3.act(moved[:, None], source)).square().sum(-1)).sum()
    (grad,) = torch.autograd.grad(cost, delta)
    assert grad.abs().max() < 1e-10
    # And it beats small perturbations of itself (a minimum, not just a stationary point).
    for _ in range(5):
        d = 1e-3 * torch.randn(4, 6, generator=generator, dtype=torch.float64)
        other = T_hat @ se3.exp(d)
        cost_other = weights * (target - se3.act(other[:, None], source)).square().sum(-1)
        cost_hat = weights * (target - se3.act(T_hat[:, None], source)).square().sum(-1)
        assert (cost_other.sum(-1) > cost_hat.sum(-1)).all()


def test_integer_weights_equal_repeated_points(generator):
    source = torch.randn(12, 3, generator=generator, dtype=torch.float64)
    target = source @ so3.exp(torch.tensor([0.3, -0.2, 0.9], dtype=torch.float64)).T
    target = target + 0.05 * torch.randn(12, 3, generator=generator, dtype=torch.float64)
    counts = torch.randint(1, 4, (12,), generator=generator)
    weighted = weighted_kabsch(source, target, counts.to(torch.float64))
    repeated = weighted_kabsch(
        source.repeat_interleave(counts, dim=0), target.repeat_interleave(counts, dim=0)
    )
    torch.testing.assert_close(weighted, repeated, atol=1e-12, rtol=0)


def test_mask_ignores_padding_even_nan(generator):
    T = _random_transforms((2,), generator)
    source = torch.randn(2, 8, 3, generator=generator, dtype=torch.float64)
    target = se3.act(T[:, None], source) + 0.01 * torch.randn(
        2, 8, 3, generator=generator, dtype=torch.float64
    )
    mask = torch.ones(2, 8, dtype=torch.bool)
    mask[0, 5:] = False
    padded_source = source.clone()
    padded_source[0, 5:] = float("nan")
    T_masked = weighted_kabsch(padded_source, target, mask=mask)
    torch.testing.assert_close(T_masked[0], weighted_kabsch(source[0, :5], target[0, :5]))
    torch.testing.assert_close(T_masked[1], weighted_kabsch(source[1], target[1]))
    # Zero weights act like the mask.
    weights = mask.to(torch.float64)
    torch.testing.assert_close(weighted_kabsch(source, target, weights), T_masked)


def test_reflection_is_replaced_by_a_rotation(generator):
    """A mirrored target would be fit best by a reflection; the result stays in SO(3)."""
    source = torch.randn(3, 20, 3, generator=generator, dtype=torch.float64)
    target = source * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)
    T_hat = weighted_kabsch(source, target)
    R = T_hat[..., :3, :3]
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(3, dtype=torch.float64))
    eye = torch.eye(3, dtype=torch.float64).expand(3, 3, 3)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, eye, atol=TOL[torch.float64], rtol=0)
    torch.testing.assert_close(T_hat[..., 3, :], torch.tensor([0.0, 0, 0, 1]).double().expand(3, 4))


def test_planar_points_are_fine(generator):
    """Coplanar (rank-2) points still determine the rotation uniquely."""
    source = torch.randn(10, 3, generator=generator, dtype=torch.float64)
    source[:, 2] = 0.0
    T = _random_transforms((), generator)
    T_hat = weighted_kabsch(source, se3.act(T, source))
    torch.testing.assert_close(T_hat, T, atol=1e-12, rtol=0)


def test_gradcheck(generator):
    T = _random_transforms((2,), generator)
    source = torch.randn(2, 6, 3, generator=generator, dtype=torch.float64)
    target = se3.act(T[:, None], source) + 0.1 * torch.randn(
        2, 6, 3, generator=generator, dtype=torch.float64
    )
    weights = 0.5 + torch.rand(2, 6, generator=generator, dtype=torch.float64)
    inputs = tuple(x.clone().requires_grad_(True) for x in (source, target, weights))
    assert torch.autograd.gradcheck(weighted_kabsch, inputs)


def test_works_under_vmap(generator):
    T = _random_transforms((3,), generator)
    source = torch.randn(3, 7, 3, generator=generator, dtype=torch.float64)
    target = se3.act(T[:, None], source)
    T_hat = torch.func.vmap(weighted_kabsch)(source, target)
    torch.testing.assert_close(T_hat, T, atol=1e-12, rtol=0)


def test_too_few_points_raises(generator):
    source = torch.randn(2, 5, 3, generator=generator, dtype=torch.float64)
    mask = torch.ones(2, 5, dtype=torch.bool)
    mask[1, 2:] = False
    with pytest.raises(ValueError, match=r"problem \(1,\) has 2 point\(s\)"):
        weighted_kabsch(source, source, mask=mask)


def test_collinear_points_raise(generator):
    direction = torch.tensor([1.0, 2.0, -0.5], dtype=torch.float64)
    source = torch.linspace(-1, 1, 6, dtype=torch.float64)[:, None] * direction
    with pytest.raises(ValueError, match="degenerate"):
        weighted_kabsch(source, source + 1.0)
    # Without value checks the call goes through (no host sync) and returns a transform.
    with validation(False):
        assert weighted_kabsch(source, source + 1.0).shape == (4, 4)


def test_bad_arguments(generator):
    source = torch.randn(5, 3, generator=generator, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"'source' must have shape \(\.\.\., 3\), got \(5, 2\)"):
        weighted_kabsch(source[:, :2], source[:, :2])
    with pytest.raises(ValueError, match=r"'source' must have shape \(\.\.\., N, 3\), got \(3,\)"):
        weighted_kabsch(source[0], source[0])
    with pytest.raises(ValueError, match="same shape"):
        weighted_kabsch(source, source[:4])
    with pytest.raises(TypeError, match=r"'source' is torch.float64 but 'target' is torch.float32"):
        weighted_kabsch(source, source.float())
    with pytest.raises(ValueError, match="'weights' must have a shape broadcastable to"):
        weighted_kabsch(source, source, torch.ones(4, dtype=torch.float64))
    with pytest.raises(ValueError, match="'weights' must be >= 0"):
        weighted_kabsch(source, source, -torch.ones(5, dtype=torch.float64))
    with pytest.raises(TypeError, match="'mask' must be a bool tensor"):
        weighted_kabsch(source, source, mask=torch.ones(5))
    with pytest.raises(ValueError, match="non-finite"):
        bad = source.clone()
        bad[2, 1] = float("inf")
        weighted_kabsch(bad, source)
