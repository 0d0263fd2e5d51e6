"""segment_sum: the sparse-matrix path equals index_add_, its cache follows the index tensor."""

from __future__ import annotations

import pytest
import torch

from torchslam.solver import segments
from torchslam.solver.segments import segment_sum, unique_rows


def _reference(index, rows, values):
    tail = values.shape[1:]
    return values.new_zeros(rows, *tail).index_add_(0, index.reshape(-1), values)


def _bound(index, rows, values):
    """Round-off bound of a row sum whatever its order: (count − 1)·ε·Σ|terms| per entry."""
    eps = torch.finfo(values.dtype).eps
    count = torch.bincount(index.reshape(-1), minlength=rows).to(values.dtype)
    shape = (rows,) + (1,) * (values.dim() - 1)
    return count.reshape(shape) * eps * _reference(index, rows, values.abs())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("tail", [(), (3,), (3, 3), (10,)])
def test_matches_index_add(dtype, tail):
    g = torch.Generator().manual_seed(0)
    N, rows = 3 * segments.SPARSE_MIN_EDGES, 257  # above the sparse threshold, uneven rows
    index = torch.randint(0, rows, (N,), generator=g)
    values = torch.randn(N, *tail, generator=g, dtype=torch.float64).to(dtype)
    out = segment_sum(index, rows, values)
    assert out.shape == (rows, *tail) and out.dtype == dtype
    assert (out - _reference(index, rows, values)).abs().le(_bound(index, rows, values)).all()


def test_small_inputs_and_empty_rows():
    index = torch.tensor([0, 2, 2])
    values = torch.tensor([[1.0], [2.0], [3.0]], dtype=torch.float64)
    assert segment_sum(index, 4, values).flatten().tolist() == [1.0, 0.0, 5.0, 0.0]
    empty = segment_sum(torch.zeros(0, dtype=torch.long), 3, torch.zeros(0, 2))
    assert empty.shape == (3, 2) and not empty.any()


def test_cache_follows_the_index_tensor_and_its_in_place_changes():
    N, rows = 2 * segments.SPARSE_MIN_EDGES, 8
    index = torch.arange(N) % rows
    values = torch.ones(N, 1, dtype=torch.float64)
    first = segment_sum(index, rows, values)
    assert first.flatten().tolist() == [N / rows] * rows
    index.zero_()  # in place: the cached matrix must not be reused
    second = segment_sum(index, rows, values)
    assert second.flatten().tolist() == [float(N)] + [0.0] * (rows - 1)
    assert segment_sum(index, rows + 2, values).shape == (rows + 2, 1)  # another row count


def test_gradients_flow_through_the_fallback():
    N, rows = 2 * segments.SPARSE_MIN_EDGES, 7
    index = torch.arange(N) % rows
    values = torch.randn(N, 3, dtype=torch.float64, requires_grad=True)
    out = segment_sum(index, rows, values)
    (out * torch.arange(rows, dtype=torch.float64)[:, None]).sum().backward()
    assert torch.equal(values.grad, (index.to(torch.float64)[:, None]).expand(N, 3))


@pytest.mark.parametrize("high", [2, 300, 1 << 40])
def test_unique_rows_matches_torch_unique(high):
    """Rows folded into one key while it fits, re-ranked when the next column would overflow
    (entries up to 2⁴⁰: a re-rank every column): the same rows, order and inverse as
    ``torch.unique(dim=0)``."""
    generator = torch.Generator().manual_seed(high % 1000)
    x = torch.randint(0, high, (400, 7), generator=generator)
    x[200:] = x[:200]  # duplicates
    rows, inverse = unique_rows(x)
    expected, expected_inverse = torch.unique(x, dim=0, return_inverse=True)
    assert torch.equal(rows, expected)
    assert torch.equal(inverse, expected_inverse)
    assert torch.equal(rows[inverse], x)
