"""Validators that build every shape, dtype and value error message of torchslam.

Metadata checks (type, dtype, shape, device) are free and always run at the public boundary.
Value checks (finite, orthonormal, unit norm) need a reduction and a host sync, so they run
only in eager mode with validation switched on (the default). They are skipped automatically
inside ``torch.func`` transforms (``jacrev``/``vmap``), under ``torch.compile``, and inside
``validation(False)`` blocks, which the solver uses on its hot path after checking its
inputs once.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence

import torch
from torch import Tensor

_SUPPORTED_DTYPES = (torch.float32, torch.float64)
_validation_enabled = True


@contextlib.contextmanager
def validation(enabled: bool) -> Iterator[None]:
    """Switch value checks (finite, orthonormal, unit norm) on or off inside a ``with`` block.

    Shape and dtype checks always run; only the checks that need a reduction are affected.
    """
    global _validation_enabled
    previous = _validation_enabled
    _validation_enabled = enabled
    try:
        yield
    finally:
        _validation_enabled = previous


def value_checks_active() -> bool:
    """True when a value check may sync with the host: eager mode, validation switched on."""
    if not _validation_enabled:
        return False
    if torch._C._functorch.maybe_current_level() is not None:
        return False
    return not torch.compiler.is_compiling()


def _shape_str(shape: Sequence[int | str]) -> str:
    return "(" + ", ".join(str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"


def check_tensor(
    fn: str,
    name: str,
    x: object,
    trailing: Sequence[int] = (),
    *,
    min_batch_dims: int = 0,
    floating: bool = True,
) -> Tensor:
    """Check that ``x`` is a tensor of shape ``(..., *trailing)`` with a supported float dtype.

    Args:
        fn: public function name for the message, e.g. ``"se3.exp"``.
        name: argument name for the message, e.g. ``"xi"``.
        x: the value to check.
        trailing: required trailing dimensions.
        min_batch_dims: number of leading dims that must exist in front of ``trailing``.
        floating: require float32 or float64.

    Returns:
        ``x`` unchanged.
    """
    if not isinstance(x, Tensor):
        raise TypeError(f"{fn}: argument '{name}' must be a torch.Tensor, got {type(x).__name__}")
    if floating and x.dtype not in _SUPPORTED_DTYPES:
        raise TypeError(
            f"{fn}: argument '{name}' must be float32 or float64, got {x.dtype}; "
            "convert it with .double() (recommended) or .float()"
        )
    nt = len(trailing)
    expected = _shape_str(
        ["..."] * (1 if min_batch_dims == 0 else 0) + ["B"] * min_batch_dims + list(trailing)
    )
    if x.dim() < nt + min_batch_dims or tuple(x.shape[x.dim() - nt :]) != tuple(trailing):
        raise ValueError(
            f"{fn}: argument '{name}' must have shape {expected}, got {tuple(x.shape)}"
        )
    return x


def check_same_kind(fn: str, **tensors: Tensor) -> None:
    """Reject mixed dtypes or devices among the named tensors (no silent casting)."""
    items = list(tensors.items())
    name0, t0 = items[0]
    for name, t in items[1:]:
        if t.dtype != t0.dtype:
            raise TypeError(
                f"{fn}: '{name0}' is {t0.dtype} but '{name}' is {t.dtype}; "
                "convert one of them first"
            )
        if t.device != t0.device:
            raise ValueError(
                f"{fn}: '{name0}' is on {t0.device} but '{name}' is on {t.device}; "
                "move one of them first"
            )


def check_finite(fn: str, name: str, x: Tensor) -> None:
    """Raise ValueError if ``x`` holds NaN or Inf (only when value checks are active)."""
    if not value_checks_active():
        return
    bad = ~torch.isfinite(x.detach())
    if bool(bad.any()):
        first = tuple(int(i) for i in bad.nonzero()[0].tolist())
        raise ValueError(
            f"{fn}: argument '{name}' contains {int(bad.sum())} non-finite value(s) "
            f"(NaN or Inf), first at index {first}"
        )


def orthonormality_tolerance(dtype: torch.dtype) -> float:
    """Largest accepted max-abs deviation of RᵀR from I (and of |q| from 1)."""
    return 1e-6 if dtype == torch.float64 else 1e-4


def check_rotation(fn: str, name: str, R: Tensor) -> None:
    """Raise ValueError if ``R`` (..., 3, 3) is not a rotation (orthonormal with det +1)."""
    check_finite(fn, name, R)
    if not value_checks_active() or R.numel() == 0:
        return
    Rd = R.detach()
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    deviation = (Rd.transpose(-1, -2) @ Rd - eye).abs().amax(dim=(-1, -2))
    det = torch.linalg.det(Rd)
    tol = orthonormality_tolerance(R.dtype)
    bad = (deviation > tol) | (det <= 0)
    if bool(bad.any()):
        idx = tuple(int(i) for i in bad.nonzero()[0].tolist())
        raise ValueError(
            f"{fn}: argument '{name}' must hold rotation matrices (RᵀR = I within {tol:g}, "
            f"det = +1); at batch index {idx} max|RᵀR - I| = {float(deviation[idx]):.3g}, "
            f"det = {float(det[idx]):.6g}. Project it first with "
            "torchslam.lie.so3.project(R)"
        )


def check_unit_quaternion(fn: str, name: str, q: Tensor) -> None:
    """Raise ValueError if quaternions ``q`` (..., 4) are not unit norm."""
    check_finite(fn, name, q)
    if not value_checks_active() or q.numel() == 0:
        return
    deviation = (torch.linalg.vector_norm(q.detach(), dim=-1) - 1).abs()
    tol = orthonormality_tolerance(q.dtype)
    bad = deviation > tol
    if bool(bad.any()):
        idx = tuple(int(i) for i in bad.nonzero()[0].tolist())
        raise ValueError(
            f"{fn}: argument '{name}' must hold unit quaternions (|q| = 1 within {tol:g}); "
            f"at batch index {idx} |q| = {float(deviation[idx]) + 1:.6g}. "
            "Normalize it first with q / q.norm(dim=-1, keepdim=True)"
        )


def check_pose_matrix(fn: str, name: str, T: Tensor) -> None:
    """Raise ValueError if ``T`` (..., 4, 4) is not a rigid transform [[R, t], [0, 1]]."""
    check_finite(fn, name, T)
    check_rotation(fn, name, T[..., :3, :3])
    if not value_checks_active() or T.numel() == 0:
        return
    bottom = T.detach()[..., 3, :]
    expected = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T.dtype, device=T.device)
    bad = (bottom != expected).any(dim=-1)
    if bool(bad.any()):
        idx = tuple(int(i) for i in bad.nonzero()[0].tolist())
        raise ValueError(
            f"{fn}: argument '{name}' must have bottom row [0, 0, 0, 1]; at batch index {idx} "
            f"it is {bottom[idx].tolist()}"
        )


# ------------------------------------------------------------------------------------------
# Named batched shapes and short descriptions of wrong values (problem, terms, solver).


def describe(value: object) -> str:
    """A short description of a value for an error message: its type, plus the value itself
    for strings and numbers (``str 'lm'``, ``float 0.5``), the class name for classes."""
    if isinstance(value, type):
        return f"the class {value.__name__}"
    if isinstance(value, Tensor):
        return f"Tensor of shape {tuple(value.shape)} and dtype {value.dtype}"
    if isinstance(value, (str, int, float, bool)):
        return f"{type(value).__name__} {value!r}"
    return type(value).__name__


def check_batched(
    fn: str,
    name: str,
    x: object,
    dims: Sequence[str],
    trailing: Sequence[int] = (),
    sizes: Sequence[int | None] | None = None,
    *,
    floating: bool = True,
    against: str = "",
) -> Tensor:
    """Check that ``x`` is a tensor of exactly the shape ``(*dims, *trailing)``.

    Args:
        fn, name: function and argument names for the message.
        x: the value to check.
        dims: names of the leading dims, e.g. ``("B", "m")`` (shown as ``(B, m, 6)``).
        trailing: required trailing sizes, e.g. ``(6,)``.
        sizes: required sizes of the named dims (None: any), e.g. ``(B, m)`` of the data.
        floating: require float32 or float64.
        against: what the sizes come from, for the message (e.g. ``"'data'"``).

    A tensor missing only the leading batch dim gets the hint ``add a leading batch dim with
    name[None]``. Returns ``x`` unchanged.
    """
    check_tensor(fn, name, x, floating=floating)
    assert isinstance(x, Tensor)
    expected = _shape_str(list(dims) + list(trailing))
    got = tuple(x.shape)
    rank = len(dims) + len(trailing)
    nt = len(trailing)
    trailing_ok = x.dim() >= nt and tuple(got[x.dim() - nt :]) == tuple(trailing)
    if x.dim() != rank or not trailing_ok:
        hint = ""
        if x.dim() == rank - 1 and trailing_ok and len(dims) > 1:
            hint = f"; add a leading batch dim with {name}[None]"
        raise ValueError(f"{fn}: argument '{name}' must have shape {expected}, got {got}{hint}")
    if sizes is not None:
        want = [s if s is not None else got[k] for k, s in enumerate(sizes)]
        want += list(got[len(sizes) : len(dims)]) + list(trailing)
        if tuple(want) != got:
            source = f" to match {against}" if against else ""
            raise ValueError(
                f"{fn}: argument '{name}' must have shape {expected} = {_shape_str(want)}"
                f"{source}, got {got}"
            )
    return x
