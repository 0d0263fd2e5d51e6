"""Products of stacks of small matrices (6 × 6 to 12 × 12 blocks, one per residual instance).

On the CPU, outside autograd and ``torch.func`` transforms, NumPy's ``matmul`` (a loop of small
products in C) is several times faster than torch's batched one for such blocks; the values are
the same products. Elsewhere (CUDA, tensors that need gradients, ``jacrev``/``vmap``) it is
torch's ``@``.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["GRAIN_SIZE", "matmul", "sum_last"]

# at::internal::GRAIN_SIZE: the elements below which torch's elementwise kernels stay serial.
GRAIN_SIZE = 32768


def matmul(a: Tensor, b: Tensor, out: Tensor | None = None) -> Tensor:
    """a @ b for stacks of small matrices, (..., p, q) @ (..., q, r) → (..., p, r) (leading
    dims broadcast, as ``@``); written into ``out`` (contiguous, of that shape) when given."""
    if (
        type(a) is torch.Tensor  # not a subclass (FakeTensor, a tracing wrapper): no .numpy()
        and type(b) is torch.Tensor
        and a.device.type == "cpu"
        and b.device.type == "cpu"
        and a.dtype == b.dtype
        and a.dtype in (torch.float32, torch.float64)
        and not (torch.is_grad_enabled() and (a.requires_grad or b.requires_grad))
        and not torch._C._functorch.is_functorch_wrapped_tensor(a)
        and not torch._C._functorch.is_functorch_wrapped_tensor(b)
    ):
        # Measured on such stacks (NumPy 2): ``a`` as it comes (a transposed view takes
        # NumPy's own loop, faster than a copy and BLAS per matrix); ``b`` copied unless each
        # of its matrices is contiguous (a strided ``b`` is NumPy's slow case). NaN and Inf
        # propagate as in torch, without NumPy's floating-point warnings.
        b_np = b.detach().numpy()
        if not _matrices_contiguous(b):
            b_np = np.ascontiguousarray(b_np)
        with np.errstate(all="ignore"):
            if out is not None and out.is_contiguous() and out.dtype == a.dtype:
                np.matmul(a.detach().numpy(), b_np, out=out.detach().numpy())
                return out
            product = np.matmul(a.detach().numpy(), b_np)
        return torch.from_numpy(product) if out is None else out.copy_(torch.from_numpy(product))
    if out is not None:
        return out.copy_(a @ b)
    return a @ b


def _matrices_contiguous(x: Tensor) -> bool:
    """Each (p, q) matrix of ``x`` (..., p, q) is C-contiguous (gaps between matrices allowed)."""
    p, q = x.shape[-2:]
    return (q <= 1 or x.stride(-1) == 1) and (p <= 1 or x.stride(-2) == q)


def sum_last(x: Tensor) -> Tensor:
    """``x.sum(-1)`` for a short last dimension (2 to 4 entries: 3-vectors), (..., k) → (...).

    For large tensors (from torch's parallel grain size of 32,768 entries on) it is k − 1
    elementwise adds left to right: torch's reduction kernel over such a short row costs about
    5× more on the CPU, and its sum runs left to right too. Small tensors keep the one
    reduction (fewer operations)."""
    k = x.shape[-1]
    if not 2 <= k <= 4 or x.numel() < GRAIN_SIZE:
        return x.sum(-1)
    out = x[..., 0] + x[..., 1]
    for i in range(2, k):
        out = out + x[..., i]
    return out
