"""Pose graphs: relative-pose (between) and prior terms, objectives, initializers.

Conventions: ξ = (ω, v), rotation first; right perturbation T·Exp(δ); a vertex pose T_i maps
body-i points into the world and an edge measures Z_ij ≈ T_i⁻¹ T_j (g2o's meaning), with a 6 × 6
information matrix in (ω, v) order. Files are read and written by :mod:`torchslam.io.g2o`.
"""

from torchslam.posegraph import between, initialization, objectives
from torchslam.posegraph.covariance import VertexCovariances, marginal_covariances
from torchslam.posegraph.graph import PoseGraph

__all__ = [
    "PoseGraph",
    "VertexCovariances",
    "between",
    "initialization",
    "marginal_covariances",
    "objectives",
]
