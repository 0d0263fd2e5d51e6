"""Data: seeded synthetic ICP-SLAM scenes (``synthetic``), the benchmark cases of issue 4 and
loop scenes with odometry and loop-closure measurements (``loop``), and synthetic pose graphs
(``posegraph``: a torus or grid with loop closures, optionally wrong ones) and a range-sensor
sequence of a room scanned along a loop (``sequence``); named real data sets, fetched and
checked by sha256 (``files``: :func:`fetch`)."""

from torchslam.data.files import DATASETS, DatasetUnavailableError, fetch
from torchslam.data.loop import LoopScene, make_loop_scene
from torchslam.data.posegraph import SyntheticPoseGraph, make_pose_graph
from torchslam.data.sequence import (
    SyntheticDepthSequence,
    SyntheticSequence,
    make_depth_sequence,
    make_sequence,
)
from torchslam.data.synthetic import BENCHMARK_CASES, SyntheticScene, benchmark_case, make_scene

__all__ = [
    "BENCHMARK_CASES",
    "DATASETS",
    "DatasetUnavailableError",
    "LoopScene",
    "SyntheticDepthSequence",
    "SyntheticPoseGraph",
    "SyntheticScene",
    "SyntheticSequence",
    "benchmark_case",
    "fetch",
    "make_depth_sequence",
    "make_loop_scene",
    "make_pose_graph",
    "make_scene",
    "make_sequence",
]
