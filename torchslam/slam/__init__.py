"""ICP-SLAM on a moving range sensor (depth camera or LiDAR), from raw frames to a
loop-closed trajectory.

- :mod:`~torchslam.slam.config`: :class:`SLAMConfig` and its defaults per sensor;
- :mod:`~torchslam.slam.local_map`: the odometry's voxel map of recent keyframes;
- :mod:`~torchslam.slam.odometry`: :class:`Odometry`, frame-to-model point-to-plane ICP;
- :mod:`~torchslam.slam.loops`: loop-closure candidates and their verification;
- :mod:`~torchslam.slam.backend`: the robust keyframe pose graph and the joint refinement;
- :mod:`~torchslam.slam.pipeline`: :class:`SLAM` (streaming), :func:`run_sequence` and the
  reader it uses, :func:`frame_reader`.

Poses are frame → world everywhere (as TUM and KITTI files hold them).
"""

from torchslam.slam.backend import BackendResult, optimize_keyframes
from torchslam.slam.config import SLAMConfig
from torchslam.slam.loops import LoopClosure, find_candidates, verify_loop
from torchslam.slam.odometry import FrameInfo, FrameStatus, Keyframe, Odometry
from torchslam.slam.pipeline import SLAM, SLAMResult, frame_reader, run_sequence

__all__ = [
    "SLAM",
    "BackendResult",
    "FrameInfo",
    "FrameStatus",
    "Keyframe",
    "LoopClosure",
    "Odometry",
    "SLAMConfig",
    "SLAMResult",
    "find_candidates",
    "frame_reader",
    "optimize_keyframes",
    "run_sequence",
    "verify_loop",
]
