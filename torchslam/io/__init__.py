"""File formats: PLY point clouds (``ply``), Stanford scan alignments (``stanford``) and pose
files (``trajectories``)."""

from torchslam.io import ply, stanford, trajectories
from torchslam.io.ply import PlyData, PlyElement, PlyProperty, read_ply, read_ply_points, write_ply
from torchslam.io.stanford import read_conf
from torchslam.io.trajectories import read_poses, write_poses

__all__ = [
    "PlyData",
    "PlyElement",
    "PlyProperty",
    "ply",
    "read_conf",
    "read_ply",
    "read_ply_points",
    "read_poses",
    "stanford",
    "trajectories",
    "write_ply",
    "write_poses",
]
