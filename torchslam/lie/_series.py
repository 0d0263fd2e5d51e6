"""Trigonometric coefficients of the SO(3)/SE(3) formulas, exact at and near θ = 0.

Every coefficient is a function of θ² only. Below ``SMALL_ANGLE_SQUARED`` it is evaluated from
its Taylor series (Horner form, enough terms that truncation is far below float64 round-off on
the whole branch); above, from the closed form. The branches are joined with the double-``where``
idiom: the closed form is evaluated on a "safe" θ² (1.0 swapped into the small slots), so
reverse-mode never sees 0/0 and gradients at θ = 0 are the series' exact ones.

The threshold θ < 0.5 is large on purpose: the closed forms of ``c``, ``d`` and the SE(3)
``q2``/``q3`` coefficients suffer cancellation (e.g. θ − sin θ) that costs up to 1e-11
relative at θ = 0.1, while the 9-term series is exact to round-off up to θ = 0.5.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchslam import _inference

# Taylor branch for θ² below this value (θ < 0.5); same for float32 and float64 since the
# series is accurate to < 1e-20 there.
SMALL_ANGLE_SQUARED = {torch.float32: 0.25, torch.float64: 0.25}

_N_TERMS = 9


def _coefficients(term) -> list[float]:
    return [term(k) for k in range(_N_TERMS)]


# sin θ / θ = Σ (−1)^k θ^2k / (2k+1)!
_A = _coefficients(lambda k: (-1) ** k / math.factorial(2 * k + 1))
# (1 − cos θ) / θ² = Σ (−1)^k θ^2k / (2k+2)!
_B = _coefficients(lambda k: (-1) ** k / math.factorial(2 * k + 2))
# (θ − sin θ) / θ³ = Σ (−1)^k θ^2k / (2k+3)!
_C = _coefficients(lambda k: (-1) ** k / math.factorial(2 * k + 3))
# (θ² + 2 cos θ − 2) / (2 θ⁴) = Σ (−1)^k θ^2k / (2k+4)!
_Q2 = _coefficients(lambda k: (-1) ** k / math.factorial(2 * k + 4))
# (2θ − 3 sin θ + θ cos θ) / (2 θ⁵) = Σ (−1)^k (k+1) θ^2k / (2k+5)!
_Q3 = _coefficients(lambda k: (-1) ** k * (k + 1) / math.factorial(2 * k + 5))
# (1 − (θ/2) cot(θ/2)) / θ² = Σ |B_2k+2| θ^2k / (2k+2)!   (Bernoulli numbers)
_BERNOULLI_ABS = [1 / 6, 1 / 30, 1 / 42, 1 / 30, 5 / 66, 691 / 2730, 7 / 6, 3617 / 510, 43867 / 798]
_D = [_BERNOULLI_ABS[k] / math.factorial(2 * k + 2) for k in range(_N_TERMS)]
# atan(x) / x = Σ (−1)^k x^2k / (2k+1)
_ATAN = _coefficients(lambda k: (-1) ** k / (2 * k + 1))


def _horner(x: Tensor, coefficients: list[float]) -> Tensor:
    result = x * coefficients[-1] + coefficients[-2]
    for c in reversed(coefficients[:-2]):
        result = result * x + c
    return result


_TABLES: dict[tuple, Tensor] = {}


def constant(key: object, values: object, dtype: torch.dtype, device: torch.device) -> Tensor:
    """``torch.as_tensor(values, dtype, device)``, made once per (key, dtype, device): the
    coefficient tables, index vectors and other constant matrices of the library (small
    batches are bound by the number of tensor operations, and making a tensor costs several).
    ``values``: nested sequences or a tensor, or a function returning them (called only when
    the table is made)."""
    full_key = (key, dtype, device)
    table = _TABLES.get(full_key)
    if table is None:
        with _inference.outside():  # a normal tensor, usable after an inference-mode solve
            table = torch.as_tensor(
                values() if callable(values) else values, dtype=dtype, device=device
            )
        # Cache plain tensors only (a few tables × dtypes × devices): not an inference tensor
        # (inference_mode) nor a fake one (FakeTensorMode), which later calls could not use.
        if type(table) is torch.Tensor and not table.is_inference():
            _TABLES[full_key] = table
    return table


_ROWS: dict[tuple, tuple[Tensor, ...]] = {}


def _rows(key: tuple, series: tuple, dtype: torch.dtype, device: torch.device) -> tuple:
    """The rows of the (terms, k) coefficient table of ``series`` (:func:`constant`), unbound
    once per (key, dtype, device) (unbinding costs one operation per row)."""
    full_key = (key, dtype, device)
    rows = _ROWS.get(full_key)
    if rows is None:
        table = constant(key, list(zip(*series, strict=True)), dtype, device)
        with _inference.outside():
            rows = table.unbind(0)
        if _TABLES.get(full_key) is table:  # cached only where the table is
            _ROWS[full_key] = rows
    return rows


def eye(n: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """``torch.eye(n, dtype, device)`` made once per (n, dtype, device) (:func:`constant`);
    shared: never write to it."""
    return constant(("eye", n), lambda: torch.eye(n, dtype=torch.float64), dtype, device)


def _horner_stack(x: Tensor, *series: list[float]) -> tuple[Tensor, ...]:
    """:func:`_horner` of several series at the same x, in one pass over a (…, k) stack:
    the same operations per entry (bit for bit the same values), a third of the tensor
    operations for three series."""
    rows = _rows(tuple(id(c) for c in series), series, x.dtype, x.device)
    xs = x[..., None]
    result = xs * rows[-1] + rows[-2]
    for row in reversed(rows[:-2]):
        result = result * xs + row
    return result.unbind(-1)


def _split(theta2: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Return (small mask, safe θ², safe θ) for the double-where idiom."""
    small = theta2 < SMALL_ANGLE_SQUARED[theta2.dtype]
    theta2_safe = torch.where(small, 1.0, theta2)
    return small, theta2_safe, torch.sqrt(theta2_safe)


