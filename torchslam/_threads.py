"""The library's thread policy for a solve's own tensor work: small problems on one thread.

torch splits an elementwise kernel over its intra-op threads only from :data:`GRAIN_SIZE`
(32,768) elements on, but some kernels open an OpenMP parallel region whatever their size
(``index_add``, the triangle a Cholesky zeroes, small LU factorizations, advanced indexing).
In a solve whose per-operation tensors all stay below the grain size, a second thread can only
add those regions' fork and join — and on a CPU shared with other work, a wait for a busy core
in every region: with one of two cores kept busy by another process, case S of ``torchslam
bench`` took 102 ms on 2 threads without this policy, 28 ms with it (25 ms on 1 thread). So a
solve (forward, and the implicit backward) whose largest per-operation tensor,
:func:`solve_entries`, is below :data:`GRAIN_SIZE` runs on one intra-op thread; a larger one on
torch's setting (``torch.get_num_threads()``); a :class:`torchslam.PointMapProblem`'s
construction (its argument checks and gauge) follows the same rule. The count is restored on
exit. Like
``torch.set_num_threads`` itself this is a process setting: do not change torch's thread count
from another Python thread while a solve runs.

A larger solve does not take the cores that other work keeps busy either
(:func:`available_threads`): each OpenMP region would wait for them. On Linux the number of
runnable tasks (``/proc/loadavg``, an instantaneous count, not the averages) less this one is
subtracted from the cores this process may use; with one of two cores spinning in another
process, case M of ``torchslam bench`` took 5.3× longer on 2 threads than on 1, and
``solve_pose_graph`` on parking-garage 2.1× (``experiments/threads_under_load.py``).
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Iterator

import torch

from torchslam._batched import GRAIN_SIZE
from torchslam.objective.data import PointMapData

__all__ = [
    "GRAIN_SIZE",
    "available_threads",
    "busy_cores",
    "solve_entries",
    "threads_for",
    "threads_for_entries",
]


def usable_cores() -> int:
    """The cores this process may run on (its affinity mask where the OS has one)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def busy_cores() -> int:
    """Tasks that are runnable now besides the caller (Linux: the fourth field of
    ``/proc/loadavg``, minus one); 0 where the OS does not say."""
    try:
        with open("/proc/loadavg", encoding="ascii") as f:
            running = int(f.read().split()[3].split("/")[0])
    except (OSError, ValueError, IndexError):
        return 0
    return max(0, running - 1)


def available_threads(requested: int) -> int:
    """``requested`` threads, less the cores that other work keeps busy now (at least 1)."""
    if requested <= 1:
        return max(1, requested)
    return max(1, min(requested, usable_cores() - busy_cores()))


def solve_entries(data: PointMapData) -> int:
    """The entries of a solve's largest per-operation tensor, estimated from its sizes: the
    per-observation 3 × 3 blocks (9·B·E), the pose blocks (36·B·m), the terms' 6 × 6 blocks
    (36 per instance and batch problem), the points (3·B·n) and the dense reduced system
    ((6m)² per problem, which a dense solve forms)."""
    B, E = data.pose_index.shape
    m, n = data.num_poses, data.num_points
    terms = 0
    for term in data.terms:
        shape = term.pose_index.shape[:-1]
        terms += math.prod(shape) * (B if len(shape) == 1 else 1)
    return max(9 * B * E, 36 * B * m, 36 * terms, 3 * B * n, B * (6 * m) ** 2)


@contextlib.contextmanager
def threads_for(data: PointMapData) -> Iterator[None]:
    """``with threads_for(data):`` one intra-op thread inside when :func:`solve_entries` of
    ``data`` is below :data:`GRAIN_SIZE` (module doc), torch's setting otherwise."""
    with threads_for_entries(solve_entries(data)):
        yield


@contextlib.contextmanager
def threads_for_entries(entries: int) -> Iterator[None]:
    """:func:`threads_for` for work whose largest per-operation tensor has ``entries``
    entries (a problem's construction and checks)."""
    threads = torch.get_num_threads()
    if threads == 1:
        yield
        return
    target = available_threads(threads) if entries >= GRAIN_SIZE else 1
    if target == threads:
        yield
        return
    torch.set_num_threads(target)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
