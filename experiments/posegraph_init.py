"""Pose-graph initializers on the shared benchmarks: file values vs odometry chain vs chordal.

Prints, for sphere2500 and parking-garage, the standard cost ½ Σ rᵀΩr (r = Log(Z⁻¹ T_i⁻¹ T_j),
Ω in (ω, v) order) and the SE-Sync objective (Rosen et al. IJRR 2019, eq. 12) of each
initialization, and the time each initializer takes. References: GTSAM's LM optimum of the
standard cost is 675.70 (sphere2500) and 0.63419 (parking-garage); the certified SE-Sync optima
are 1687 and 1.263.

Run from the repository root:  .venv/bin/python experiments/posegraph_init.py
(with torchslam installed, ``pip install -e .``, or with ``PYTHONPATH=.`` in front).
"""

from __future__ import annotations

import sys
import time

from torchslam.data import fetch
from torchslam.io import g2o
from torchslam.posegraph import initialization, objectives

REFERENCE = {  # (GTSAM LM standard cost, SE-Sync certified optimum f*)
    "sphere2500": (675.70, 1687.0),
    "parking-garage": (0.63419, 1.263),
}


def main() -> int:
    for name, (gtsam_cost, sesync_optimum) in REFERENCE.items():
        path = fetch("posegraph") / f"{name}.g2o"
        if not path.exists():
            print(f"{name}: {path} is absent, skipped")
            continue
        graph = g2o.read_g2o(path)
        print(
            f"\n{name}: {graph.num_vertices} vertices, {graph.num_edges} edges "
            f"(optimum: standard cost {gtsam_cost} by GTSAM LM, SE-Sync f* {sesync_optimum})"
        )
        print(f"  {'initialization':<16} {'standard cost':>16} {'SE-Sync obj.':>16} {'time':>9}")
        candidates = {"file vertices": (lambda g=graph: g.poses)}
        candidates["odometry chain"] = lambda g=graph: initialization.odometry_initialization(g)
        candidates["chordal"] = lambda g=graph: initialization.chordal_initialization(g)
        for label, make in candidates.items():
            start = time.perf_counter()
            poses = make()
            seconds = time.perf_counter() - start
            cost = float(objectives.standard_cost(graph, poses))
            sesync = float(objectives.sesync_objective(graph, poses))
            print(f"  {label:<16} {cost:>16.6g} {sesync:>16.6g} {seconds:>8.3f}s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
