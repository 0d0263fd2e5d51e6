"""Point-cloud neighbourhoods: voxel grids, nearest neighbours (KD-tree) and PCA normals.

The preprocessing that ICP (:mod:`torchslam.registration.icp`), the point tracks
(:mod:`torchslam.registration.tracks`) and the multiview pipeline share. Neighbour queries run
on the host with a KD-tree (:mod:`torchslam.registration.kdtree`; never an O(N·M) matrix), on
``torch.get_num_threads()`` threads (:func:`query_workers`); they are not meant for jacrev or
vmap. Clouds are (N, 3) torch tensors or numpy arrays (float32/float64), in any
frame: nothing here knows about poses.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from torchslam import _checks
from torchslam.registration.kdtree import KDTree

__all__ = ["estimate_normals", "nearest_neighbors", "query_workers", "voxel_downsample"]


def voxel_downsample(points: Tensor, voxel_size: float) -> Tensor:
    """Replace the points of each occupied voxel by their centroid (vectorized).

    Voxels are the cells of a grid of pitch ``voxel_size`` anchored at the minimum corner of
    the cloud. The output is sorted by voxel index (lexicographic in (x, y, z) cell
    coordinates; deterministic). Cell coordinates are computed in the dtype of ``points``
    and compared exactly, so any ratio of extent to pitch is handled; a pitch so small that
    the cell coordinates overflow the dtype is refused.

    Args:
        points: cloud, shape (N, 3), N ≥ 0, finite; a torch tensor or a numpy array
            (float32/float64).
        voxel_size: grid pitch, a finite number > 0, in the units of ``points``.

    Returns:
        Centroids, shape (M, 3) with M ≤ N, same dtype and device as ``points``.
    """
    fn = "voxel_downsample"
    points = _checks.as_points(fn, "points", points)
    voxel = _checks.check_real(fn, "voxel_size", voxel_size, low=0.0, low_open=True)
    return _downsample(fn, points, voxel)


# Largest number of cells for which an int64 key (cx · ey + cy) · ez + cz cannot overflow.
_MAX_INT_CELLS = 2**62


def _downsample(fn: str, points: Tensor, voxel: float) -> Tensor:
    """voxel_downsample on checked arguments (``fn`` names the public function)."""
    if points.shape[0] == 0:
        return points.clone()
    low = points.amin(0)
    cells = torch.floor((points - low) / voxel)
    top = cells.amax(0).tolist()  # one host sync (torch.unique syncs anyway)
    if not all(math.isfinite(c) for c in top):
        _checks.as_points(fn, "points", points, finite=True)  # NaN/Inf (validation off)
        extent = (points.amax(0) - low).tolist()
        raise ValueError(
            f"{fn}: argument 'voxel_size' = {voxel:g} is too small for the extent "
            f"{[f'{e:g}' for e in extent]} of 'points': the cell coordinates overflow "
            f"{points.dtype}"
        )
    if math.prod(int(c) + 1 for c in top) <= _MAX_INT_CELLS:
        index = cells.to(torch.int64)
        extent_y, extent_z = int(top[1]) + 1, int(top[2]) + 1
        key = (index[:, 0] * extent_y + index[:, 1]) * extent_z + index[:, 2]
        _, inverse, counts = torch.unique(key, return_inverse=True, return_counts=True)
    else:
        # More cells than an int64 key can number: compare the (exact, float) cell rows.
        _, inverse, counts = torch.unique(cells, dim=0, return_inverse=True, return_counts=True)
    sums = points.new_zeros(counts.shape[0], 3).index_add_(0, inverse, points)
    return sums / counts[:, None].to(points.dtype)


def _host(fn: str, name: str, points: Tensor) -> np.ndarray:
    """Points as a float64 numpy array (N, 3); refuses NaN/Inf, which the KD-tree cannot hold.

    Always checked (not only with validation on): the KD-tree code runs on the host anyway.
    """
    array = points.detach().reshape(-1, 3).cpu().numpy().astype(np.float64, copy=False)
    if not np.isfinite(array).all():
        bad = ~np.isfinite(array)
        first = np.unravel_index(int(np.flatnonzero(bad)[0]), tuple(points.shape))
        raise ValueError(
            f"{fn}: argument '{name}' contains {int(bad.sum())} non-finite value(s) (NaN or "
            f"Inf), first at index {tuple(int(i) for i in first)}"
        )
    return array


def _tree(fn: str, name: str, points: Tensor) -> KDTree:
    return KDTree(_host(fn, name, points))


# Thread counts of the callers that run their tensor algebra on one thread (innermost last).
_WORKERS: list[int] = []


# Fewer query points than this run on one thread whatever the setting: SciPy starts its
# worker threads per call, and on a core that other work keeps busy a second worker made the
# 5k-point queries of a LiDAR frame 1.3× slower (it gains 14 % on a quiet machine; 20k points
# gain 1.4×, 80k 1.9×).
QUERY_GRAIN = 16384


def query_workers(count: int | None = None) -> int:
    """Threads of the KD-tree queries: ``torch.get_num_threads()`` (of the caller, where ICP
    runs its own algebra on one thread), so that one setting (``torch.set_num_threads``,
    ``--threads``) governs the whole front end; 1 for a query of fewer than
    :data:`QUERY_GRAIN` points (``count``); never more than the cores other work leaves free
    (:func:`torchslam._threads.available_threads`)."""
    if count is not None and count < QUERY_GRAIN:
        return 1
    from torchslam._threads import available_threads  # the cores other work leaves free

    return available_threads(_WORKERS[-1] if _WORKERS else max(1, torch.get_num_threads()))


def nearest_neighbors(
    query: Tensor, reference: Tensor, max_distance: float | None = None
) -> tuple[Tensor, Tensor]:
    """Nearest reference point of every query point, with a KD-tree
    (:class:`~torchslam.registration.kdtree.KDTree`).

    Args:
        query: points, shape (..., 3), finite; a torch tensor or a numpy array
            (float32/float64).
        reference: points, shape (M, 3), M ≥ 1, finite, same dtype as ``query``.
        max_distance: if given, a number > 0 (``inf`` means no bound): neighbours farther
            than this are reported as missing.

    Returns:
        ``(distances, indices)``, each of shape (...); distances in ``query``'s dtype,
        indices int64. A missing neighbour has distance ``inf`` and index −1.
    """
    fn = "nearest_neighbors"
    like = _checks.first_tensor(query, reference)
    query = _checks.as_points(fn, "query", query, like=like, cloud=False, finite=False)
    reference = _checks.as_points(fn, "reference", reference, like=like, min_points=1, finite=False)
    _checks.check_same_kind(fn, query=query, reference=reference)
    if max_distance is not None:
        max_distance = _checks.check_real(
            fn, "max_distance", max_distance, low=0.0, low_open=True, allow_inf=True
        )
    tree = _tree(fn, "reference", reference)
    return _query(tree, query, max_distance, fn=fn, name="query")


def _query(
    tree: KDTree,
    query: Tensor,
    max_distance: float | None,
    k: int = 1,
    *,
    fn: str = "icp",
    name: str = "source",
) -> tuple[Tensor, Tensor]:
    """k nearest neighbours of ``query`` (..., 3) in ``tree``; ``fn``/``name`` for messages
    about non-finite query points (moved clouds whose coordinates overflowed)."""
    distance, index = _query_host(tree, _host(fn, name, query), max_distance, k)
    shape = (*query.shape[:-1], k) if k > 1 else query.shape[:-1]
    distance_t = torch.from_numpy(distance).to(query.dtype).reshape(shape)
    index_t = torch.from_numpy(index).reshape(shape)
    return distance_t.to(query.device), index_t.to(query.device)


def _query_host(
    tree: KDTree, flat: np.ndarray, max_distance: float | None, k: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_query` on a finite float64 array (n, 3): distances (float64) and int64 indices,
    shape (n,) for k = 1, else (n, k); a missing neighbour is (inf, −1)."""
    bound = np.inf if max_distance is None else float(max_distance)
    distance, index = tree.query(
        flat, k=k, distance_upper_bound=bound, workers=query_workers(len(flat))
    )
    distance = np.asarray(distance, dtype=np.float64)
    index = np.asarray(index, dtype=np.int64)
    if bound < np.inf:  # scipy reports a missing neighbour as index n
        index[~np.isfinite(distance)] = -1
    return distance, index


