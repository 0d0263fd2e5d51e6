"""The KD-tree of the lookups (torchslam.registration.kdtree.KDTree, pykdtree) against scipy's
cKDTree as torchslam configured it before (sliding-midpoint splits, no node shrinking), on the
library's real sequences: build a tree of a local map (the first frames of a sequence, stacked)
and query the next frame's points for k = 1 (ICP), 2 (certified lookups) and 10 (normals),
on 1 and 2 threads. Also counts how often the two disagree (ties in distance: equal answers).

    python experiments/kdtree_speed.py [--sequences rgbd-7scenes,lidar-hku2-loop] [--repeat 20]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from scipy.spatial import cKDTree

from torchslam.data import fetch
from torchslam.registration.kdtree import KDTree
from torchslam.slam import frame_reader


def _best(repeat: int, fn, *args, **kwargs) -> float:
    """The fastest of ``repeat`` calls, ms."""
    best = float("inf")
    for _ in range(repeat):
        tic = time.perf_counter()
        fn(*args, **kwargs)
        best = min(best, time.perf_counter() - tic)
    return 1000 * best


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequences", default="rgbd-7scenes,lidar-hku2-loop")
    parser.add_argument("--frames", type=int, default=5, help="frames stacked into the map")
    parser.add_argument("--repeat", type=int, default=20)
    args = parser.parse_args(argv)
    print(f"{'sequence':18} {'map':>7} {'query':>6} thr  {'build ms':>17}  ", end="")
    print("  ".join(f"k={k} ms (scipy / ours)" for k in (1, 2, 10)), " ties")
    for name in args.sequences.split(","):
        read, _, _, _ = frame_reader(fetch(name))
        frames = [np.asarray(read(i), dtype=np.float64) for i in range(args.frames + 1)]
        data = np.concatenate(frames[:-1])
        query = frames[-1]
        for threads in (1, 2):
            torch.set_num_threads(threads)
            build_s = _best(args.repeat, cKDTree, data, balanced_tree=False, compact_nodes=False)
            build_o = _best(args.repeat, KDTree, data)
            scipy_tree = cKDTree(data, balanced_tree=False, compact_nodes=False)
            ours = KDTree(data)
            cells, ties = [], 0
            for k in (1, 2, 10):
                s = _best(args.repeat, scipy_tree.query, query, k=k, workers=threads)
                o = _best(args.repeat, ours.query, query, k=k, workers=threads)
                cells.append(f"{s:7.2f} / {o:6.2f}    ")
                a, b = scipy_tree.query(query, k=k), ours.query(query, k=k)
                assert np.array_equal(a[0], b[0]), "the distances differ"
                ties += int(np.count_nonzero(a[1] != b[1]))
            print(
                f"{name:18} {len(data):7d} {len(query):6d} {threads:3d}  "
                f"{build_s:7.2f} / {build_o:6.2f}  " + "".join(cells) + f" {ties}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
