"""Reports of a registration: how consistent a pose set is, and how far from a reference.

Without a reference: :func:`alignment_residual` (RMS point-to-plane distance between
overlapping scans) and :func:`plane_distances` (the distances themselves, for histograms).
Against a reference alignment: :func:`error_table` (per-scan rotation and translation errors,
mean and max). Poses are T_0i, mapping scan i into a common frame, shape (m, 4, 4).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from torchslam import _checks
from torchslam.io.stanford import pose_errors
from torchslam.lie import se3
from torchslam.registration.config import check_clouds, check_poses
from torchslam.registration.kdtree import KDTree
from torchslam.registration.neighbors import estimate_normals, query_workers

__all__ = ["alignment_residual", "error_table", "plane_distances"]


def plane_distances(
    clouds: Sequence[Tensor],
    poses: Tensor,
    pairs: Sequence[tuple[int, int]],
    distance: float,
    normal_neighbors: int = 12,
) -> np.ndarray:
    """Signed point-to-plane distances between overlapping scans (see :func:`alignment_residual`).

    Returns:
        One distance per corresponding point, float64 array (K,), in the clouds' units.
    """
    return _plane_distances("plane_distances", clouds, poses, pairs, distance, normal_neighbors)


def _plane_distances(
    fn: str,
    clouds: Sequence[Tensor],
    poses: Tensor,
    pairs: Sequence[tuple[int, int]],
    distance: float,
    normal_neighbors: int,
) -> np.ndarray:
    clouds = check_clouds(fn, clouds, min_points=3)
    m = len(clouds)
    check_poses(fn, poses, m)
    poses = poses.to(clouds[0].dtype)
    pairs = _checks.check_index_pairs(fn, pairs, m)
    distance = _checks.check_real(fn, "distance", distance, low=0, low_open=True)
    normal_neighbors = _checks.check_int(fn, "normal_neighbors", normal_neighbors, minimum=3)
    normals = [estimate_normals(c, min(normal_neighbors, len(c))) for c in clouds]
    world = [se3.act(poses[i], clouds[i]).detach().cpu().numpy() for i in range(m)]
    world_normals = [(normals[i] @ poses[i, :3, :3].T).detach().cpu().numpy() for i in range(m)]
    trees = [KDTree(w) for w in world]
    out = [np.zeros(0)]
    for a, b in pairs:
        for i, k in ((a, b), (b, a)):
            d, j = trees[k].query(world[i], distance_upper_bound=distance, workers=query_workers())
            inside = np.isfinite(d)
            offset = world[i][inside] - world[k][j[inside]]
            out.append((offset * world_normals[k][j[inside]]).sum(-1))
    return np.concatenate(out)


def alignment_residual(
    clouds: Sequence[Tensor],
    poses: Tensor,
    pairs: Sequence[tuple[int, int]],
    distance: float,
    normal_neighbors: int = 12,
) -> float:
    """RMS point-to-plane distance between overlapping scans: a consistency check of poses.

    For every ordered pair (i, k) of ``pairs`` (both directions), each point of scan i whose
    nearest point of scan k (world frame) lies within ``distance`` contributes its distance
    to the tangent plane of scan k there (PCA normal). Independent of any point tracks.

    Args:
        clouds: m clouds in their scan frames, shapes (N_i, 3).
        poses: T_0i, shape (m, 4, 4).
        pairs: scan pairs.
        distance: correspondence gate, > 0.
        normal_neighbors: k of the PCA normals.

    Returns:
        The RMS distance, in the clouds' units (nan when no point corresponds).
    """
    d = _plane_distances("alignment_residual", clouds, poses, pairs, distance, normal_neighbors)
    return float(np.sqrt(np.mean(d**2))) if len(d) else math.nan


def error_table(
    names: Sequence[str],
    frame: int,
    reference: Tensor,
    columns: dict[str, Tensor],
    include: Sequence[int] | None = None,
) -> tuple[str, dict[str, dict[str, float]]]:
    """Per-scan rotation (degrees) and translation (mm, for scans in metres) error table.

    Args:
        names: scan names, m.
        frame: index of the scan whose frame both pose sets are compared in.
        reference: reference T_0i (any common frame), shape (m, 4, 4).
        columns: label → estimated T_0i (m, 4, 4).
        include: scans in the mean/max rows; all but ``frame`` by default.

    Returns:
        ``(text, summary)`` with summary[label] = {"rot_mean", "rot_max", "trans_mean",
        "trans_max"} (degrees, mm).
    """
    fn = "error_table"
    names = _checks.check_names(fn, names, words=False)
    m = len(names)
    if m == 0:
        raise ValueError(f"{fn}: argument 'names' must hold at least one name, got none")
    frame = _checks.check_int(fn, "frame", frame, minimum=0, maximum=m - 1)
    check_poses(fn, reference, m, against="'names'")
    if not isinstance(columns, dict) or not columns:
        raise TypeError(
            f"{fn}: argument 'columns' must be a non-empty dict label → poses (m, 4, 4), "
            f"got {_checks.describe(columns)}"
        )
    for label, poses in columns.items():
        if not isinstance(label, str):
            raise TypeError(f"{fn}: argument 'columns' must have str labels, got {label!r}")
        _checks.check_batched(fn, f"columns[{label!r}]", poses, ("m",), (4, 4), sizes=(m,))
        _checks.check_pose_matrix(fn, f"columns[{label!r}]", poses)
    if include is None:
        include = [i for i in range(m) if i != frame]
    else:
        if isinstance(include, (str, Tensor)) or not isinstance(include, Sequence):
            raise TypeError(
                f"{fn}: argument 'include' must be None or a list of scan indices, "
                f"got {_checks.describe(include)}"
            )
        include = [
            _checks.check_int(fn, f"include[{k}]", i, minimum=0, maximum=m - 1)
            for k, i in enumerate(include)
        ]
    if not include:
        raise ValueError(f"{fn}: no scans to summarize ('include' is empty or only 'frame')")
    errors = {}
    for label, poses in columns.items():
        rotation, translation = pose_errors(poses.to(reference.dtype), reference, frame)
        errors[label] = (rotation, translation * 1000)
    head = f"{'scan':<10}" + "".join(
        f" {label + ' rot°':>14} {label + ' mm':>12}" for label in errors
    )
    lines = [head]
    for i, name in enumerate(names):
        mark = "" if i in include or i == frame else " *"
        row = f"{name + mark:<10}"
        for rotation, translation in errors.values():
            row += f" {float(rotation[i]):14.3f} {float(translation[i]):12.3f}"
        lines.append(row)
    summary: dict[str, dict[str, float]] = {}
    index = torch.tensor(include, dtype=torch.int64)
    for key in ("mean", "max"):
        row = f"{key:<10}"
        for label, (rotation, translation) in errors.items():
            r, t = rotation[index], translation[index]
            r_value = float(r.mean() if key == "mean" else r.max())
            t_value = float(t.mean() if key == "mean" else t.max())
            summary.setdefault(label, {})[f"rot_{key}"] = r_value
            summary[label][f"trans_{key}"] = t_value
            row += f" {r_value:14.3f} {t_value:12.3f}"
        lines.append(row)
    return "\n".join(lines), summary