def estimate_normals(
    points: Tensor, neighbors: int = 16, viewpoint: Tensor | None = None
) -> Tensor:
    """Unit surface normals by PCA over the k nearest neighbours of each point.

    The normal is the eigenvector of the smallest eigenvalue of the neighbourhood covariance.
    Its sign is arbitrary unless ``viewpoint`` is given, in which case every normal is flipped
    to point towards it (e.g. the scanner position).

    Args:
        points: cloud, shape (N, 3), N ≥ 3, finite; a torch tensor or a numpy array
            (float32/float64).
        neighbors: k (an int), the neighbourhood size including the point itself,
            3 ≤ k ≤ N.
        viewpoint: optional position, shape (3,), finite, same dtype as ``points``.

    Returns:
        Normals, shape (N, 3), unit length, same dtype and device as ``points``.
    """
    fn = "estimate_normals"
    points = _checks.as_points(fn, "points", points, min_points=3, finite=False)
    k = _checks.check_int(fn, "neighbors", neighbors, minimum=3, maximum=points.shape[0])
    if viewpoint is not None:
        viewpoint = _checks.as_points(fn, "viewpoint", viewpoint, like=points, cloud=False)
        if viewpoint.shape != (3,):
            raise ValueError(
                f"{fn}: argument 'viewpoint' must have shape (3,), got {tuple(viewpoint.shape)}"
            )
        _checks.check_same_kind(fn, points=points, viewpoint=viewpoint)
    return _normals(fn, points, k, viewpoint)


