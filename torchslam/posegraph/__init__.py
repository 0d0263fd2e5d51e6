"""Pose graphs: relative-pose (between) and prior terms, objectives, initializers.

Conventions: ξ = (ω, v), rotation first; right perturbation T·Exp(δ); a vertex pose T_i maps
body-i points into the world and an edge measures Z_ij ≈ T_i⁻¹ T_j (g2o's meaning), with a 6 × 6
information matrix in (ω, v) order. Files are read and written by :mod:`torchslam.io.g2o`.
"""

import importlib as _importlib

from torchslam.posegraph import between, objectives
from torchslam.posegraph.covariance import VertexCovariances, marginal_covariances
from torchslam.posegraph.graph import GraphSource, PoseGraph

__all__ = [
    "GraphSource",
    "PoseGraph",
    "VertexCovariances",
    "between",
    "certification",
    "certify",
    "initialization",
    "marginal_covariances",
    "objectives",
]


def __getattr__(name: str) -> object:
    # The SciPy-backed modules load on first use (``import torchslam.data`` stays light).
    if name in ("certification", "initialization"):
        return _importlib.import_module(f"torchslam.posegraph.{name}")
    if name == "certify":
        return _importlib.import_module("torchslam.posegraph.certification").certify
    raise AttributeError(f"module 'torchslam.posegraph' has no attribute {name!r}")
