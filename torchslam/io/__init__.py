"""File formats: PLY point clouds (``ply``) and Stanford scan alignments (``stanford``)."""

from torchslam.io import ply, stanford
from torchslam.io.ply import PlyData, PlyElement, PlyProperty, read_ply, read_ply_points, write_ply
from torchslam.io.stanford import read_conf

__all__ = [
    "PlyData",
    "PlyElement",
    "PlyProperty",
    "ply",
    "read_conf",
    "read_ply",
    "read_ply_points",
    "stanford",
    "write_ply",
]
