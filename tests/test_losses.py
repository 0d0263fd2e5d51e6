"""Tests of torchslam.losses: kernels (values, derivatives, knees, batching) and the corrector."""

from __future__ import annotations

import math

import pytest
import torch

from torchslam import validation
from torchslam.losses import (
    CauchyLoss,
    HuberLoss,
    RobustLoss,
    TrivialLoss,
    TukeyLoss,
    triggs_correction,
)

F64 = torch.float64
SCALED = [HuberLoss, CauchyLoss, TukeyLoss]
LOSSES = [TrivialLoss(), HuberLoss(1.5), CauchyLoss(1.5), TukeyLoss(1.5)]
IDS = [repr(loss) for loss in LOSSES]


def _grid(scale: float) -> torch.Tensor:
    """s from 0 across the knee a² to 10 a², avoiding the knee itself (a kink for Huber)."""
    b = scale * scale
    return torch.cat(
        (
            torch.tensor([0.0, 1e-12, 1e-6], dtype=F64),
            torch.linspace(0.01, 0.99, 9, dtype=F64) * b,
            torch.linspace(1.01, 10.0, 9, dtype=F64) * b,
        )
    )


# --------------------------------------------------------------------------- values


def test_hand_computed_values():
    """Ceres' formulas at a = 2 (a² = 4), evaluated by hand."""
    s = torch.tensor([1.0, 9.0], dtype=F64)
    rho, rho1, rho2 = HuberLoss(2.0)(s)
    # s = 1 ≤ 4: (s, 1, 0); s = 9: 2·2·3 − 4 = 8, 2/3, −(2/3)/(2·9) = −1/27.
    torch.testing.assert_close(rho, torch.tensor([1.0, 8.0], dtype=F64))
    torch.testing.assert_close(rho1, torch.tensor([1.0, 2.0 / 3.0], dtype=F64))
    torch.testing.assert_close(rho2, torch.tensor([0.0, -1.0 / 27.0], dtype=F64))

    rho, rho1, rho2 = CauchyLoss(2.0)(torch.tensor([4.0], dtype=F64))
    # 4 log 2, 1/(1 + 1) = ½, −¼ · ¼ = −1/16.
    torch.testing.assert_close(rho, torch.tensor([4.0 * math.log(2.0)], dtype=F64))
    torch.testing.assert_close(rho1, torch.tensor([0.5], dtype=F64))
    torch.testing.assert_close(rho2, torch.tensor([-1.0 / 16.0], dtype=F64))

    rho, rho1, rho2 = TukeyLoss(2.0)(torch.tensor([2.0, 5.0], dtype=F64))
    # s = 2: v = ½, 4/3 (1 − 1/8) = 7/6, v² = ¼, −2v/4 = −¼; s = 5 > 4: (4/3, 0, 0).
    torch.testing.assert_close(rho, torch.tensor([7.0 / 6.0, 4.0 / 3.0], dtype=F64))
    torch.testing.assert_close(rho1, torch.tensor([0.25, 0.0], dtype=F64))
    torch.testing.assert_close(rho2, torch.tensor([-0.25, 0.0], dtype=F64))

    s = torch.tensor([0.0, 3.0], dtype=F64)
    for out, expected in zip(TrivialLoss()(s), (s, torch.ones(2), torch.zeros(2)), strict=True):
        torch.testing.assert_close(out, expected.to(F64))


@pytest.mark.parametrize("loss", LOSSES, ids=IDS)
def test_quadratic_near_zero(loss):
    """ρ(0) = 0 and ρ'(0) = 1 for every kernel: small residuals are plain least squares."""
    rho, rho1, _ = loss(torch.zeros(3, dtype=F64))
    torch.testing.assert_close(rho, torch.zeros(3, dtype=F64), rtol=0, atol=0)
    torch.testing.assert_close(rho1, torch.ones(3, dtype=F64), rtol=0, atol=0)


