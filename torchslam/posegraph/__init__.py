"""Pose graphs: relative-pose (between) and prior terms, objectives, initializers.

Conventions: ξ = (ω, v), rotation first; right perturbation T·Exp(δ); a vertex pose T_i maps
body-i points into the world and an edge measures Z_ij ≈ T_i⁻¹ T_j (g2o's meaning), with a 6 × 6
information matrix in (ω, v) order. Files are read and written by :mod:`torchslam.io.g2o`.
"""

from torchslam.posegraph import between, certification, initialization, objectives
from torchslam.posegraph.certification import certify
from torchslam.posegraph.graph import GraphSource, PoseGraph

__all__ = [
    "GraphSource",
    "PoseGraph",
    "between",
    "certification",
    "certify",
    "initialization",
    "objectives",
]
