"""The public entry points at 1 and 2 threads, with and without one busy core (issue 28 §3).

For each entry point: alternate 1- and 2-thread runs (``torch.set_num_threads``), ``--pairs``
pairs, first on the machine as it is, then with a background process spinning on one core;
prints the median seconds and the median of the paired 2-thread/1-thread ratios. A ratio above
1 under load is the cliff the issue describes.

Entry points: ``solve`` (the M case of the benchmark), ``solve_pose_graph`` (parking-garage),
``marginal covariances`` of that graph, pairwise ``icp`` (bunny bun045 → bun000, point-to-plane)
and ``run_sequence`` (the first 60 keyframes of lidar-quick-shack).

Usage::

    .venv/bin/python experiments/threads_under_load.py [--pairs 3] [--entries solve,icp,...]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import statistics
import time

import torch


def _spin() -> None:
    while True:
        pass


def _entries() -> dict:
    import torchslam as ts
    from torchslam import benchmark
    from torchslam.data import fetch
    from torchslam.io import frames as fio
    from torchslam.io import g2o
    from torchslam.io.ply import read_ply_points
    from torchslam.posegraph.covariance import marginal_covariances
    from torchslam.posegraph.solve import solve_pose_graph
    from torchslam.registration import icp
    from torchslam.slam import run_sequence

    scene, init, loss = benchmark.build("M")
    graph = g2o.read_g2o(fetch("posegraph") / "parking-garage.g2o")
    solved = solve_pose_graph(graph)
    bunny = fetch("bunny")
    source = read_ply_points(bunny / "bun045.ply")
    target = read_ply_points(bunny / "bun000.ply")
    normals = icp.estimate_normals(target, 10)
    paths, _ = fio.list_frames(fetch("lidar-quick-shack"))
    clouds = [fio.read_points(p) for p in paths[:60]]
    icp_config = icp.ICPConfig(method="point_to_plane", max_distance=0.005, gate_scale=None)

    entries = {
        "solve_pose_graph": lambda: solve_pose_graph(graph),
        "covariances": lambda: marginal_covariances(graph, solved.poses),
        "icp": lambda: icp.icp(source, target, None, icp_config, normals),
        "run_sequence": lambda: run_sequence(clouds),
    }
    entries["solve"] = lambda: ts.solve(
        ts.PointMapProblem.from_scene(scene, init.poses, init.points, loss=loss)
    )
    return entries


def _time(f) -> float:
    tic = time.perf_counter()
    f()
    return time.perf_counter() - tic


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, default=3)
    parser.add_argument("--entries", default="")
    args = parser.parse_args(argv)
    entries = _entries()
    if args.entries:
        entries = {k: v for k, v in entries.items() if k in args.entries.split(",")}
    print(f"{'entry point':18} {'load':6} {'1 thread s':>11} {'2 threads s':>12} {'2/1 ratio':>10}")
    for load in ("quiet", "1 busy"):
        spinner = None
        if load != "quiet":
            spinner = mp.Process(target=_spin, daemon=True)
            spinner.start()
        try:
            for name, f in entries.items():
                torch.set_num_threads(1)
                f()  # warm-up
                one, two, ratios = [], [], []
                for _ in range(args.pairs):
                    torch.set_num_threads(1)
                    a = _time(f)
                    torch.set_num_threads(2)
                    b = _time(f)
                    one.append(a)
                    two.append(b)
                    ratios.append(b / a)
                print(
                    f"{name:18} {load:6} {statistics.median(one):11.3f} "
                    f"{statistics.median(two):12.3f} {statistics.median(ratios):10.2f}",
                    flush=True,
                )
        finally:
            if spinner is not None:
                spinner.terminate()
                spinner.join()
    torch.set_num_threads(1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
