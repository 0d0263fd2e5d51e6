"""Paired, in-process speed comparison of `solve_pose_graph` against an earlier commit.

The earlier commit's package is exported with `git archive` into a temporary folder and its
imports renamed to `torchslam_base`, so both versions run in one process: solves alternate
(this checkout, then the base), and the median of the per-pair time ratios is reported, which
cancels most of a shared machine's drift. Costs and iteration counts are printed for both.

    OMP_NUM_THREADS=1 PYTHONPATH=. .venv/bin/python experiments/posegraph_ab.py \\
        --base 585607f [--repeats 9] [--clock wall|cpu]

(585607f is the last commit with the dedicated pose-graph solver, before issue 13.)
"""

from __future__ import annotations

import argparse
import importlib
import re
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import torch

from torchslam.data import fetch

ROOT = Path(__file__).resolve().parents[1]


def export_base(rev: str, folder: Path) -> None:
    """``torchslam`` of commit ``rev`` as the package ``torchslam_base`` in ``folder``."""
    archive = folder / "base.tar"
    subprocess.run(
        ["git", "-C", str(ROOT), "archive", "-o", str(archive), rev, "torchslam"], check=True
    )
    with tarfile.open(archive) as tar:
        tar.extractall(folder, filter="data")
    (folder / "torchslam").rename(folder / "torchslam_base")
    for path in (folder / "torchslam_base").rglob("*.py"):
        text = path.read_text()
        path.write_text(re.sub(r"\btorchslam\b", "torchslam_base", text))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--base", required=True, help="the earlier commit (any git revision)")
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--clock", choices=("wall", "cpu"), default="wall")
    parser.add_argument("--data", type=Path, default=None)
    args = parser.parse_args()
    args.data = args.data or fetch("posegraph")
    torch.set_num_threads(1)
    clock = time.perf_counter if args.clock == "wall" else time.process_time
    with tempfile.TemporaryDirectory() as tmp:
        export_base(args.base, Path(tmp))
        sys.path.insert(0, tmp)
        versions = {}
        for name in ("torchslam", "torchslam_base"):
            g2o = importlib.import_module(f"{name}.io.g2o")
            solve = importlib.import_module(f"{name}.posegraph.solve").solve_pose_graph
            versions[name] = (g2o, solve)
        print(f"this checkout vs {args.base}: {args.repeats} alternating solves, 1 thread")
        for file in ("parking-garage", "sphere2500"):
            path = args.data / f"{file}.g2o"
            if not path.exists():
                print(f"{file}: {path} is absent, skipped")
                continue
            graphs = {n: g2o.read_g2o(path) for n, (g2o, _) in versions.items()}
            times = {n: [] for n in versions}
            results = {}
            for _ in range(args.repeats + 1):  # the first round warms up
                for name, (_, solve) in versions.items():
                    start = clock()
                    results[name] = solve(graphs[name])
                    times[name].append(clock() - start)
            new, old = times["torchslam"][1:], times["torchslam_base"][1:]
            ratio = statistics.median(a / b for a, b in zip(new, old, strict=True))
            now, base = results["torchslam"], results["torchslam_base"]
            print(
                f"{file:15s} now {statistics.median(new):.3f} s, base "
                f"{statistics.median(old):.3f} s, paired ratio (median) {ratio:.3f}; "
                f"½χ² {now.final_cost:.8g} / {base.final_cost:.8g}, iterations "
                f"{now.iterations} / {base.iterations}"
            )


if __name__ == "__main__":
    main()
