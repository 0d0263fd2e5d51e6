"""The KD-tree of the nearest-neighbour lookups: pykdtree, with scipy cKDTree's conventions.

Every lookup of the library runs here (ICP, odometry's local map, normals, loop checks, point
tracks): pykdtree builds a tree of a LiDAR or depth map and answers its k = 1, 2 and 10
queries 1.4–1.8× faster than scipy's cKDTree, on one thread or two
(``experiments/kdtree_speed.py``), with the same distances bit for bit (both compute ‖x − y‖
as the square root of the sum of the three squared differences, in float64) and the same
neighbours but where two distances tie, which it may order differently (depth frames, whose
points lie on a pixel lattice, have many such ties). :class:`KDTree` answers in cKDTree's
form:

- ``distance`` float64, ``index`` int64 (not pykdtree's uint32), shape (n,) for k = 1, else
  (n, k), ascending;
- a neighbour missing (none within ``distance_upper_bound``, a strict bound, or fewer than k
  points in the tree) is (inf, N), N the tree's size (pykdtree pads k > N with garbage);
- an empty tree answers every query with misses (pykdtree refuses to build one).

Threads: pykdtree parallelizes a query with OpenMP in its own runtime, which ``torch``'s
thread setting does not reach. Each query runs on exactly ``workers`` threads (the caller's
:func:`~torchslam.registration.neighbors.query_workers`: torch's count, less the cores other
work keeps busy), set through ``threadpoolctl``: on pykdtree's own runtime (the wheels bundle
one) only when the count changes, on a runtime shared with other libraries around each query,
restored after it. So the library's one thread policy (``torchslam._threads``) holds here too.
"""

from __future__ import annotations

import contextlib
import functools
import threading

import numpy as np

__all__ = ["KDTree"]


class KDTree:
    """A KD-tree of a fixed cloud for k-nearest queries (see the module docstring).

    Args:
        points: (N, 3) finite float64 array (N ≥ 0); kept by reference, not copied when
            C-contiguous: do not modify it while the tree is in use.
    """

    def __init__(self, points: np.ndarray) -> None:
        data = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        self.data = data
        self.n = data.shape[0]
        self._tree = None
        if self.n:
            from pykdtree.kdtree import KDTree as _PyKDTree

            self._tree = _PyKDTree(data, leafsize=16)

    def query(
        self,
        x: np.ndarray,
        k: int = 1,
        distance_upper_bound: float = np.inf,
        workers: int = 1,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The k nearest points of the tree to each row of ``x`` (m, 3) within the strict
        bound ``distance_upper_bound``, on ``workers`` threads: (distance, index) as
        ``scipy.spatial.cKDTree.query`` returns them (see the module docstring)."""
        x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 3)
        m = x.shape[0]
        found = min(k, self.n)
        if found == k and m:
            bound = None if distance_upper_bound == np.inf else float(distance_upper_bound)
            with _threads(workers):
                d, i = self._tree.query(x, k=k, distance_upper_bound=bound)
            # pykdtree's miss index is its size too; in int64 rather than its uint32
            distance, index = d.reshape(m, k), i.astype(np.int64).reshape(m, k)
        else:  # an empty query, or fewer points than k: the rest padded with misses
            distance = np.full((m, k), np.inf)
            index = np.full((m, k), self.n, dtype=np.int64)
            if found and m:
                d, i = self.query(x, found, distance_upper_bound, workers)
                distance[:, :found] = d.reshape(m, found)
                index[:, :found] = i.reshape(m, found)
        if k == 1:
            return distance[:, 0], index[:, 0]
        return distance, index


@functools.cache
def _runtime() -> tuple[object, bool] | None:
    """threadpoolctl's handle of the OpenMP runtime pykdtree's queries run in and whether it
    is pykdtree's own: its own copy when the wheel bundles one (found by path), else every
    OpenMP runtime loaded (a shared one, whose limit is restored after each query so that
    torch's count is unchanged); None when none is loaded."""
    import pykdtree.kdtree  # noqa: F401 -- loads its OpenMP runtime
    from threadpoolctl import ThreadpoolController

    controller = ThreadpoolController()
    runtimes = [lib for lib in controller.info() if lib.get("internal_api") == "openmp"]
    own = [lib for lib in runtimes if "pykdtree" in str(lib.get("filepath", ""))]
    if own:
        return controller.select(filepath=[lib["filepath"] for lib in own]), True
    if runtimes:
        return controller.select(internal_api="openmp"), False
    return None


# The thread count last set on pykdtree's own runtime, per Python thread (OpenMP keeps the
# setting per calling thread; nothing else uses that runtime, so it stays set).
_OWN = threading.local()


def _threads(workers: int):
    """A context in which pykdtree's queries run on ``workers`` threads."""
    found = _runtime()
    if found is None:
        return contextlib.nullcontext()
    runtime, own = found
    workers = max(1, int(workers))
    if not own:
        return runtime.limit(limits=workers)
    if getattr(_OWN, "threads", None) != workers:  # ~50 µs a call: set only on a change
        runtime.limit(limits=workers)
        _OWN.threads = workers
    return contextlib.nullcontext()
