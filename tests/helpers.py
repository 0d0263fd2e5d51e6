"""Test helpers: the one list of hard inputs, tolerances by dtype, central differences."""

from __future__ import annotations

import importlib.util
import math
import sys
from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor

# The hard rotation angles every Lie/Jacobian test goes through (STYLE.md).
HARD_ANGLES = (0.0, 1e-12, 1e-8, 1e-4, 0.3, 0.5, math.pi / 2, math.pi - 1e-6, math.pi)
# Tiny and huge translation magnitudes.
HARD_TRANSLATIONS = (0.0, 1e-9, 1.0, 1e4)

# Absolute tolerance of round trips / identities at unit scale, by dtype.
TOL = {torch.float64: 1e-12, torch.float32: 2e-5}


def random_unit_vectors(count: int, generator: torch.Generator, dtype=torch.float64) -> Tensor:
    v = torch.randn(count, 3, generator=generator, dtype=torch.float64)
    return (v / v.norm(dim=-1, keepdim=True)).to(dtype)


def rotation_vectors_with_angles(
    angles, generator: torch.Generator, per_angle: int = 4, dtype=torch.float64
) -> Tensor:
    """(len(angles) * per_angle, 3) rotation vectors with exactly the given angles."""
    axes = random_unit_vectors(len(angles) * per_angle, generator)
    theta = torch.tensor(angles, dtype=torch.float64).repeat_interleave(per_angle)
    return (axes * theta[:, None]).to(dtype)


def twists_with_hard_inputs(generator: torch.Generator, dtype=torch.float64) -> Tensor:
    """Twists ξ = (ω, v) over every hard angle × every hard translation magnitude."""
    omega = rotation_vectors_with_angles(HARD_ANGLES, generator, per_angle=2)
    rows = []
    for scale in HARD_TRANSLATIONS:
        v = torch.randn(omega.shape[0], 3, generator=generator, dtype=torch.float64) * scale
        rows.append(torch.cat((omega, v), dim=-1))
    return torch.cat(rows).to(dtype)


def central_difference(f: Callable[[Tensor], Tensor], x: Tensor, eps: float = 1e-6) -> Tensor:
    """Jacobian of ``f`` at a single point ``x`` (shape (k,)) by central differences, (m, k)."""
    columns = []
    for i in range(x.numel()):
        step = torch.zeros_like(x)
        step[i] = eps
        columns.append((f(x + step) - f(x - step)).reshape(-1) / (2 * eps))
    return torch.stack(columns, dim=-1)


def load_example(name: str):
    """The module of ``examples/<name>.py``, loaded once and registered in ``sys.modules`` as
    ``examples_<name>`` (so that ``inspect.getsource`` finds its classes)."""
    module_name = f"examples_{name}"
    if module_name not in sys.modules:
        path = Path(__file__).resolve().parent.parent / "examples" / f"{name}.py"
        spec = importlib.util.spec_from_file_location(module_name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[module_name] = module
        spec.loader.exec_module(module)
    return sys.modules[module_name]


def dataset_folder(name: str) -> Path:
    """The folder of a named data set (torchslam.data.files), mirrored or cached, checked by
    sha256; never downloads. A path that does not exist when the data set is unavailable (the
    data tests check ``is_dir()`` and skip)."""
    from torchslam.data import files

    try:
        return files.fetch(name, download=False)
    except files.DatasetUnavailableError:
        return Path(f"<data set {name!r} unavailable: torchslam data fetch {name}>")
