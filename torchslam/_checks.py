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
import operator
from collections.abc import Iterable, Iterator, Sequence

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
    dims: Sequence[str] | None = None,
) -> Tensor:
    """Check that ``x`` is a tensor of shape ``(..., *trailing)`` with a supported float dtype.

    Args:
        fn: public function name for the message, e.g. ``"se3.exp"``.
        name: argument name for the message, e.g. ``"xi"``.
        x: the value to check.
        trailing: required trailing dimensions.
        min_batch_dims: number of leading dims that must exist in front of ``trailing``.
        floating: require float32 or float64.
        dims: names of the ``min_batch_dims`` leading dims for the message, e.g.
            ``("B", "m")``; default ``B`` for the first and ``d1``, ``d2``, … after it.

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
    shape = x.shape
    if len(shape) >= nt + min_batch_dims and (nt == 0 or shape[-nt:] == tuple(trailing)):
        return x  # the common case; the message below is built only on failure (hot paths)
    if dims is None or len(dims) != min_batch_dims:
        dims = ["B"] + [f"d{k}" for k in range(1, min_batch_dims)] if min_batch_dims else []
    expected = _shape_str(["..."] * (1 if min_batch_dims == 0 else 0) + list(dims) + list(trailing))
    if x.dim() < nt + min_batch_dims or tuple(x.shape[x.dim() - nt :]) != tuple(trailing):
        hint = ""
        if (
            min_batch_dims > 0
            and dims[0] == "B"
            and x.dim() == nt + min_batch_dims - 1
            and tuple(x.shape[x.dim() - nt :]) == tuple(trailing)
        ):
            hint = f"; add a leading batch dim with {name}[None]"
        raise ValueError(
            f"{fn}: argument '{name}' must have shape {expected}, got {tuple(x.shape)}{hint}"
        )
    return x


def check_same_kind(fn: str, **tensors: Tensor) -> None:
    """Reject mixed dtypes or devices among the named tensors (no silent casting)."""
    values = list(tensors.values())
    dtype, device = values[0].dtype, values[0].device
    for t in values:
        if t.dtype != dtype or t.device != device:
            break
    else:
        return  # the common case, without building the messages below (hot paths)
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
    if not (x.is_floating_point() or x.is_complex()):
        return  # integers and booleans are finite
    bad = ~(x.detach().abs() < _math.inf)  # isfinite in two operations (NaN compares False)
    if bool(bad.any()):
        first = tuple(int(i) for i in bad.nonzero()[0].tolist())
        raise ValueError(
            f"{fn}: argument '{name}' contains {int(bad.sum())} non-finite value(s) "
            f"(NaN or Inf), first at index {first}"
        )


def orthonormality_tolerance(dtype: torch.dtype) -> float:
    """Largest accepted max-abs deviation of RᵀR from I (and of |q| from 1)."""
    return 1e-6 if dtype == torch.float64 else 1e-4


def check_rotation(fn: str, name: str, R: Tensor, *, finite_checked: bool = False) -> None:
    """Raise ValueError if ``R`` (..., 3, 3) is not a rotation (orthonormal with det +1);
    ``finite_checked``: the caller has checked that R is finite."""
    if not value_checks_active():
        return
    if not finite_checked:
        check_finite(fn, name, R)
    if R.numel() == 0:
        return
    Rd = R.detach()
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    deviation = (Rd.transpose(-1, -2) @ Rd - eye).abs().amax(dim=(-1, -2))
    # det R = r₀ · (r₁ × r₂) of its rows: a few operations (linalg.det factors each matrix).
    det = (Rd[..., 0, :] * torch.linalg.cross(Rd[..., 1, :], Rd[..., 2, :], dim=-1)).sum(-1)
    tol = orthonormality_tolerance(R.dtype)
    # NaN-safe: RᵀR and det overflow to Inf/NaN for huge finite entries, and NaN > tol is False.
    bad = ~(deviation <= tol) | ~(det > 0)
    if bool(bad.any()):
        idx = tuple(int(i) for i in bad.nonzero()[0].tolist())
        raise ValueError(
            f"{fn}: argument '{name}' must hold rotation matrices (RᵀR = I within {tol:g}, "
            f"det = +1); at batch index {idx} max|RᵀR - I| = "
            f"{_deviation_str(deviation[idx], Rd[idx])}, det = {float(det[idx]):.6g}. "
            "Project it first with torchslam.lie.so3.project(R)"
        )


def check_unit_quaternion(fn: str, name: str, q: Tensor) -> None:
    """Raise ValueError if quaternions ``q`` (..., 4) are not unit norm."""
    if not value_checks_active():
        return
    check_finite(fn, name, q)
    if q.numel() == 0:
        return
    norm = torch.linalg.vector_norm(q.detach(), dim=-1)
    tol = orthonormality_tolerance(q.dtype)
    bad = ~((norm - 1).abs() <= tol)  # NaN-safe
    if bool(bad.any()):
        idx = tuple(int(i) for i in bad.nonzero()[0].tolist())
        raise ValueError(
            f"{fn}: argument '{name}' must hold unit quaternions (|q| = 1 within {tol:g}); "
            f"at batch index {idx} |q| = {_magnitude_str(q.detach()[idx])}. "
            "Normalize it first with q / q.norm(dim=-1, keepdim=True)"
        )


def _bottom_row(dtype: torch.dtype, device: torch.device) -> Tensor:
    """[0, 0, 0, 1], made once per dtype and device."""
    from torchslam.lie import _series  # here: the lie package imports this module

    return _series.constant("pose bottom row", (0.0, 0.0, 0.0, 1.0), dtype, device)


def check_pose_matrix(fn: str, name: str, T: Tensor) -> None:
    """Raise ValueError if ``T`` (..., 4, 4) is not a rigid transform [[R, t], [0, 1]]."""
    if not value_checks_active():
        return  # before slicing T: this is on hot paths under validation(False)
    check_finite(fn, name, T)
    check_rotation(fn, name, T[..., :3, :3], finite_checked=True)
    if T.numel() == 0:
        return
    bottom = T.detach()[..., 3, :]
    bad = (bottom != _bottom_row(T.dtype, T.device)).any(dim=-1)
    if bool(bad.any()):
        idx = tuple(int(i) for i in bad.nonzero()[0].tolist())
        raise ValueError(
            f"{fn}: argument '{name}' must have bottom row [0, 0, 0, 1]; at batch index {idx} "
            f"it is {bottom[idx].tolist()}"
        )


# --------------------------------------------------------------------------------------------
# Lie-group boundary checks (lie-checks branch): NaN-safe messages, broadcasting, sizes and
# results that overflow although the arguments are finite.
# --------------------------------------------------------------------------------------------


def _magnitude_str(x: Tensor) -> str:
    """The Euclidean norm of ``x`` for a message, computed without overflow or underflow."""
    scale = x.abs().amax() if x.numel() else x.new_zeros(())
    if not bool(torch.isfinite(scale)):
        return "non-finite"
    if float(scale) == 0.0:
        return "0"
    # |x| = s·|x / s|; in float64 on the host (Python floats), so 1e300 prints as 1.7e300.
    ratio = float(torch.linalg.vector_norm((x / scale).double()))
    return f"{float(scale) * ratio:.6g}"


def _deviation_str(deviation: Tensor, R: Tensor) -> str:
    """max|RᵀR − I| for a message; when it overflows, say so and give the largest entry."""
    if bool(torch.isfinite(deviation)):
        return f"{float(deviation):.3g}"
    return f"too large to compute (largest |entry| = {float(R.abs().amax()):.3g})"


def check_broadcast(fn: str, **batch_shapes: Sequence[int]) -> tuple[int, ...]:
    """Broadcast the leading (batch) shapes of named arguments, or raise ValueError naming them.

    Args:
        fn: public function name for the message.
        batch_shapes: argument name → its batch shape (the shape without the trailing dims).

    Returns:
        The broadcast batch shape.
    """
    shape = _broadcast_shapes(list(batch_shapes.values()))
    if shape is None:
        described = " and ".join(
            f"'{name}' with batch shape {tuple(shape)}" for name, shape in batch_shapes.items()
        )
        raise ValueError(
            f"{fn}: the leading (batch) dims of the arguments do not broadcast: {described}"
        )
    return shape


def _broadcast_shapes(shapes: list[Sequence[int]]) -> tuple[int, ...] | None:
    """torch.broadcast_shapes in plain Python (that one costs ~30 µs a call, too much for hot
    paths), or None when the shapes do not broadcast."""
    result = list(shapes[0])
    for shape in shapes[1:]:
        if len(shape) > len(result):
            result = [1] * (len(shape) - len(result)) + result
        offset = len(result) - len(shape)
        for k, size in enumerate(shape):
            current = result[offset + k]
            if size != current and size != 1:
                if current != 1:
                    return None
                result[offset + k] = size
    return tuple(result)


def broadcast_shapes(*shapes: Sequence[int]) -> torch.Size:
    """``torch.broadcast_shapes`` for plain shapes, without its first call's cost (it imports
    ``torch._refs``: ~0.2 s, once per process, on the path of every entry point that uses it);
    RuntimeError when the shapes do not broadcast, as torch's."""
    result = _broadcast_shapes([tuple(shape) for shape in shapes]) if shapes else ()
    if result is None:
        raise RuntimeError(f"shapes {[tuple(s) for s in shapes]} do not broadcast")
    return torch.Size(result)


