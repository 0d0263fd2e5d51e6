"""``torch.inference_mode`` for the solves that need no gradient, kept from leaking.

Small problems are bound by the number of tensor operations, and each costs less in inference
mode than under ``torch.no_grad`` (no version counters, no autograd metadata): a no-grad solve
of the S benchmark runs ~15% faster (:func:`torchslam.solve_tensors`). Tensors made in inference
mode cannot be saved for a later backward nor edited in place outside it, so none may leave:

- :func:`plain` clones the inference tensors of a result (a tensor or a dataclass of them) into
  normal ones before it is returned;
- :func:`outside` makes the tensors that are cached across calls (constant tables, index
  tensors, per-term factors) normal ones, with the grad mode as it was;
- :func:`cacheable`: an inference tensor has no version counter, so a cache keyed by one (the
  segment sums' sparse matrices) is not kept for it.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Iterator

import torch
from torch import Tensor

__all__ = ["cacheable", "outside", "plain", "tracked"]


@contextlib.contextmanager
def outside() -> Iterator[None]:
    """Tensors made inside are normal tensors, also under ``torch.inference_mode``; the grad
    mode is the one outside this block."""
    if not torch.is_inference_mode_enabled():
        yield
        return
    grad = torch.is_grad_enabled()
    with torch.inference_mode(False), torch.set_grad_enabled(grad):
        yield


def tracked(*tensors: Tensor | None) -> bool:
    """Whether autograd would record an operation on ``tensors`` (None entries skipped): grad
    mode is on and one of them requires a gradient."""
    return torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in tensors)


def cacheable(t: Tensor) -> bool:
    """Whether ``t`` has a version counter (a cache can tell an in-place edit)."""
    return not t.is_inference()


def plain(value):
    """``value`` with every inference tensor cloned into a normal one: a tensor, a list or
    tuple of them, or a dataclass whose fields hold them (not nested dataclasses); others as
    given."""
    if isinstance(value, Tensor):
        if not value.is_inference():
            return value
        with torch.inference_mode(False), torch.no_grad():
            return value.clone()
    if type(value) in (list, tuple):
        items = [plain(v) for v in value]
        if all(a is b for a, b in zip(items, value, strict=True)):
            return value
        return type(value)(items)
    if type(value) is dict:
        return {k: plain(v) for k, v in value.items()}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        changes = {}
        for field in dataclasses.fields(value):
            if not field.init:
                continue
            old = getattr(value, field.name)
            new = old if dataclasses.is_dataclass(old) else plain(old)
            if new is not old:
                changes[field.name] = new
        return dataclasses.replace(value, **changes) if changes else value
    return value
