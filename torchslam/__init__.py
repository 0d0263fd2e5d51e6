"""torchslam: ICP-SLAM as batched, differentiable nonlinear least squares on SE(3).

Conventions (kept everywhere): tangent vectors ξ = (ω, v), rotation first; right perturbation
T ← T·Exp(δ); T_i0 maps world (frame 0) points into frame i; Hamilton quaternions (w, x, y, z);
float64 by default.
"""

import importlib as _importlib

from torchslam import losses
from torchslam._checks import validation
from torchslam.covariance import MarginalCovariances, marginal_covariances
from torchslam.lie import convert, se3, so3
from torchslam.losses import CauchyLoss, HuberLoss, TrivialLoss, TukeyLoss
from torchslam.objective import PointMapData
from torchslam.objective.reprojection import ReprojectionTerm
from torchslam.objective.terms import PointObservationTerm, PosePriorTerm, RelativePoseTerm, Term
from torchslam.problem import PointMapProblem
from torchslam.solver import (
    ImplicitConfig,
    IterationInfo,
    SolverConfig,
    SolveResult,
    Status,
    solve,
    solve_differentiable,
    solve_tensors,
)

__version__ = "0.1.0"

# Subpackages and modules imported on first use (PEP 562), so that ``import torchslam`` costs
# little beyond ``import torch``: ``torchslam.posegraph``, ``torchslam.registration`` and the
# like work as attributes all the same. ``register``, ``icp``, ``tracks``, ``demo`` and
# ``terms`` are deprecated shims (their names warn when read).
_LAZY = (
    "alignment",
    "benchmark",
    "bundle_adjustment",
    "cameras",
    "cli",
    "data",
    "demo",
    "icp",
    "initialization",
    "io",
    "jacobians",
    "manifold",
    "metrics",
    "posegraph",
    "register",
    "registration",
    "slam",
    "terms",
    "tracks",
)


def __getattr__(name: str) -> object:
    if name in _LAZY:
        return _importlib.import_module(f"torchslam.{name}")
    raise AttributeError(f"module 'torchslam' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


__all__ = [
    "CauchyLoss",
    "HuberLoss",
    "ImplicitConfig",
    "IterationInfo",
    "MarginalCovariances",
    "PointMapData",
    "PointMapProblem",
    "PointObservationTerm",
    "PosePriorTerm",
    "RelativePoseTerm",
    "ReprojectionTerm",
    "SolveResult",
    "SolverConfig",
    "Status",
    "Term",
    "TrivialLoss",
    "TukeyLoss",
    "__version__",
    "alignment",
    "convert",
    "covariance",
    "data",
    "icp",
    "initialization",
    "io",
    "jacobians",
    "losses",
    "manifold",
    "marginal_covariances",
    "metrics",
    "posegraph",
    "registration",
    "se3",
    "slam",
    "so3",
    "solve",
    "solve_differentiable",
    "solve_tensors",
    "terms",
    "tracks",
    "validation",
]