def check_sizes(fn: str, name: str, sizes: Sequence[object]) -> tuple[int, ...]:
    """Check a batch shape given as ints (TypeError unless int-like, ValueError if negative)."""
    checked = []
    for size in sizes:
        try:
            if isinstance(size, bool):
                raise TypeError
            value = operator.index(size)  # int, numpy integers, 0-dim integer tensors
        except TypeError:
            raise TypeError(
                f"{fn}: argument '{name}' must be ints, got {type(size).__name__} ({size!r})"
            ) from None
        if value < 0:
            raise ValueError(f"{fn}: argument '{name}' must be non-negative ints, got {value}")
        checked.append(value)
    return tuple(checked)


def check_dtype_device(fn: str, dtype: object, device: object) -> None:
    """Check the ``dtype`` (float32/float64) and ``device`` keyword arguments of a factory."""
    if dtype not in _SUPPORTED_DTYPES:
        raise TypeError(
            f"{fn}: argument 'dtype' must be torch.float32 or torch.float64, got {dtype}"
        )
    if device is None or isinstance(device, torch.device):
        return
    if not isinstance(device, str):
        raise TypeError(
            f"{fn}: argument 'device' must be a torch.device, a str or None, "
            f"got {type(device).__name__}"
        )
    try:
        torch.device(device)
    except RuntimeError as error:
        raise ValueError(f"{fn}: argument 'device' is not a device: {device!r} ({error})") from None