@pytest.mark.parametrize("loss", LOSSES, ids=IDS)
def test_derivatives_match_autograd(loss):
    s = _grid(1.5)

    def rho(s_):
        return loss(s_)[0]

    def rho1(s_):
        return loss(s_)[1]

    d_rho = torch.func.vmap(torch.func.grad(rho))(s)
    dd_rho = torch.func.vmap(torch.func.grad(torch.func.grad(rho)))(s)
    d_rho1 = torch.func.vmap(torch.func.grad(rho1))(s)
    _, expected_rho1, expected_rho2 = loss(s)
    torch.testing.assert_close(d_rho, expected_rho1, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(dd_rho, expected_rho2, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(d_rho1, expected_rho2, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("kind", SCALED, ids=lambda k: k.__name__)
def test_continuity_at_the_knee(kind):
    a = 0.7
    b = a * a
    eps = 1e-9
    s = torch.tensor([b - eps, b, b + eps], dtype=F64)
    rho, rho1, rho2 = kind(a)(s)
    for values in (rho, rho1):
        assert float(values.max() - values.min()) < 1e-8
    if kind is TukeyLoss:
        # Tukey is C² at the knee: (a²/3, 0, 0) from both sides.
        assert float(rho2.abs().max()) < 1e-8
        torch.testing.assert_close(rho[1], torch.tensor(b / 3.0, dtype=F64))
    if kind is HuberLoss:
        # Huber's ρ'' jumps from 0 to −1/(2a²) at the knee (documented).
        torch.testing.assert_close(rho2[2], torch.tensor(-1.0 / (2.0 * b), dtype=F64))


@pytest.mark.parametrize("loss", LOSSES, ids=IDS)
def test_gradients_are_finite_at_zero(loss):
    s = torch.zeros(4, dtype=F64, requires_grad=True)
    rho, rho1, rho2 = loss(s)
    (grad,) = torch.autograd.grad((rho + rho1 + rho2).sum(), s)
    assert bool(torch.isfinite(grad).all())


# --------------------------------------------------------------------------- the scale


@pytest.mark.parametrize("kind", SCALED, ids=lambda k: k.__name__)
def test_batched_tensor_scale_broadcasts_per_problem(kind):
    """A scale of shape (B,) applies row by row to s of shape (B, E)."""
    scale = torch.tensor([0.5, 1.0, 3.0], dtype=F64)
    s = torch.linspace(0.0, 4.0, 7, dtype=F64).expand(3, 7)
    batched = kind(scale)(s)
    for row in range(3):
        single = kind(float(scale[row]))(s[row])
        for out_batched, out_single in zip(batched, single, strict=True):
            assert out_batched.shape == (3, 7)
            torch.testing.assert_close(out_batched[row], out_single, rtol=1e-15, atol=0)


@pytest.mark.parametrize("kind", SCALED, ids=lambda k: k.__name__)
def test_gradients_flow_to_the_scale(kind):
    scale = torch.tensor([0.5, 1.0, 3.0], dtype=F64, requires_grad=True)
    s = torch.cat((torch.zeros(3, 1, dtype=F64), _grid(1.0).expand(3, -1)), dim=1)

    def outputs(scale_, s_):
        return torch.cat(kind(scale_)(s_), dim=-1)

    # Away from the knee s = a² (Huber's ρ'' jumps there), including s = 0.
    knee = (s - scale.detach()[:, None] ** 2).abs() < 1e-3
    s = torch.where(knee, s + 0.01, s).requires_grad_()
    with validation(False):  # gradcheck steps s = 0 to −ε
        assert torch.autograd.gradcheck(outputs, (scale, s))
    rho = kind(scale)(s)[0]
    rho.sum().backward()
    assert scale.grad is not None and bool(torch.isfinite(scale.grad).all())
    assert bool((scale.grad != 0).all())


def test_scale_must_align_with_leading_dims_of_s():
    loss = HuberLoss(torch.ones(3, dtype=F64))
    with pytest.raises(ValueError, match=r"HuberLoss.__call__: the scale of shape \(3,\)"):
        loss(torch.ones(4, 3, dtype=F64))
    with pytest.raises(ValueError, match=r"HuberLoss.__call__: the scale of shape \(3,\)"):
        loss(torch.ones(dtype=F64, size=()))
    with pytest.raises(TypeError, match=r"'s' is torch\.float32 but 'scale' is torch\.float64"):
        loss(torch.ones(3, 2, dtype=torch.float32))


def test_bad_scale():
    for kind in SCALED:
        name = kind.__name__
        for bad in (0.0, -1.0, math.inf, math.nan):
            with pytest.raises(ValueError, match=rf"{name}: argument 'scale' must be positive"):
                kind(bad)
        with pytest.raises(ValueError, match=rf"{name}: argument 'scale' must be positive"):
            kind(torch.tensor([1.0, -2.0], dtype=F64))
        for wrong in ("1.0", None, True, [1.0]):
            with pytest.raises(TypeError, match=rf"{name}: argument 'scale' must be"):
                kind(wrong)  # type: ignore[arg-type]
        with pytest.raises(TypeError, match=rf"{name}: argument 'scale' must be float32"):
            kind(torch.tensor([1, 2]))
    assert HuberLoss(2).scale == 2.0


def test_bad_s():
    loss = CauchyLoss(1.0)
    with pytest.raises(TypeError, match=r"CauchyLoss.__call__: argument 's' must be a torch"):
        loss(1.0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"argument 's' must be a squared norm"):
        loss(torch.tensor([1.0, -1.0], dtype=F64))
    with pytest.raises(ValueError, match=r"TrivialLoss.__call__: argument 's' contains"):
        TrivialLoss()(torch.tensor([math.nan], dtype=F64))


def test_losses_share_the_base_class_and_work_under_vmap():
    assert all(isinstance(loss, RobustLoss) for loss in LOSSES)
    s = _grid(1.0).reshape(3, -1)
    for loss in LOSSES:
        mapped = torch.func.vmap(loss)(s)
        for a, b in zip(mapped, loss(s), strict=True):
            torch.testing.assert_close(a, b)


def test_float32():
    s = _grid(1.0).float()
    for loss in LOSSES:
        ref = loss(s.double())
        for out, expected in zip(loss(s), ref, strict=True):
            assert out.dtype == torch.float32
            torch.testing.assert_close(out.double(), expected, rtol=1e-5, atol=1e-6)


# --------------------------------------------------------------------------- the corrector


def _linear_model(generator: torch.Generator):
    """r(x) = A x − c: a tiny linear residual (k = 3 rows, n = 4 parameters)."""
    A = torch.randn(3, 4, generator=generator, dtype=F64)
    c = torch.randn(3, generator=generator, dtype=F64)
    x = torch.randn(4, generator=generator, dtype=F64)
    return A, c, x


def _corrected(A, c, x, rho_fn):
    r = A @ x - c
    s = r @ r
    _, rho1, rho2 = rho_fn(s)
    residual_scale, alpha_over_s = triggs_correction(s, rho1, rho2)
    sqrt_rho1 = torch.sqrt(rho1)
    J_tilde = sqrt_rho1 * (A - alpha_over_s * torch.outer(r, r @ A))
    r_tilde = residual_scale * r
    return r, s, rho1, rho2, r_tilde, J_tilde, alpha_over_s


def _smooth_convex(s):
    """A test kernel with ρ'' > 0 (the branch where Ceres applies the full correction)."""
    return s + 0.25 * s * s, 1.0 + 0.5 * s, torch.full_like(s, 0.5)


@pytest.mark.parametrize(
    "rho_fn",
    [_smooth_convex, TrivialLoss(), HuberLoss(0.5), CauchyLoss(0.5), TukeyLoss(3.0)],
    ids=["convex", "trivial", "huber", "cauchy", "tukey"],
)
def test_corrected_gradient_is_exact(rho_fn, generator):
    """J̃ᵀ r̃ = ∂(½ρ(‖r(x)‖²))/∂x for every kernel, with or without the clamp."""
    A, c, x = _linear_model(generator)
    *_, r_tilde, J_tilde, _ = _corrected(A, c, x, rho_fn)

    def cost(x_):
        r = A @ x_ - c
        return 0.5 * rho_fn(r @ r)[0]

    gradient = torch.func.grad(cost)(x)
    torch.testing.assert_close(J_tilde.T @ r_tilde, gradient, rtol=1e-13, atol=1e-13)


def test_corrected_hessian_is_the_second_order_model(generator):
    """With ρ'' > 0, J̃ᵀJ̃ = ρ' AᵀA + 2ρ'' Aᵀr rᵀA = ∇²(½ρ(‖Ax − c‖²)) exactly (linear r)."""
    A, c, x = _linear_model(generator)
    r, _, rho1, rho2, _, J_tilde, alpha_over_s = _corrected(A, c, x, _smooth_convex)
    assert float(alpha_over_s) < 0  # the full Triggs branch ran

    def cost(x_):
        r_ = A @ x_ - c
        return 0.5 * _smooth_convex(r_ @ r_)[0]

    hessian = torch.func.jacrev(torch.func.jacrev(cost))(x)
    torch.testing.assert_close(J_tilde.T @ J_tilde, hessian, rtol=1e-12, atol=1e-12)
    g = A.T @ r
    expected = rho1 * A.T @ A + 2.0 * rho2 * torch.outer(g, g)
    torch.testing.assert_close(J_tilde.T @ J_tilde, expected, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("loss", [HuberLoss(0.5), CauchyLoss(0.5)], ids=["huber", "cauchy"])
def test_clamp_for_concave_kernels(loss, generator):
    """ρ'' ≤ 0 (Ceres' clamp): α = 0, r̃ = √ρ' r and J̃ᵀJ̃ = ρ' JᵀJ (IRLS)."""
    A, c, x = _linear_model(generator)
    r, _, rho1, rho2, r_tilde, J_tilde, alpha_over_s = _corrected(A, c, x, loss)
    assert float(rho2) < 0
    assert float(alpha_over_s) == 0.0
    torch.testing.assert_close(r_tilde, torch.sqrt(rho1) * r, rtol=0, atol=0)
    torch.testing.assert_close(J_tilde.T @ J_tilde, rho1 * A.T @ A, rtol=1e-13, atol=1e-13)


def test_corrector_formula_and_special_cases():
    s = torch.tensor([0.0, 2.0, 2.0, 2.0, 2.0], dtype=F64)
    rho1 = torch.tensor([1.0, 3.0, 3.0, 0.0, 3.0], dtype=F64)
    rho2 = torch.tensor([5.0, 0.75, -1.0, 0.0, 0.0], dtype=F64)
    residual_scale, alpha_over_s = triggs_correction(s, rho1, rho2)
    # Index 1: D = 1 + 2·2·0.75/3 = 2, α = 1 − √2, scale = √3/√2.
    alpha = 1.0 - math.sqrt(2.0)
    expected_scale = [1.0, math.sqrt(3.0) / math.sqrt(2.0), math.sqrt(3.0), 0.0, math.sqrt(3.0)]
    expected_alpha = [0.0, alpha / 2.0, 0.0, 0.0, 0.0]
    torch.testing.assert_close(residual_scale, torch.tensor(expected_scale, dtype=F64))
    torch.testing.assert_close(alpha_over_s, torch.tensor(expected_alpha, dtype=F64))
    # √ρ' = residual_scale · (1 − alpha_over_s · s), as documented.
    torch.testing.assert_close(residual_scale * (1 - alpha_over_s * s), torch.sqrt(rho1))


def test_corrector_gradients_are_finite_for_tukey_outliers_and_zero():
    a = torch.tensor(1.0, dtype=F64, requires_grad=True)
    s = torch.tensor([0.0, 0.5, 4.0], dtype=F64, requires_grad=True)
    _, rho1, rho2 = TukeyLoss(a)(s)
    residual_scale, alpha_over_s = triggs_correction(s, rho1, rho2)
    (residual_scale.sum() + alpha_over_s.sum()).backward()
    assert bool(torch.isfinite(s.grad).all()) and bool(torch.isfinite(a.grad).all())
    assert float(residual_scale.detach()[2]) == 0.0


def test_corrector_bad_input():
    s = torch.ones(3, dtype=F64)
    with pytest.raises(ValueError, match=r"triggs_correction: argument 's' must be a squared"):
        triggs_correction(-s, s, s)
    with pytest.raises(ValueError, match=r"triggs_correction: argument 'rho1' must be non-neg"):
        triggs_correction(s, -s, s)
    with pytest.raises(TypeError, match=r"triggs_correction: 's' is torch\.float64 but 'rho2'"):
        triggs_correction(s, s, s.float())
    with pytest.raises(ValueError, match=r"triggs_correction: shapes of 's' \(3,\)"):
        triggs_correction(s, torch.ones(4, dtype=F64), s)
    with pytest.raises(TypeError, match=r"triggs_correction: argument 'rho1' must be a torch"):
        triggs_correction(s, 1.0, s)  # type: ignore[arg-type]
    with validation(False):
        triggs_correction(s, s, s)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_weight_is_rho_prime_bit_for_bit(dtype):
    # ρ' alone (ICP's IRLS weights) by the same formulas: identical values, over squared norms
    # from 1e-30 to 1e30 (float64) and scales from tiny to huge, batched and scalar.
    from torchslam.losses import CauchyLoss, HuberLoss, TrivialLoss, TukeyLoss

    g = torch.Generator().manual_seed(0)
    exponent = torch.randint(-30, 31, (2, 500), generator=g).to(torch.float64)
    if dtype == torch.float32:
        exponent = exponent.clamp(-18, 18)
    s = torch.rand(2, 500, generator=g, dtype=torch.float64) * 10.0**exponent
    s = torch.cat((s, torch.zeros(2, 3, dtype=torch.float64)), 1).to(dtype)
    scales = (torch.tensor([0.5, 1e-30], dtype=dtype), 3.0, 1e15)
    for kernel in (CauchyLoss, HuberLoss, TukeyLoss):
        for scale in scales:
            loss = kernel(scale)
            assert torch.equal(loss.weight(s), loss(s)[1]), (kernel, scale)
    assert torch.equal(TrivialLoss().weight(s), torch.ones_like(s))
