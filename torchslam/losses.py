"""Robust kernels in Ceres' convention, and Ceres' corrector (the Triggs correction).

A loss acts on the squared norm s = rᵀΩr ≥ 0 of one observation's whitened residual and
returns (ρ(s), ρ'(s), ρ''(s)); a robustified problem minimizes ½ Σ ρ(s) (Ceres' convention, so
ρ(s) = s for :class:`TrivialLoss` gives plain least squares). Every loss with a scale a has
ρ(s) = s + O(s²) near 0 (ρ'(0) = 1) and bends away from the quadratic around s = a².

The scale may be a Python number or a tensor; a tensor scale may require grad (gradients flow
to it through ρ, ρ' and ρ'') and may be batched per problem: its dims align with the *leading*
dims of s, so a scale of shape (B,) applies to s of shape (B, E) row by row (a scale of shape
(B, E) or a 0-d tensor works too). Every value and gradient is finite at s = 0 and on both
sides of each knee (the double-``where`` idiom: the unused branch of a ``where`` is evaluated
at a safe value).

:func:`triggs_correction` turns (s, ρ', ρ'') into the scalings that let a plain Gauss-Newton /
Levenberg-Marquardt solver minimize ½ Σ ρ(s) (Triggs et al., "Bundle adjustment — a modern
synthesis", §4.3, as in Ceres' ``Corrector``).
"""

from __future__ import annotations

import abc
import copy
import math
import numbers

import torch
from torch import Tensor

from torchslam import _checks

__all__ = [
    "CauchyLoss",
    "HuberLoss",
    "RobustLoss",
    "TrivialLoss",
    "TukeyLoss",
    "check_loss",
    "tensor_attributes",
    "triggs_correction",
    "with_tensor_attributes",
]


def tensor_attributes(loss: object, floating: bool = True) -> dict[str, Tensor]:
    """The tensor attributes of a loss by name (e.g. a tensor ``scale``), floating-point ones
    only by default: what a differentiable solve carries gradients to, or moves and casts."""
    if loss is None or not hasattr(loss, "__dict__"):
        return {}
    return {
        name: value
        for name, value in vars(loss).items()
        if isinstance(value, Tensor) and (value.is_floating_point() or not floating)
    }


def with_tensor_attributes(loss: object, values: dict[str, Tensor]) -> object:
    """A shallow copy of ``loss`` with the given tensor attributes replaced (``loss`` itself
    when there is nothing to replace); the caller's object is never modified."""
    if not values:
        return loss
    new = copy.copy(loss)
    for name, value in values.items():
        setattr(new, name, value)
    return new


def check_loss(fn: str, loss: object, name: str = "loss") -> None:
    """Reject anything but None or a :class:`RobustLoss` instance (TypeError naming ``fn``
    and the argument): a string, a loss class instead of an instance, a number."""
    if loss is None or isinstance(loss, RobustLoss):
        return
    if isinstance(loss, type) and issubclass(loss, RobustLoss):
        scaled = issubclass(loss, _ScaledKernel)
        example = f"{loss.__name__}(0.05)" if scaled else f"{loss.__name__}()"
        raise TypeError(
            f"{fn}: argument '{name}' must be a RobustLoss instance, got the class "
            f"{loss.__name__} itself; create one, e.g. ts.{example}"
        )
    shown = f" {loss!r}" if isinstance(loss, (str, int, float)) else ""
    raise TypeError(
        f"{fn}: argument '{name}' must be a RobustLoss instance such as ts.HuberLoss(0.05) "
        f"(or None for least squares), got {type(loss).__name__}{shown}"
    )


def _check_s(fn: str, s: object) -> Tensor:
    """Metadata checks of a squared norm s (any shape); non-negative and finite when active."""
    s = _checks.check_tensor(fn, "s", s)
    _checks.check_finite(fn, "s", s)
    if _checks.value_checks_active() and s.numel() > 0:
        negative = s.detach() < 0
        if bool(negative.any()):
            idx = tuple(int(i) for i in negative.nonzero()[0].tolist())
            raise ValueError(
                f"{fn}: argument 's' must be a squared norm (s ≥ 0); at index {idx} "
                f"s = {float(s.detach()[idx]):.6g}"
            )
    return s