def _normals(fn: str, points: Tensor, k: int, viewpoint: Tensor | None) -> Tensor:
    """estimate_normals on checked arguments (``fn`` names the public function)."""
    return _normals_and_neighbours(fn, points, k, viewpoint)[0]


def _normals_and_neighbours(
    fn: str, points: Tensor, k: int, viewpoint: Tensor | None
) -> tuple[Tensor, np.ndarray, np.ndarray]:
    """:func:`_normals` and the k-nearest query it made: (normals (N, 3), distances (N, k)
    float64 ascending, indices (N, k) int64), for a caller with more to compute from the same
    neighbourhoods (:func:`_boundary_from_neighbours`)."""
    flat = _host(fn, "points", points)
    tree = KDTree(flat)
    distance, index = _query_host(tree, flat, None, k)
    normals = torch.from_numpy(_smallest_eigenvectors(flat, index))
    normals = normals.to(dtype=points.dtype, device=points.device)
    if viewpoint is not None:
        facing = ((viewpoint - points) * normals).sum(-1, keepdim=True)
        normals = torch.where(facing < 0, -normals, normals)
    return normals, distance, index


def _boundary_from_neighbours(
    points: np.ndarray,
    distance: np.ndarray,
    index: np.ndarray,
    threshold: float,
    normals: np.ndarray | None = None,
) -> np.ndarray:
    """The boundary test of :func:`~torchslam.registration.pipeline.boundary_mask` from a
    k-nearest query made already (e.g. for the normals): ``points`` (N, 3) float64,
    ``distance``/``index`` (N, k) of the k ≥ 2 nearest neighbours of each point among
    ``points`` (the point itself first, distances ascending), ``normals`` (N, 3) float64 of
    any sign, or None for the PCA of each neighbourhood → bool (N,), True on the boundary.
    The arguments are not checked (an internal step; ``boundary_mask`` checks them)."""
    local = points[index]  # (N, k, 3)
    centroid = local.mean(1)
    # Only the offset along the surface counts: on a curved surface the centroid also lies
    # off the point along the normal (the smallest principal axis of the neighbourhood).
    if normals is None:
        centred = local - centroid[:, None]
        _, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
        normals = vectors[..., 0]
    offset = centroid - points
    offset -= (offset * normals).sum(-1, keepdims=True) * normals
    spacing = distance[:, 1:].mean(1)
    return np.linalg.norm(offset, axis=-1) > threshold * spacing


