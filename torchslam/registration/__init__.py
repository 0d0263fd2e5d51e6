"""Registration of range scans: neighbourhoods, ICP, point tracks and the multiview pipeline.

Modules, from the ground up:

- :mod:`~torchslam.registration.neighbors`: voxel grids, nearest neighbours, PCA normals;
- :mod:`~torchslam.registration.icp`: pairwise ICP (point-to-point, point-to-plane),
  multistart, coarse to fine, pose chaining;
- :mod:`~torchslam.registration.quality`: whether an alignment can be trusted (overlap,
  residual RMS, conditioning of its normal equations) and its information matrix;
- :mod:`~torchslam.registration.tracks`: point tracks across scans (the data association);
- :mod:`~torchslam.registration.config`: :class:`RegisterConfig`, :func:`default_stages`;
- :mod:`~torchslam.registration.pipeline`: :func:`register` (scans in any order and unit:
  pairwise alignment of all pairs and their spanning tree, or a chain; overlapping pairs;
  joint ICP-SLAM refinement) and its steps;
- :mod:`~torchslam.registration.report`: consistency residuals and error tables;
- :mod:`~torchslam.registration.conventions`: checks that detect inverted pose sets.

Pose files are in :mod:`torchslam.io.trajectories`; the command ``torchslam register`` and
its figure in :mod:`torchslam.cli.register` and :mod:`torchslam.cli.plots`.
"""

from torchslam.registration import (
    config,
    conventions,
    icp,
    neighbors,
    pipeline,
    quality,
    report,
    tracks,
)
from torchslam.registration.config import (
    RegisterConfig,
    ScanScale,
    auto_voxel_size,
    default_stages,
    scan_scale,
)
from torchslam.registration.conventions import (
    InvertedPosesWarning,
    PoseDirectionCheck,
    check_problem_poses,
    check_scan_poses,
)
from torchslam.registration.pipeline import (
    ChainResult,
    RefineResult,
    Registration,
    RoundInfo,
    boundary_mask,
    information_matrices,
    joint_cost,
    load_scans,
    overlapping_pairs,
    refine,
    register,
    register_chain,
    register_tree,
)
from torchslam.registration.quality import (
    AlignmentQuality,
    QualityThresholds,
    alignment_quality,
)
from torchslam.registration.report import alignment_residual, error_table, plane_distances

__all__ = [
    "AlignmentQuality",
    "ChainResult",
    "InvertedPosesWarning",
    "PoseDirectionCheck",
    "QualityThresholds",
    "RefineResult",
    "RegisterConfig",
    "Registration",
    "RoundInfo",
    "ScanScale",
    "alignment_quality",
    "alignment_residual",
    "auto_voxel_size",
    "boundary_mask",
    "check_problem_poses",
    "check_scan_poses",
    "config",
    "conventions",
    "default_stages",
    "error_table",
    "icp",
    "information_matrices",
    "joint_cost",
    "load_scans",
    "neighbors",
    "overlapping_pairs",
    "pipeline",
    "plane_distances",
    "quality",
    "refine",
    "register",
    "register_chain",
    "register_tree",
    "report",
    "scan_scale",
    "tracks",
]
