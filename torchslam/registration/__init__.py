"""Registration of point clouds: neighbourhoods, ICP, point tracks and the multiview pipeline.

Modules: :mod:`~torchslam.registration.neighbors` (voxel grids, nearest neighbours, PCA
normals), :mod:`~torchslam.registration.icp` (pairwise ICP, pose chaining) and
:mod:`~torchslam.registration.tracks` (point tracks across scans).
"""

from torchslam.registration import icp, neighbors, tracks

__all__ = ["icp", "neighbors", "tracks"]
