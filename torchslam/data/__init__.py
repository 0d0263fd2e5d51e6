"""Data: seeded synthetic ICP-SLAM scenes (``synthetic``) and the benchmark cases of issue 4."""

from torchslam.data.synthetic import BENCHMARK_CASES, SyntheticScene, benchmark_case, make_scene

__all__ = ["BENCHMARK_CASES", "SyntheticScene", "benchmark_case", "make_scene"]
