"""Shared fixtures: a seeded generator, dtype and device parametrizations; the data sets'
offline mirror (``TORCHSLAM_DATA_MIRROR``, when unset: the project's ``../shared/data``)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

_SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
if "TORCHSLAM_DATA_MIRROR" not in os.environ and _SHARED.is_dir():
    os.environ["TORCHSLAM_DATA_MIRROR"] = str(_SHARED)


@pytest.fixture
def generator() -> torch.Generator:
    return torch.Generator().manual_seed(20261122)


@pytest.fixture(params=[torch.float64, torch.float32], ids=["f64", "f32"])
def dtype(request) -> torch.dtype:
    return request.param


_DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=_DEVICES)
def device(request) -> torch.device:
    return torch.device(request.param)
