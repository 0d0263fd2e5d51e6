"""Registration of point clouds: ICP front end, point tracks and the multiview pipeline.

Modules: :mod:`~torchslam.registration.icp` (voxel grids, normals, nearest neighbours,
pairwise ICP, pose chaining) and :mod:`~torchslam.registration.tracks` (point tracks across
scans).
"""

from torchslam.registration import icp, tracks

__all__ = ["icp", "tracks"]