def check_loss_values(fn: str, loss: object, name: str = "loss") -> None:
    """At solve time: a tensor scale (a learnable one an optimizer step may have moved since
    the loss was built) must still be finite and positive; only when value checks are active.
    """
    if not isinstance(loss, _ScaledKernel) or not isinstance(loss.scale, Tensor):
        return
    if not _checks.value_checks_active():
        return
    scale = loss.scale.detach()
    bad = ~(torch.isfinite(scale) & (scale > 0))
    if bool(bad.any()):
        idx = tuple(int(i) for i in bad.nonzero()[0].tolist()) if scale.dim() else ()
        raise ValueError(
            f"{fn}: {name} {type(loss).__name__} has a scale that is no longer positive and "
            f"finite (at index {idx} it is {float(scale[idx])!r}); a learnable scale should be "
            "parameterized to stay positive, e.g. HuberLoss(torch.exp(log_scale))"
        )


class RobustLoss(abc.ABC):
    """A robust kernel ρ applied to squared norms s ≥ 0 (Ceres' ``LossFunction``).

    Calling it returns (ρ(s), ρ'(s), ρ''(s)), each of shape broadcast(s, scale) (with the
    scale's dims aligned to the leading dims of s), same dtype and device as s.
    """

    def __call__(self, s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Evaluate (ρ(s), ρ'(s), ρ''(s)).

        Args:
            s: squared norms rᵀΩr of whitened residuals, any shape (...), s ≥ 0.

        Returns:
            (ρ, ρ', ρ''), each of shape (...) (broadcast against a batched scale).
        """
        fn = f"{type(self).__name__}.__call__"
        s = _check_s(fn, s)
        return self._evaluate(fn, s)

    def weight(self, s: Tensor) -> Tensor:
        """ρ'(s) alone: the weight of iteratively reweighted least squares (ICP), the same
        values as ``self(s)[1]`` at a fraction of the cost."""
        fn = f"{type(self).__name__}.weight"
        s = _check_s(fn, s)
        return self._weight(fn, s)

    def _weight(self, fn: str, s: Tensor) -> Tensor:
        return self._evaluate(fn, s)[1]

    @abc.abstractmethod
    def _evaluate(self, fn: str, s: Tensor) -> tuple[Tensor, Tensor, Tensor]: ...


class TrivialLoss(RobustLoss):
    """ρ(s) = s, ρ' = 1, ρ'' = 0: plain least squares (Ceres' ``TrivialLoss``)."""

    def _evaluate(self, fn: str, s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        return s, torch.ones_like(s), torch.zeros_like(s)

    def __repr__(self) -> str:
        return "TrivialLoss()"


class _ScaledKernel(RobustLoss):
    """A kernel with one positive scale a (the residual norm where it departs from s)."""

    def __init__(self, scale: float | Tensor) -> None:
        owner = type(self).__name__
        if isinstance(scale, bool) or not isinstance(scale, (numbers.Real, Tensor)):
            raise TypeError(
                f"{owner}: argument 'scale' must be a positive float or a float tensor, "
                f"got {type(scale).__name__}"
            )
        if isinstance(scale, Tensor):
            _checks.check_tensor(owner, "scale", scale)
            bad = ~(torch.isfinite(scale.detach()) & (scale.detach() > 0))
            if scale.numel() > 0 and _checks.value_checks_active() and bool(bad.any()):
                idx = tuple(int(i) for i in bad.nonzero()[0].tolist())
                raise ValueError(
                    f"{owner}: argument 'scale' must be positive and finite; at index {idx} "
                    f"it is {float(scale.detach()[idx])!r}"
                )
        else:
            try:
                value = float(scale)
            except OverflowError:  # an int beyond the float range
                value = math.inf
            if not (math.isfinite(value) and value > 0):
                raise ValueError(
                    f"{owner}: argument 'scale' must be positive and finite, got {scale!r}"
                )
            scale = value
        self._scale = scale

    @property
    def scale(self) -> float | Tensor:
        """The scale a as given (a float, or the tensor itself so gradients reach it)."""
        return self._scale

    def __repr__(self) -> str:
        scale = self._scale
        shown = repr(scale) if isinstance(scale, float) else f"tensor{tuple(scale.shape)}"
        return f"{type(self).__name__}(scale={shown})"

    def _evaluate(self, fn: str, s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        return self._evaluate_scaled(s, self._aligned_scale(fn, s))

    def _weight(self, fn: str, s: Tensor) -> Tensor:
        return self._weight_scaled(s, self._aligned_scale(fn, s))

    def _weight_scaled(self, s: Tensor, scale: Tensor) -> Tensor:
        """ρ' from s and the aligned scale, bit for bit :meth:`_evaluate_scaled`'s."""
        return self._evaluate_scaled(s, scale)[1]

    def _aligned_scale(self, fn: str, s: Tensor) -> Tensor:
        """The scale as a tensor of s's dtype, with trailing singleton dims so that its dims
        align with s's leading dims, clamped to the dtype's positive normal range (a float
        scale of 1e-200 is the smallest float32 one in a float32 evaluation)."""
        info = torch.finfo(s.dtype)
        scale = self._scale
        if not isinstance(scale, Tensor):
            return s.new_full((), min(max(scale, info.tiny), info.max))
        _checks.check_same_kind(fn, s=s, scale=scale)
        if scale.dim() > s.dim() or any(
            a != b and a != 1 and b != 1 for a, b in zip(scale.shape, s.shape, strict=False)
        ):
            raise ValueError(
                f"{fn}: the scale of shape {tuple(scale.shape)} must match the leading dims of "
                f"'s' (shape {tuple(s.shape)}), e.g. scale (B,) for s (B, E)"
            )
        scale = scale.clamp(info.tiny, info.max)
        return scale.reshape(tuple(scale.shape) + (1,) * (s.dim() - scale.dim()))

    @abc.abstractmethod
    def _evaluate_scaled(self, s: Tensor, scale: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(ρ, ρ', ρ'') from s and the aligned scale tensor; finite for every finite s ≥ 0
        and scale in the dtype's positive normal range."""


class HuberLoss(_ScaledKernel):
    """Huber's kernel (Ceres' ``HuberLoss(a)``), quadratic inside |r| ≤ a, linear outside.

    ρ(s) = s for s ≤ a², 2a√s − a² otherwise; ρ' = 1 resp. a/√s; ρ'' = 0 resp. −ρ'/(2s).
    ρ and ρ' are continuous at the knee s = a²; ρ'' jumps there (from 0 to −1/(2a²)).

    Args:
        scale: a > 0, a float or a float tensor (may require grad; dims align with the
            leading dims of s, e.g. (B,) for s of shape (B, E)).
    """

    def _evaluate_scaled(self, s: Tensor, scale: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        outlier = _beyond_knee(s, scale)
        # Double where: the outlier branch sees s > a² > 0 and the scale itself, the inlier
        # positions a harmless (1, 1); ρ = a(2√s − a) ≤ s never overflows (a² alone may).
        s_out = torch.where(outlier, s, 1.0)
        a_out = torch.where(outlier, scale, 1.0)
        root = torch.sqrt(s_out)
        rho1_out = a_out / root
        rho = torch.where(outlier, a_out * (2.0 * root - a_out), s)
        rho1 = torch.where(outlier, rho1_out, 1.0)
        rho2 = torch.where(outlier, _saturate(-0.5 * rho1_out / s_out), 0.0)
        return rho, rho1, rho2

    def _weight_scaled(self, s: Tensor, scale: Tensor) -> Tensor:
        outlier = _beyond_knee(s, scale)
        s_out = torch.where(outlier, s, 1.0)
        a_out = torch.where(outlier, scale, 1.0)
        return torch.where(outlier, a_out / torch.sqrt(s_out), 1.0)


class CauchyLoss(_ScaledKernel):
    """Cauchy (Lorentzian) kernel (Ceres' ``CauchyLoss(a)``): ρ(s) = a² log(1 + s/a²).

    ρ' = 1/(1 + s/a²), ρ'' = −(1/a²)·ρ'², smooth everywhere.

    Args:
        scale: a > 0, a float or a float tensor (may require grad; dims align with the
            leading dims of s, e.g. (B,) for s of shape (B, E)).
    """

    def _evaluate_scaled(self, s: Tensor, scale: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        outer = _beyond_knee(s, scale)
        # Inside (t = s/a² ≤ 1): ρ = s·log1p(t)/t, no a² (it overflows for a ≳ 1e154).
        s_in = torch.where(outer, 0.0, s)
        a_in = torch.where(outer, 1.0, scale)
        t_in = s_in / a_in / a_in
        rho1_in = 1.0 / (1.0 + t_in)
        rho_in = s_in * _log1p_ratio(t_in)
        # Outside (s > a² > 0): ρ' = u/(1 + u) with u = a²/s < 1, ρ = a·(a·log(1 + t)); for
        # t > 1e30 log(1 + t) = log s − 2 log a (the dropped log1p(u) < 1e-30 is far below
        # round-off), so that neither t nor a derivative ∂t/∂a ~ t/a can overflow.
        s_out = torch.where(outer, s, 2.0)
        a_out = torch.where(outer, scale, 1.0)
        u = a_out / s_out * a_out
        with torch.no_grad():
            far = s_out.detach() / a_out.detach() > 1e30 * a_out.detach()
        s_near = torch.where(far, 2.0, s_out)
        a_near = torch.where(far, 1.0, a_out)
        s_far = torch.where(far, s_out, 2.0)
        a_far = torch.where(far, a_out, 1.0)
        log_t = torch.where(
            far,
            torch.log(s_far) - 2.0 * torch.log(a_far),
            torch.log1p(s_near / a_near / a_near),
        )
        rho_out = a_out * (a_out * log_t)
        rho1_out = u / (1.0 + u)
        rho = torch.where(outer, rho_out, rho_in)
        rho1 = torch.where(outer, rho1_out, rho1_in)
        ratio = torch.where(outer, rho1_out / a_out, rho1_in / a_in)
        rho2 = _saturate(-(ratio * ratio))
        return rho, rho1, rho2

    def _weight_scaled(self, s: Tensor, scale: Tensor) -> Tensor:
        outer = _beyond_knee(s, scale)
        s_in = torch.where(outer, 0.0, s)
        a_in = torch.where(outer, 1.0, scale)
        s_out = torch.where(outer, s, 2.0)
        a_out = torch.where(outer, scale, 1.0)
        u = a_out / s_out * a_out
        return torch.where(outer, u / (1.0 + u), 1.0 / (1.0 + s_in / a_in / a_in))


class TukeyLoss(_ScaledKernel):
    """Tukey's biweight (Ceres' ``TukeyLoss(a)``), constant for |r| > a.

    ρ(s) = a²/3 · (1 − (1 − s/a²)³) for s ≤ a², a²/3 otherwise; ρ' = (1 − s/a²)² resp. 0;
    ρ'' = −(2/a²)(1 − s/a²) resp. 0. ρ, ρ' and ρ'' are continuous at the knee s = a².
    This is the form of current Ceres (ρ'(0) = 1 like every other kernel, so ½ρ is the
    textbook biweight a²/6 (1 − (1 − (r/a)²)³)); older Ceres releases returned half of it
    (a²/6 (1 − (1 − s/a²)³), ρ' = ½(1 − s/a²)²).

    Args:
        scale: a > 0, a float or a float tensor (may require grad; dims align with the
            leading dims of s, e.g. (B,) for s of shape (B, E)).
    """

    def _evaluate_scaled(self, s: Tensor, scale: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        outlier = _beyond_knee(s, scale)
        # Inside, with v = 1 − s/a²: a²/3 (1 − v³) = s (1 + v + v²)/3 (no a², which over- or
        # underflows for extreme scales); outside (a²/3, 0, 0) with a² < s finite.
        s_in = torch.where(outlier, 0.0, s)
        a_in = torch.where(outlier, 1.0, scale)
        v = 1.0 - s_in / a_in / a_in
        a_out = torch.where(outlier, scale, 1.0)
        rho = torch.where(outlier, a_out * a_out / 3.0, s_in * ((1.0 + v + v * v) / 3.0))
        rho1 = torch.where(outlier, 0.0, v * v)
        rho2 = torch.where(outlier, 0.0, _saturate(-2.0 * (v / a_in / a_in)))
        return rho, rho1, rho2

    def _weight_scaled(self, s: Tensor, scale: Tensor) -> Tensor:
        outlier = _beyond_knee(s, scale)
        s_in = torch.where(outlier, 0.0, s)
        a_in = torch.where(outlier, 1.0, scale)
        v = 1.0 - s_in / a_in / a_in
        return torch.where(outlier, 0.0, v * v)


def _beyond_knee(s: Tensor, scale: Tensor) -> Tensor:
    """s > a² without forming a² (it over- or underflows for extreme scales), as a mask."""
    with torch.no_grad():
        return s.detach() / scale.detach() > scale.detach()


def _saturate(x: Tensor) -> Tensor:
    """x clamped to the finite range of its dtype: ρ'' of an extreme scale (|ρ''| ~ 1/a²)
    may exceed it; the largest finite value is the honest representable answer."""
    big = torch.finfo(x.dtype).max
    return x.clamp(min=-big, max=big)


def _log1p_ratio(t: Tensor) -> Tensor:
    """log(1 + t)/t for t ∈ [0, 1] (1 at t = 0), smooth with finite derivatives at 0: a
    Taylor series below t = 0.01 (truncation error < t⁸/9 ≤ 2e-17), log1p(t)/t above."""
    small = t < 0.01
    t_small = torch.where(small, t, 0.0)
    t_large = torch.where(small, 1.0, t)
    series = torch.zeros_like(t_small)
    for k in range(7, -1, -1):  # Σ_k (−t)^k / (k + 1), by Horner
        series = 1.0 / (k + 1) - t_small * series
    return torch.where(small, series, torch.log1p(t_large) / t_large)


def triggs_correction(s: Tensor, rho1: Tensor, rho2: Tensor) -> tuple[Tensor, Tensor]:
    """Ceres' ``Corrector``: scalings that make Gauss-Newton minimize ½ρ(‖r‖²) (Triggs).

    With α = 1 − √(1 + 2 s ρ''/ρ'), the corrected residual and Jacobian of one observation
    (r whitened, s = ‖r‖²) are

        r̃ = residual_scale · r,            residual_scale = √ρ' / (1 − α),
        J̃ = √ρ' · (J − alpha_over_s · r (rᵀ J)),   alpha_over_s = α / s,

    so that J̃ᵀ r̃ = ρ' Jᵀ r is exactly the gradient of ½ρ(‖r‖²) and J̃ᵀ J̃ = ρ' JᵀJ + 2ρ'' Jᵀr rᵀJ
    is its Gauss-Newton Hessian (second order in the residual model). Ceres' clamp is kept:
    when s = 0 or ρ'' ≤ 0 (every robust kernel outside its quadratic part) α = 0, i.e. plain
    √ρ' scaling of both r and J (IRLS): the gradient stays exact, the Hessian model becomes
    ρ' JᵀJ, which keeps the normal equations positive semi-definite. The correction also needs
    ρ' > 0; where ρ' = 0 (Tukey outliers) both scalings are 0.

    The J̃ formula applies column by column, so it may be applied to each parameter block of an
    observation separately (always with the uncorrected r). Gradients are finite everywhere,
    including ρ' = 0 and s = 0.

    Args:
        s: squared norms ‖r‖² of the whitened residuals, shape (...), s ≥ 0.
        rho1: ρ'(s) ≥ 0, shape broadcastable with s.
        rho2: ρ''(s), shape broadcastable with s.

    Returns:
        (residual_scale, alpha_over_s), each of shape broadcast(s, rho1, rho2); √ρ', the
        Jacobian's scale, is ``residual_scale * (1 − alpha_over_s * s)``.
    """
    fn = "triggs_correction"
    s = _check_s(fn, s)
    _checks.check_tensor(fn, "rho1", rho1)
    _checks.check_tensor(fn, "rho2", rho2)
    _checks.check_same_kind(fn, s=s, rho1=rho1, rho2=rho2)
    try:
        _checks.broadcast_shapes(s.shape, rho1.shape, rho2.shape)
    except RuntimeError:
        raise ValueError(
            f"{fn}: shapes of 's' {tuple(s.shape)}, 'rho1' {tuple(rho1.shape)} and 'rho2' "
            f"{tuple(rho2.shape)} do not broadcast"
        ) from None
    _checks.check_finite(fn, "rho1", rho1)
    _checks.check_finite(fn, "rho2", rho2)
    if _checks.value_checks_active() and rho1.numel() > 0 and bool((rho1.detach() < 0).any()):
        raise ValueError(f"{fn}: argument 'rho1' must be non-negative (ρ' ≥ 0)")

    positive = rho1 > 0
    # √ρ' with a finite gradient at ρ' = 0 (Tukey outliers): double where.
    sqrt_rho1 = torch.where(positive, torch.sqrt(torch.where(positive, rho1, 1.0)), 0.0)
    full = (s > 0) & (rho2 > 0) & positive
    s_safe = torch.where(full, s, 1.0)
    ratio = torch.where(full, rho2, 0.0) / torch.where(full, rho1, 1.0)
    # α is the smaller root of ½α² − α − (ρ''/ρ') s = 0; D > 1 on the full branch.
    alpha = 1.0 - torch.sqrt(1.0 + 2.0 * s_safe * ratio)
    residual_scale = torch.where(full, sqrt_rho1 / (1.0 - alpha), sqrt_rho1)
    alpha_over_s = torch.where(full, alpha / s_safe, 0.0)
    return residual_scale, alpha_over_s
