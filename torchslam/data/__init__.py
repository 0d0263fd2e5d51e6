"""Data: seeded synthetic ICP-SLAM scenes (``synthetic``), the benchmark cases of issue 4 and
loop scenes with odometry and loop-closure measurements (``loop``)."""

from torchslam.data.loop import LoopScene, make_loop_scene
from torchslam.data.synthetic import BENCHMARK_CASES, SyntheticScene, benchmark_case, make_scene

__all__ = [
    "BENCHMARK_CASES",
    "LoopScene",
    "SyntheticScene",
    "benchmark_case",
    "make_loop_scene",
    "make_scene",
]
