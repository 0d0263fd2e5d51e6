"""In-process time of `solve_pose_graph` on the shared pose graphs: the minimum of N solves from
the file's vertices, with its linearization and linear-solve parts.

Run it in two checkouts alternately to compare them on a noisy machine (a before/after pair):

    OMP_NUM_THREADS=1 PYTHONPATH=. .venv/bin/python experiments/posegraph_time.py [--repeats 7]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

import torchslam
from torchslam.data import fetch
from torchslam.io import g2o
from torchslam.posegraph.solve import solve_pose_graph


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--data", type=Path, default=None)
    args = parser.parse_args()
    args.data = args.data or fetch("posegraph")
    torch.set_num_threads(1)
    print(f"torchslam from {Path(torchslam.__file__).parent}")
    for name in ("parking-garage", "sphere2500"):
        path = args.data / f"{name}.g2o"
        if not path.exists():
            print(f"{name}: {path} is absent, skipped")
            continue
        graph = g2o.read_g2o(path)
        runs = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            result = solve_pose_graph(graph)
            runs.append(
                (time.perf_counter() - start, result.linearize_seconds, result.linear_solve_seconds)
            )
        total, lin, solve = (min(r[k] for r in runs) for k in range(3))
        print(
            f"{name:15s} total {total:.3f} s  linearization {lin:.3f} s  linear solves "
            f"{solve:.3f} s  ({result.iterations} iterations, ½χ² {result.final_cost:.8g})"
        )


if __name__ == "__main__":
    main()