def _smallest_eigenvectors(points: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Unit eigenvector of the smallest eigenvalue of each neighbourhood's scatter matrix.

    ``points`` (M, 3) float64, ``index`` (N, k) rows of ``points`` → (N, 3) float64 (sign
    arbitrary). Closed form instead of a
    batched LAPACK call per 3 × 3 matrix (several times faster): with the scatter matrix C
    scaled to unit trace, the eigenvalues follow from the trigonometric solution of the
    characteristic cubic, and the eigenvector of the smallest, λ, is the largest of the cross
    products of two rows of C − λI (the columns of its adjugate, each a multiple of the
    eigenvector). Its direction error is about ε / ((λ₂ − λ)(λ₃ − λ)) (ε the rounding of λ, a
    few units in the last place); where that product is below 1e-6 (neighbourhoods on a line
    or a point, whose normal is ill-defined anyway) the rows go to ``numpy.linalg.eigh``.
    """
    # One coordinate at a time: contiguous (N, k) arrays, centred on each neighbourhood's mean.
    x, y, z = (np.ascontiguousarray(points[:, axis])[index] for axis in range(3))
    # Row sums by einsum (faster than .mean(1) on short rows; no BLAS threads).
    x, y, z = (u - (np.einsum("nk->n", u) / index.shape[1])[:, None] for u in (x, y, z))
    xx = np.einsum("nk,nk->n", x, x)
    yy = np.einsum("nk,nk->n", y, y)
    zz = np.einsum("nk,nk->n", z, z)
    xy = np.einsum("nk,nk->n", x, y)
    xz = np.einsum("nk,nk->n", x, z)
    yz = np.einsum("nk,nk->n", y, z)
    trace = xx + yy + zz
    scale = 1.0 / np.where(trace > 0, trace, 1.0)
    xx, yy, zz, xy, xz, yz = (c * scale for c in (xx, yy, zz, xy, xz, yz))
    q = 1.0 / 3.0  # trace / 3 after scaling
    dx, dy, dz = xx - q, yy - q, zz - q
    p = np.sqrt((dx * dx + dy * dy + dz * dz + 2.0 * (xy * xy + xz * xz + yz * yz)) / 6.0)
    inverse_p = 1.0 / np.where(p > 0, p, 1.0)
    # r = det((C − qI) / p) / 2 ∈ [−1, 1]
    det = dx * (dy * dz - yz * yz) - xy * (xy * dz - yz * xz) + xz * (xy * yz - dy * xz)
    r = np.clip(0.5 * det * inverse_p**3, -1.0, 1.0)
    smallest = q + 2.0 * p * np.cos(np.arccos(r) / 3.0 + 2.0 * np.pi / 3.0)
    a, b, c = xx - smallest, yy - smallest, zz - smallest  # C − λI, rows m0, m1, m2
    crosses = np.stack(
        (
            (xy * yz - xz * b, xz * xy - a * yz, a * b - xy * xy),  # m0 × m1
            (xy * c - xz * yz, xz * xz - a * c, a * yz - xy * xz),  # m0 × m2
            (b * c - yz * yz, yz * xz - xy * c, xy * yz - b * xz),  # m1 × m2
        )
    )  # (3 products, 3 components, N)
    lengths = np.sqrt(np.einsum("pcn,pcn->pn", crosses, crosses))
    best = lengths.argmax(0)
    every = np.arange(len(best))
    length = lengths[best, every]
    normals = crosses[best, :, every] / np.where(length > 0, length, 1.0)[:, None]
    poor = length < 1e-6
    if poor.any():
        centred = np.stack((x[poor], y[poor], z[poor]), -1)  # (n, k, 3)
        scatter = centred.transpose(0, 2, 1) @ centred
        normals[poor] = np.linalg.eigh(scatter)[1][..., 0]  # ascending eigenvalues
    return normals


class _Matcher:
    """Nearest target point of every point of a moving cloud, pass after pass (the ICP loop).

    A point's nearest neighbour is looked up in the KD-tree only when its previous answer is
    not certain to still hold. A lookup with k = 2 returns the two nearest target points
    c, c₂ within a bound b (at distances d ≤ d₂; d₂ = ∞ beyond b). While the point stays
    within δ < (min(d₂, b) − d) / 2 of where it was looked up, c is still its unique nearest
    target point: |x′ − c| ≤ d + δ < min(d₂, b) − δ ≤ |x′ − y| for every other y. A point
    with no target point within b has none within b − δ either, so it stays unmatched while
    b − δ exceeds the gate of the current pass. The answers (distances recomputed at the new
    position) are therefore exactly those of a fresh query; near convergence, where the
    points move by far less than their spacing, almost no point needs one. A slack relative
    to the coordinates covers rounding in the distances.

    The second neighbour costs about 15 % more per lookup, and pays only if the points move
    little before the next pass: lookups ask for it once the mean motion between passes has
    at least halved (ICP's steps shrink fast near convergence) or is below a quarter of the
    gate, or most points kept their answer; otherwise k = 1 and found points get no
    certificate.

    State is kept per batch row (``batch`` runs of the same cloud of ``n`` points).
    """

    # Lookups with k = 2 use a bound this much wider than the gate, so that unmatched points
    # stay certainly unmatched under small motions.
    BOUND_FACTOR = 1.0625

    def __init__(self, tree: KDTree, target: np.ndarray, batch: int, n: int) -> None:
        self.tree = tree
        self.target = target
        self.target_size = float(np.abs(target).max()) if target.size else 0.0
        self.batch = batch
        self.reference = np.zeros((batch, n, 3))  # positions at the last lookup
        self.index = np.full((batch, n), -1, dtype=np.int64)  # nearest target point or −1
        self.margin = np.full((batch, n), -np.inf)  # see the class docstring (−inf: none)
        self.motion = math.nan  # mean motion since the last lookup, at the previous pass
        self.looked_up = False

    def __call__(
        self, rows: np.ndarray, moved: Tensor, gate: np.ndarray, fn: str, name: str
    ) -> tuple[Tensor, Tensor]:
        """Distances (inf where none within the bound) and indices (−1) of ``moved``
        (R, n, 3), the clouds of the increasing batch rows ``rows`` (R,), whose gates are
        ``gate`` (R,)."""
        x = _host(fn, name, moved).reshape(moved.shape)
        whole = len(rows) == self.batch  # then rows = 0 … batch − 1: work in place
        if whole:
            reference, index, margin = self.reference, self.index, self.margin
        else:
            reference, index, margin = self.reference[rows], self.index[rows], self.margin[rows]
        step = x - reference
        delta = np.sqrt(np.einsum("rnk,rnk->rn", step, step))
        slack = 1e-12 * (float(np.abs(x).max()) + self.target_size)
        found = index >= 0
        keep = np.where(found, delta + slack < margin, margin - delta - slack > gate[:, None])
        kept = int(np.count_nonzero(keep))
        motion = float(delta.mean()) if self.looked_up else math.nan  # NaN: no reference yet
        reach = float(gate.max())  # the gates are the scale of the expected motions
        small = motion <= 0.5 * self.motion or (math.isfinite(reach) and motion <= reach / 4)
        k = 2 if small or 2 * kept >= keep.size else 1
        self.motion, self.looked_up = motion, True
        distance = np.full(index.shape, np.inf)
        if kept:
            hit = keep & found
            offset = x[hit] - self.target[index[hit]]
            distance[hit] = np.sqrt(np.einsum("mk,mk->m", offset, offset))
        if kept < keep.size:
            lookup = ~keep
            every = kept == 0
            bound = float((gate if every else gate[lookup.any(1)]).max())
            bound *= self.BOUND_FACTOR if k == 2 else 1.0
            points = x.reshape(-1, 3) if every else x[lookup]
            d, i = self.tree.query(
                points, k=k, distance_upper_bound=bound, workers=query_workers(len(points))
            )
            first, nearest = (d, i) if k == 1 else (d[:, 0], i[:, 0])
            near = np.isfinite(first)
            nearest = np.where(near, nearest, -1)
            if k == 2:
                room = np.where(near, 0.5 * (np.minimum(d[:, 1], bound) - first), bound)
            else:
                room = np.where(near, -np.inf, bound)
            if every:
                distance = first.reshape(index.shape)
                index[...] = nearest.reshape(index.shape)
                margin[...] = room.reshape(index.shape)
                reference[...] = x
            else:
                distance[lookup], index[lookup], margin[lookup] = first, nearest, room
                reference[lookup] = points
            if not whole:
                self.reference[rows], self.index[rows], self.margin[rows] = (
                    reference,
                    index,
                    margin,
                )
        return (
            torch.from_numpy(distance).to(dtype=moved.dtype, device=moved.device),
            torch.from_numpy(index.copy()).to(moved.device),
        )