def sinc_coefficients(theta2: Tensor) -> tuple[Tensor, Tensor]:
    """(a, b) = (sin θ / θ, (1 − cos θ) / θ²), the Rodrigues coefficients of seed eq. L4.1."""
    small, t2, t = _split(theta2)
    a = torch.sin(t) / t
    # 2 sin²(θ/2) avoids the cancellation of 1 − cos θ.
    b = 2.0 * torch.sin(0.5 * t) ** 2 / t2
    a_series, b_series = _horner_stack(theta2, _A, _B)
    return torch.where(small, a_series, a), torch.where(small, b_series, b)


def _all_small(small: Tensor) -> bool:
    """Whether every angle is on the series branch, read on the host: only for plain CPU
    tensors outside ``torch.func`` transforms (elsewhere False, without a read)."""
    return (
        type(small) is torch.Tensor
        and small.device.type == "cpu"
        and not torch._C._functorch.is_functorch_wrapped_tensor(small)
        and bool(small.all())
    )


def exp_coefficients(theta2: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(a, b, c) of :func:`sinc_coefficients` and :func:`jacobian_coefficient_c` at once (the
    same values, one series pass): what Exp of SE(3) needs. When every angle is on the series
    branch (a solver's step, on the CPU), the closed forms are not evaluated: the same values
    and gradients, half the operations."""
    small = theta2 < SMALL_ANGLE_SQUARED[theta2.dtype]
    if _all_small(small):
        return _horner_stack(theta2, _A, _B, _C)
    theta2_safe = torch.where(small, 1.0, theta2)
    t2, t = theta2_safe, torch.sqrt(theta2_safe)
    s = torch.sin(t)
    a = s / t
    b = 2.0 * torch.sin(0.5 * t) ** 2 / t2
    c = (t - s) / (t2 * t)
    a_series, b_series, c_series = _horner_stack(theta2, _A, _B, _C)
    return (
        torch.where(small, a_series, a),
        torch.where(small, b_series, b),
        torch.where(small, c_series, c),
    )


def jacobian_coefficient_c(theta2: Tensor) -> Tensor:
    """c = (θ − sin θ) / θ³, the [ω]×² coefficient of the SO(3) left Jacobian."""
    small, t2, t = _split(theta2)
    return torch.where(small, _horner(theta2, _C), (t - torch.sin(t)) / (t2 * t))


def inverse_jacobian_coefficient_d(theta2: Tensor) -> Tensor:
    """d = (1 − (θ/2) cot(θ/2)) / θ², the [ω]×² coefficient of the inverse left Jacobian.

    Written with cot(θ/2) it is finite at θ = π (where 1 + cos θ and sin θ both vanish).
    """
    small, t2, t = _split(theta2)
    half = 0.5 * t
    closed = (1.0 - half * torch.cos(half) / torch.sin(half)) / t2
    return torch.where(small, _horner(theta2, _D), closed)


def se3_q_coefficients(theta2: Tensor) -> tuple[Tensor, Tensor]:
    """(q2, q3) of Barfoot's Q(ρ, φ) block of the SE(3) left Jacobian.

    q2 = (θ² + 2 cos θ − 2) / (2 θ⁴), q3 = (2θ − 3 sin θ + θ cos θ) / (2 θ⁵).
    """
    small, t2, t = _split(theta2)
    s, c = torch.sin(t), torch.cos(t)
    q2 = (t2 + 2.0 * c - 2.0) / (2.0 * t2 * t2)
    q3 = (2.0 * t - 3.0 * s + t * c) / (2.0 * t2 * t2 * t)
    q2_series, q3_series = _horner_stack(theta2, _Q2, _Q3)
    return torch.where(small, q2_series, q2), torch.where(small, q3_series, q3)


def atan_ratio(y: Tensor, x: Tensor) -> Tensor:
    """atan2(y, x) / y for y ≥ 0 and x > 0 near y = 0, exact at y = 0 (value 1/x).

    Used by the SO(3) log: θ / sin(θ/2) = 2 · atan_ratio(|v|, w) for a quaternion (w, v).
    """
    # The atan series converges slowly (no factorials), so its branch is narrower; atan2 has
    # no cancellation, only the 0/0 at y = 0 to avoid. Both branches see safe inputs, so the
    # gradient is finite at y = 0 and at x = 0 (θ = π).
    small = y * y < 1e-2 * (x * x)
    x_safe = torch.where(small, x, 1.0)
    r2 = torch.where(small, (y / x_safe) ** 2, 0.0)
    y_safe = torch.where(small, 1.0, y)
    closed = torch.atan2(y_safe, x) / y_safe
    return torch.where(small, _horner(r2, _ATAN) / x_safe, closed)


def atan_ratio_squared(y2: Tensor, x: Tensor) -> Tensor:
    """atan2(y, x) / y for y = √y2 ≥ 0, as a function of y2 (exact at y2 = 0, value 1/x).

    The same function as :func:`atan_ratio`, but reading y² instead of y, so that callers
    never take the norm y = |v| of a vector: its derivative v/|v| is 0/0 at v = 0, which the
    first backward masks but a double backward turns into NaN. Here both branches see safe
    inputs (the square root is taken of y2 only where y2 is large), so first and second
    derivatives are finite, and exact, at y2 = 0.
    """
    small = y2 < 1e-2 * (x * x)
    x_safe = torch.where(small, x, 1.0)
    r2 = torch.where(small, y2 / (x_safe * x_safe), 0.0)
    y_safe = torch.sqrt(torch.where(small, 1.0, y2))
    closed = torch.atan2(y_safe, x) / y_safe
    return torch.where(small, _horner(r2, _ATAN) / x_safe, closed)
