"""The argument helpers of torchslam._checks that stand in for torch functions."""

from __future__ import annotations

import itertools

import pytest
import torch

from torchslam import _checks


def test_broadcast_shapes_matches_torch():
    # every pair and triple of shapes over sizes {1, 2, 3} and up to 3 dims: the same shape
    # as torch.broadcast_shapes, or the same refusal (a RuntimeError)
    shapes = [()] + [s for n in (1, 2, 3) for s in itertools.product((1, 2, 3), repeat=n)]
    for count in (1, 2, 3):
        for combo in itertools.islice(itertools.product(shapes, repeat=count), 4000):
            try:
                expected = torch.broadcast_shapes(*combo)
            except RuntimeError:
                with pytest.raises(RuntimeError, match="do not broadcast"):
                    _checks.broadcast_shapes(*combo)
                continue
            got = _checks.broadcast_shapes(*combo)
            assert got == expected and isinstance(got, torch.Size)
    assert _checks.broadcast_shapes() == torch.Size([])
    assert _checks.broadcast_shapes((0, 1), (3,)) == torch.broadcast_shapes((0, 1), (3,))
