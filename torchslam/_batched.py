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

__all__ = ["matmul"]


def matmul(a: Tensor, b: Tensor) -> Tensor:
    """a @ b for stacks of small matrices, (..., p, q) @ (..., q, r) → (..., p, r) (leading
    dims broadcast, as ``@``)."""
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
        # A transposed view makes NumPy take its slow strided loop: copy it first (cheaper).
        # NaN and Inf propagate as in torch, without NumPy's floating-point warnings.
        with np.errstate(all="ignore"):
            product = np.matmul(
                np.ascontiguousarray(a.detach().numpy()), np.ascontiguousarray(b.detach().numpy())
            )
        return torch.from_numpy(product)
    return a @ b
