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
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator

import torch

from torchslam._batched import GRAIN_SIZE
from torchslam.objective.data import PointMapData

__all__ = ["GRAIN_SIZE", "solve_entries", "threads_for", "threads_for_entries"]


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
    if threads == 1 or entries >= GRAIN_SIZE:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
