"""File formats: BAL bundle-adjustment problems (``bal``), PLY point clouds (``ply``),
range-sensor frames (``frames``: depth images, PCD/KITTI/NPY/XYZ clouds, sequence folders),
Stanford scan alignments (``stanford``) and pose files (``trajectories``)."""

from torchslam.io import bal, frames, ply, stanford, trajectories
from torchslam.io.bal import BALProblem, read_bal, write_bal
from torchslam.io.frames import list_frames, read_depth, read_intrinsics, read_points
from torchslam.io.ply import PlyData, PlyElement, PlyProperty, read_ply, read_ply_points, write_ply
from torchslam.io.stanford import read_conf
from torchslam.io.trajectories import read_poses, write_poses

__all__ = [
    "BALProblem",
    "PlyData",
    "PlyElement",
    "PlyProperty",
    "bal",
    "frames",
    "list_frames",
    "ply",
    "read_bal",
    "read_conf",
    "read_depth",
    "read_intrinsics",
    "read_ply",
    "read_ply_points",
    "read_points",
    "read_poses",
    "stanford",
    "trajectories",
    "write_bal",
    "write_ply",
    "write_poses",
]