def check_result_finite(
    fn: str, result: Tensor, *, reason: str | None = None, **arguments: Tensor
) -> None:
    """Raise ValueError if ``result`` overflowed (only when value checks are active).

    Call it after the arguments passed :func:`check_finite`: a non-finite result then means the
    arguments are too large in magnitude for the result to be representable in their dtype
    (or the map is singular there); the message names every argument with its magnitude.
    """
    if not value_checks_active() or result.numel() == 0:
        return
    if bool(torch.isfinite(result.detach()).all()):
        return
    described = ", ".join(
        f"'{name}' (largest |entry| {float(t.detach().abs().amax()):.3g})"
        if t.numel()
        else f"'{name}'"
        for name, t in arguments.items()
    )
    why = reason or "too large in magnitude for the result to be representable"
    raise ValueError(
        f"{fn}: the result is not finite ({result.dtype}) although the arguments are finite: "
        f"argument(s) {described}: {why}"
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


# --------------------------------------------------------------------------------------------
# Point clouds and scalar arguments (fix-icp branch): numpy/torch clouds at the boundary of the
# ICP front end (icp, alignment, tracks), and plain numbers (ints, reals) in configs.
# --------------------------------------------------------------------------------------------


def first_tensor(*values: object) -> Tensor | None:
    """The first torch tensor among ``values`` (the device numpy arguments are moved to)."""
    for value in values:
        if isinstance(value, Tensor):
            return value
    return None


def from_numpy(x: object, like: Tensor | None = None) -> object:
    """A numpy array as a (copied) tensor on ``like``'s device; anything else unchanged.

    Float arrays keep their precision (float32 stays float32, float64 stays float64; foreign
    byte orders are converted), so mixing float32 and float64 still meets the dtype checks.
    """
    import numpy as np

    if not isinstance(x, np.ndarray):
        return x
    dtype = x.dtype.newbyteorder("=") if x.dtype.byteorder not in ("=", "|") else x.dtype
    copied = np.array(x, dtype=dtype, order="C", copy=True)
    tensor = torch.from_numpy(copied)
    return tensor if like is None else tensor.to(like.device)


def as_points(
    fn: str,
    name: str,
    x: object,
    *,
    like: Tensor | None = None,
    cloud: bool = True,
    min_points: int = 0,
    finite: bool | None = None,
) -> Tensor:
    """Check a point array and return it as a tensor (numpy float arrays are accepted).

    Args:
        fn, name: function and argument names for the messages.
        x: a torch tensor or a numpy array, float32 or float64.
        like: a tensor whose device a numpy array is moved to.
        cloud: require shape (N, 3) exactly; otherwise (..., 3).
        min_points: smallest N (the size of dim −2) for a cloud.
        finite: refuse NaN/Inf always (True: host-bound code such as KD-trees), only when
            value checks are active (None), or never (False).
    """
    import numpy as np

    if not isinstance(x, (Tensor, np.ndarray)):
        raise TypeError(
            f"{fn}: argument '{name}' must be a torch.Tensor or a numpy array of points, "
            f"got {describe(x)}"
        )
    if isinstance(x, np.ndarray) and (x.dtype.kind != "f" or x.dtype.itemsize not in (4, 8)):
        raise TypeError(
            f"{fn}: argument '{name}' must be float32 or float64, got a numpy array of "
            f"dtype {x.dtype}"
        )
    tensor = from_numpy(x, like)
    assert isinstance(tensor, Tensor)
    check_tensor(fn, name, tensor, (3,))
    if cloud and (tensor.dim() != 2 or tensor.shape[0] < min_points):
        at_least = f" with N ≥ {min_points}" if min_points > 0 else ""
        raise ValueError(
            f"{fn}: argument '{name}' must have shape (N, 3){at_least}, got {tuple(tensor.shape)}"
        )
    if finite or (finite is None and value_checks_active()):
        bad = ~torch.isfinite(tensor.detach())
        if bool(bad.any()):
            first = tuple(int(i) for i in bad.nonzero()[0].tolist())
            raise ValueError(
                f"{fn}: argument '{name}' contains {int(bad.sum())} non-finite value(s) "
                f"(NaN or Inf), first at index {first}"
            )
    return tensor


# --------------------------------------------------------------------------------------------
# Plain-Python arguments (fix-reg branch): numbers, seeds, dtypes, devices, paths and names, for
# the register / io / data / initialization boundary and config dataclasses.
# --------------------------------------------------------------------------------------------

import math as _math  # noqa: E402
import numbers as _numbers  # noqa: E402
import os as _os  # noqa: E402


def _got(value: object) -> str:
    """``10.0 (float)``, ``'8' (str)`` for plain values, the type name otherwise."""
    if isinstance(value, (str, int, float, bool, complex)) or value is None:
        return f"{value!r} ({type(value).__name__})"
    return describe(value)


def check_bool(fn: str, name: str, value: object) -> bool:
    """TypeError ``{fn}: argument '{name}' must be a bool, got …`` unless ``value`` is one."""
    if not isinstance(value, bool):
        raise TypeError(f"{fn}: argument '{name}' must be a bool, got {describe(value)}")
    return value


def check_int(
    fn: str,
    name: str,
    value: object,
    *,
    minimum: int | None = None,
    maximum: int | None = None,
    kind: str = "argument",
) -> int:
    """An int (or numpy integer; not bool) in [minimum, maximum]: TypeError / ValueError.

    ``kind`` names what ``name`` is in the message (``"argument"``, ``"field"``).
    """
    bounds = []
    if minimum is not None:
        bounds.append(f">= {minimum}")
    if maximum is not None:
        bounds.append(f"<= {maximum}")
    expected = "an int" + (" " + " and ".join(bounds) if bounds else "")
    if isinstance(value, bool) or not isinstance(value, _numbers.Integral):
        raise TypeError(f"{fn}: {kind} '{name}' must be an int, got {_got(value)}")
    result = operator.index(value)
    if (minimum is not None and result < minimum) or (maximum is not None and result > maximum):
        raise ValueError(f"{fn}: {kind} '{name}' must be {expected}, got {result!r}")
    return result


def check_real(
    fn: str,
    name: str,
    value: object,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
    kind: str = "argument",
    allow_inf: bool = False,
) -> float:
    """A finite real number (int, float, numpy scalar; not bool) in a range, as a float.

    The range is [low, high], with ``low_open`` / ``high_open`` excluding an end; None leaves
    that side unbounded; ``allow_inf`` also accepts ±inf within the range. TypeError for a
    non-number, ValueError for NaN, Inf (unless allowed) or out of range.
    """
    parts = []
    if low is not None and high is not None:
        parts.append(f"in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}")
    elif low is not None:
        parts.append(f"{'>' if low_open else '>='} {low:g}")
    elif high is not None:
        parts.append(f"{'<' if high_open else '<='} {high:g}")
    number = "a number (inf allowed)" if allow_inf else "a finite number"
    expected = number + (" " + parts[0] if parts else "")
    if isinstance(value, bool) or not isinstance(value, _numbers.Real):
        raise TypeError(f"{fn}: {kind} '{name}' must be a real number, got {_got(value)}")
    try:
        result = float(value)
    except OverflowError:  # an int beyond the float range
        result = _math.inf if value > 0 else -_math.inf
    ok = not _math.isnan(result) and (allow_inf or _math.isfinite(result))
    if ok and low is not None:
        ok = result > low if low_open else result >= low
    if ok and high is not None:
        ok = result < high if high_open else result <= high
    if not ok:
        raise ValueError(f"{fn}: {kind} '{name}' must be {expected}, got {value!r}")
    return result


def check_float_dtype(fn: str, dtype: object, name: str = "dtype") -> torch.dtype:
    """``dtype`` must be torch.float32 or torch.float64 (TypeError otherwise)."""
    if not isinstance(dtype, torch.dtype) or dtype not in _SUPPORTED_DTYPES:
        got = str(dtype) if isinstance(dtype, torch.dtype) else describe(dtype)
        raise TypeError(
            f"{fn}: argument '{name}' must be torch.float32 or torch.float64, got {got}"
        )
    return dtype


def check_device(fn: str, device: object, name: str = "device") -> torch.device | None:
    """``device`` must be None, a torch.device or a device string; returns it parsed."""
    if device is None or isinstance(device, torch.device):
        return device
    if not isinstance(device, str):
        raise TypeError(
            f"{fn}: argument '{name}' must be a torch.device, a str or None, got {describe(device)}"
        )
    try:
        return torch.device(device)
    except (RuntimeError, ValueError) as error:
        raise ValueError(f"{fn}: argument '{name}' is not a device: {device!r} ({error})") from None


# torch.Generator.manual_seed accepts the int64 and uint64 ranges together.
SEED_RANGE = (-(2**63), 2**64 - 1)


def check_seed(fn: str, seed: object, name: str = "seed") -> int:
    """A generator seed: an int in [-2**63, 2**64 - 1] (what torch.Generator accepts)."""
    return check_int(fn, name, seed, minimum=SEED_RANGE[0], maximum=SEED_RANGE[1])


def check_path(fn: str, path: object, name: str = "path", *, is_file: bool = False) -> str:
    """A file system path (str or os.PathLike); with ``is_file``, an existing regular file.

    TypeError for another type (an int would open a file descriptor); ValueError for an empty
    path or a directory; FileNotFoundError (an OSError) for a missing file. Returns the path
    as a str.
    """
    if isinstance(path, (str, _os.PathLike)):
        text = _os.fspath(path)
        text = _os.fsdecode(text) if isinstance(text, bytes) else text
    else:
        raise TypeError(
            f"{fn}: argument '{name}' must be a str or os.PathLike, got {describe(path)}"
        )
    if not text:
        raise ValueError(f"{fn}: argument '{name}' must be a non-empty path, got ''")
    if is_file:
        if _os.path.isdir(text):
            raise ValueError(f"{fn}: argument '{name}' must be a file, got the directory {text}")
        if not _os.path.exists(text):
            raise FileNotFoundError(2, f"{fn}: no such file", text)
        if not _os.path.isfile(text):
            raise ValueError(f"{fn}: argument '{name}' must be a regular file, got {text}")
    return text


def check_names(
    fn: str, names: object, name: str = "names", *, count: int | None = None, words: bool = True
) -> list[str]:
    """A sequence of distinct str names (not a single str), ``count`` of them if given.

    With ``words``, each name must be a single word usable in a text file: non-empty, no
    white space and not starting with ``#`` (a comment). Returns them as a list.
    """
    if isinstance(names, (str, bytes)) or not isinstance(names, Sequence):
        raise TypeError(
            f"{fn}: argument '{name}' must be a sequence (list or tuple) of str, "
            f"got {describe(names)}"
        )
    out = list(names)
    for k, item in enumerate(out):
        if not isinstance(item, str):
            raise TypeError(
                f"{fn}: argument '{name}' must hold str, got {describe(item)} at index {k}"
            )
        if words and (not item or item.startswith("#") or any(c.isspace() for c in item)):
            raise ValueError(
                f"{fn}: argument '{name}' must hold non-empty names without white space that "
                f"do not start with '#', got {item!r} at index {k}"
            )
    if count is not None and len(out) != count:
        raise ValueError(f"{fn}: argument '{name}' must hold {count} names, got {len(out)}")
    repeated = sorted({n for k, n in enumerate(out) if n in out[:k]})
    if repeated:
        raise ValueError(
            f"{fn}: argument '{name}' must hold distinct names, repeated: "
            + ", ".join(map(repr, repeated))
        )
    return out


def check_index_pairs(fn: str, pairs: object, m: int) -> list[tuple[int, int]]:
    """Scan pairs (any iterable of 2-item iterables) as a list of (i, k) ints with
    0 ≤ i, k < m and i ≠ k: TypeError / ValueError naming ``fn``."""
    if isinstance(pairs, (str, bytes)) or not isinstance(pairs, Iterable):
        raise TypeError(
            f"{fn}: argument 'pairs' must be a sequence of (i, k) scan pairs, got {describe(pairs)}"
        )
    checked = []
    for position, pair in enumerate(pairs):
        items = (
            [] if isinstance(pair, (str, bytes)) or not isinstance(pair, Iterable) else list(pair)
        )
        if len(items) != 2:
            raise ValueError(
                f"{fn}: argument 'pairs' must hold (i, k) pairs, got {pair!r} at position "
                f"{position}"
            )
        i, k = (check_int(fn, f"pairs[{position}]", x) for x in items)
        if not (0 <= i < m and 0 <= k < m and i != k):
            raise ValueError(
                f"{fn}: argument 'pairs' holds the invalid scan pair ({i}, {k}) at position "
                f"{position}: need 0 ≤ i, k < {m} (the number of clouds) and i ≠ k"
            )
        checked.append((i, k))
    return checked


# ---- sequences of objects -------------------------------------------------------------------


def check_sequence(
    fn: str, name: str, values: object, kind: type, what: str, item: str | None = None
) -> tuple:
    """``values`` as a tuple, after checking it is a list or tuple (of ``what``) whose items
    are ``kind`` (each ``item``, default ``what``); TypeError naming ``fn`` and the argument or
    item."""
    if not isinstance(values, (list, tuple)):
        raise TypeError(
            f"{fn}: argument '{name}' must be a list or tuple of {what}, got {describe(values)}"
        )
    for k, value in enumerate(values):
        if not isinstance(value, kind):
            raise TypeError(f"{fn}: {name}[{k}] must be {item or what}, got {describe(value)}")
    return tuple(values)


def check_integer_tensor(fn: str, name: str, x: Tensor, what: str = "be an integer tensor") -> None:
    """TypeError ``{fn}: argument '{name}' must {what}, got {dtype}`` unless ``x`` (a tensor)
    has an integer dtype (not bool): index arguments."""
    if x.dtype.is_floating_point or x.dtype.is_complex or x.dtype == torch.bool:
        raise TypeError(f"{fn}: argument '{name}' must {what}, got {x.dtype}")
