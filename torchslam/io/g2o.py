"""Read and write g2o pose-graph files (3D ``SE3:QUAT`` and 2D ``SE2``) as :class:`PoseGraph`.

g2o's conventions and how they map to torchslam's
--------------------------------------------------
3D lines (all numbers separated by white space)::

    VERTEX_SE3:QUAT id  x y z  qx qy qz qw
    EDGE_SE3:QUAT   i j  dx dy dz  dqx dqy dqz dqw  I11 I12 … I16 I22 … I66   (21 numbers)

- Quaternions are Hamilton, written scalar LAST (qx, qy, qz, qw); torchslam stores (w, x, y, z).
  They are normalized on reading (as g2o does), robustly: divided by their largest magnitude
  before the norm, so (1e200, 1e200, 0, 0) and (1e-200, 0, 0, 0) normalize exactly; a zero
  quaternion is an error. On writing,
  the quaternion of each rotation matrix is written with qw ≥ 0.
- A vertex (t, q) is the pose T_i = [[R(q), t], [0, 1]] mapping body-i points into the world.
- An edge (i, j) measures the pose of j seen from i: Z_ij = T_ij ≈ T_i⁻¹ T_j, the same meaning as
  torchslam's between residual r_ij = Log(Z_ij⁻¹ T_i⁻¹ T_j).
- The information matrix is the upper triangle, row-major, of a symmetric 6 × 6 matrix ordered
  [translation (x, y, z), rotation (qx, qy, qz)]. torchslam orders tangents ξ = (ω, v), rotation
  first, so ``information = P I_g2o Pᵀ`` with the permutation ours[k] = g2o[(k + 3) mod 6],
  i.e. Ω_ours = [[I_RR, I_Rt], [I_tR, I_tt]]. The numbers are used as they are, like GTSAM's
  ``readG2o`` (no rescaling; g2o's own χ² measures the rotation error with the quaternion's
  vector part ≈ ω/2, torchslam and GTSAM with the log map ω).

2D lines::

    VERTEX_SE2 id  x y θ
    EDGE_SE2   i j  dx dy dθ  I11 I12 I13 I22 I23 I33      (order x, y, θ)

2D graphs are lifted into SE(3): a pose (x, y, θ) becomes [[Rz(θ), (x, y, 0)], [0, 1]], and the
3 × 3 information over (x, y, θ) fills the (v_x, v_y, ω_z) rows and columns of the 6 × 6 one. The
out-of-plane directions (ω_x, ω_y, v_z), which a 2D file does not constrain, get the diagonal
weights I_θθ, I_θθ and (I_xx + I_yy)/2 (and no cross terms), so the matrix stays positive
definite; for planar poses their residuals are exactly zero and do not change the cost. The
graph's ``dimension`` is 2. Writing a 2D graph keeps x, y, θ = atan2(R₁₀, R₀₀) and the
(x, y, θ) block of the information, i.e. it projects any out-of-plane component away.

Other rules
-----------
- Blank lines are skipped, and so is everything from a ``#`` to the end of a line.
- ``FIX id …`` lines record fixed vertices in ``PoseGraph.fixed`` (indices, not ids).
- Tags in :data:`SKIPPED_TAGS` (parameter blocks, which only landmark edges use) are skipped.
  Every other tag (landmarks included) is an unknown tag and raises ValueError, as do a wrong
  number of fields, a non-numeric or non-finite number (``nan``, ``inf``, ``1e999``), an id
  that is not a decimal integer in [0, 2⁶³ − 1], a duplicate vertex id, an edge to a missing
  vertex, an information matrix that is not positive semidefinite, 2D and 3D lines in the same
  file, and (for :func:`read_g2o`) bytes that are not UTF-8 text. Every message names the file
  and the line number.
- Vertices are sorted by id (``PoseGraph.ids``); edges keep the file's order.
- Numbers are written with ``repr`` (the shortest decimal that reads back to the same float64),
  so write → read reproduces the graph to round-off (the quaternion ↔ matrix conversions are the
  only inexact steps, about 1e-16).
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchslam._checks import check_pose_matrix, check_tensor, describe, validation
from torchslam.io import _text
from torchslam.lie import convert
from torchslam.posegraph.graph import PoseGraph

__all__ = ["SKIPPED_TAGS", "format_g2o", "parse_g2o", "read_g2o", "write_g2o"]

# Tags that carry no pose-graph information and are skipped on reading: g2o parameter blocks,
# used only by landmark/sensor-offset edges (which are rejected as unknown tags).
SKIPPED_TAGS = frozenset({"PARAMS_SE3OFFSET", "PARAMS_CAMERACALIB"})

# Number of fields after the tag, per tag.
_FIELD_COUNTS = {"VERTEX_SE3:QUAT": 8, "EDGE_SE3:QUAT": 30, "VERTEX_SE2": 4, "EDGE_SE2": 11}
_DIMENSION = {"VERTEX_SE3:QUAT": 3, "EDGE_SE3:QUAT": 3, "VERTEX_SE2": 2, "EDGE_SE2": 2}

# ours[k] = g2o[_G2O_TO_OURS[k]]: ξ = (ω, v) from g2o's [translation, rotation].
_G2O_TO_OURS = [3, 4, 5, 0, 1, 2]
# Positions (v_x, v_y, ω_z) in ξ = (ω, v) of g2o's 2D (x, y, θ).
_SE2_TO_OURS = [3, 4, 2]


# A problem with one line; ``parse_g2o`` adds the file name and line number.
_LineError = _text.TokenError

# Vertex ids are stored as int64.
_MAX_ID = 2**63 - 1
# An information matrix is positive semidefinite when its smallest eigenvalue is at least
# −_PSD_TOLERANCE × its largest magnitude: a singular matrix written with 17 digits has
# eigenvalues of order 1e-16 × that magnitude of either sign.
_PSD_TOLERANCE = 1e-9


def _int(token: str) -> int:
    return _text.parse_integer(token, 0, _MAX_ID, "an integer vertex id")


def _floats(tokens: Iterable[str]) -> list[float]:
    return [_text.parse_finite_float(token) for token in tokens]


def _with_unit_quaternion(values: list[float], start: int, what: str) -> list[float]:
    """``values`` with the quaternion at ``start:start + 4`` normalized (module docstring)."""
    q = _text.unit_quaternion(values[start : start + 4], what)
    return [*values[:start], *q, *values[start + 4 :]]


def _symmetric_from_upper(upper: np.ndarray, n: int) -> np.ndarray:
    """(E, n(n+1)/2) row-major upper triangles → (E, n, n) symmetric matrices."""
    rows, cols = np.triu_indices(n)
    full = np.zeros((upper.shape[0], n, n))
    full[:, rows, cols] = upper
    full[:, cols, rows] = upper
    return full


def _quaternion_xyzw_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (K, 3, 3) of unit Hamilton quaternions given scalar-last (K, 4)."""
    x, y, z, w = q.T
    return np.stack(
        (
            np.stack((1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)), -1),
            np.stack((2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)), -1),
            np.stack((2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)), -1),
        ),
        axis=-2,
    )


def _rotation_z(theta: np.ndarray) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    zero, one = np.zeros_like(theta), np.ones_like(theta)
    return np.stack(
        (np.stack((c, -s, zero), -1), np.stack((s, c, zero), -1), np.stack((zero, zero, one), -1)),
        axis=-2,
    )


def _poses(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.zeros((R.shape[0], 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = t
    T[:, 3, 3] = 1.0
    return T


def _poses_3d(values: np.ndarray) -> np.ndarray:
    """(K, 7) rows (x, y, z, qx, qy, qz, qw) with unit quaternions → (K, 4, 4)."""
    return _poses(_quaternion_xyzw_to_matrix(values[:, 3:7]), values[:, :3])


def _poses_2d(values: np.ndarray) -> np.ndarray:
    """(K, 3) rows (x, y, θ) → (K, 4, 4) in the plane z = 0."""
    t = np.concatenate((values[:, :2], np.zeros((values.shape[0], 1))), axis=-1)
    return _poses(_rotation_z(values[:, 2]), t)


def _not_semidefinite(matrices: np.ndarray) -> int | None:
    """Index of the first of (E, n, n) symmetric matrices that is not PSD, or None."""
    if matrices.shape[0] == 0:
        return None
    # Scale each matrix by its largest entry first: eigvalsh of entries near 1e300 overflows.
    scale = np.abs(matrices).max(axis=(-2, -1), keepdims=True)
    eigenvalues = np.linalg.eigvalsh(matrices / np.where(scale > 0, scale, 1.0))
    bad = eigenvalues[:, 0] < -_PSD_TOLERANCE * np.abs(eigenvalues).max(-1)
    return int(np.argmax(bad)) if bad.any() else None


def _information_3d(upper: np.ndarray) -> np.ndarray:
    full = _symmetric_from_upper(upper, 6)
    return full[:, _G2O_TO_OURS][:, :, _G2O_TO_OURS]


def _information_2d(upper: np.ndarray) -> np.ndarray:
    planar = _symmetric_from_upper(upper, 3)
    full = np.zeros((upper.shape[0], 6, 6))
    full[:, np.array(_SE2_TO_OURS)[:, None], np.array(_SE2_TO_OURS)[None, :]] = planar
    # Out-of-plane weights (module docstring): ω_x, ω_y like θ, v_z like the mean of x and y.
    full[:, 0, 0] = full[:, 1, 1] = planar[:, 2, 2]
    full[:, 5, 5] = 0.5 * (planar[:, 0, 0] + planar[:, 1, 1])
    return full


def parse_g2o(
    text: str, *, source: str = "<string>", dtype: torch.dtype = torch.float64
) -> PoseGraph:
    """Parse the text of a g2o pose-graph file (rules and conventions: module docstring).

    Args:
        text: the file's contents.
        source: the name used in error messages (the file's path for :func:`read_g2o`).
        dtype: floating dtype of the returned tensors (float64 by default).

    Returns:
        A :class:`PoseGraph` with N vertices sorted by id and E edges in file order:
        poses (N, 4, 4), edges (E, 2) as indices, measurements Z_ij ≈ T_i⁻¹ T_j (E, 4, 4),
        information (E, 6, 6) in (ω, v) order.

    Raises:
        ValueError: for a malformed line, an unknown tag, an inconsistent graph; the message
            names ``source`` and the line number (module docstring, "Other rules"), or a value
            that overflows ``dtype``.
        TypeError: ``text`` or ``source`` is not a str, ``dtype`` not float32/float64.
    """
    from torchslam import _checks  # local: keeps this module's imports untouched

    _checks.check_float_dtype("parse_g2o", dtype)
    for name, value in (("text", text), ("source", source)):
        if not isinstance(value, str):
            raise TypeError(
                f"parse_g2o: argument '{name}' must be a str, got {_checks.describe(value)}"
            )
    vertex_ids: list[int] = []
    vertex_values: list[list[float]] = []
    vertex_lines: list[int] = []
    edge_ids: list[tuple[int, int]] = []
    edge_values: list[list[float]] = []
    edge_lines: list[int] = []
    fixed_ids: list[tuple[int, int]] = []  # (id, line number)
    dimension = 0
    dimension_line = 0

    def error(lineno: int, message: str) -> ValueError:
        return ValueError(f"parse_g2o: {source}, line {lineno}: {message}")

    # Split at "\n" only: str.splitlines also splits at form feeds etc., shifting the numbers.
    for lineno, raw in enumerate(text.split("\n"), start=1):
        tokens = raw.split("#", 1)[0].split()
        if not tokens:
            continue
        tag, fields = tokens[0], tokens[1:]
        try:
            if tag in SKIPPED_TAGS:
                continue
            if tag == "FIX":
                if not fields:
                    raise _LineError("FIX expects at least one vertex id, got none")
                fixed_ids.extend((_int(f), lineno) for f in fields)
                continue
            if tag not in _FIELD_COUNTS:
                known = ", ".join([*_FIELD_COUNTS, "FIX", *sorted(SKIPPED_TAGS)])
                raise _LineError(f"unknown tag {tag!r} (known tags: {known})")
            if len(fields) != _FIELD_COUNTS[tag]:
                raise _LineError(
                    f"{tag} expects {_FIELD_COUNTS[tag]} fields after the tag, got {len(fields)}"
                )
            if dimension == 0:
                dimension, dimension_line = _DIMENSION[tag], lineno
            elif _DIMENSION[tag] != dimension:
                raise _LineError(
                    f"{tag} is a {_DIMENSION[tag]}D tag but line {dimension_line} made this a "
                    f"{dimension}D graph; mixed 2D/3D files are not supported"
                )
            if tag.startswith("VERTEX"):
                vid = _int(fields[0])
                values = _floats(fields[1:])
                if tag == "VERTEX_SE3:QUAT":
                    values = _with_unit_quaternion(values, 3, "quaternion (qx, qy, qz, qw)")
                vertex_ids.append(vid)
                vertex_values.append(values)
                vertex_lines.append(lineno)
            else:
                pair = (_int(fields[0]), _int(fields[1]))
                values = _floats(fields[2:])
                if tag == "EDGE_SE3:QUAT":
                    values = _with_unit_quaternion(values, 3, "quaternion (dqx, dqy, dqz, dqw)")
                edge_ids.append(pair)
                edge_values.append(values)
                edge_lines.append(lineno)
        except _LineError as exc:
            raise error(lineno, str(exc)) from None

    if not vertex_ids:
        raise ValueError(
            f"parse_g2o: {source}: no vertices (no VERTEX_SE3:QUAT or VERTEX_SE2 line)"
        )
    index_of: dict[int, int] = {}
    first_line: dict[int, int] = {}
    for vid, lineno in zip(vertex_ids, vertex_lines, strict=True):
        if vid in first_line:
            raise error(
                lineno, f"duplicate vertex id {vid} (first defined on line {first_line[vid]})"
            )
        first_line[vid] = lineno
    order = sorted(range(len(vertex_ids)), key=vertex_ids.__getitem__)
    for index, k in enumerate(order):
        index_of[vertex_ids[k]] = index

    def indices(pairs: list[tuple[int, int]], lines: list[int]) -> np.ndarray:
        out = np.zeros((len(pairs), 2), dtype=np.int64)
        for e, ((a, b), lineno) in enumerate(zip(pairs, lines, strict=True)):
            for k, vid in enumerate((a, b)):
                if vid not in index_of:
                    raise error(
                        lineno, f"edge refers to vertex id {vid}, which no VERTEX line defines"
                    )
                out[e, k] = index_of[vid]
        return out

    edges = indices(edge_ids, edge_lines)
    fixed = [index_of[vid] if vid in index_of else -1 for vid, _ in fixed_ids]
    for (vid, lineno), index in zip(fixed_ids, fixed, strict=True):
        if index < 0:
            raise error(lineno, f"FIX refers to vertex id {vid}, which no VERTEX line defines")

    vertex_array = np.asarray(vertex_values, dtype=np.float64)
    width = _FIELD_COUNTS["EDGE_SE3:QUAT" if dimension == 3 else "EDGE_SE2"] - 2
    edge_array = np.asarray(edge_values, dtype=np.float64).reshape(len(edge_values), width)
    largest = torch.finfo(dtype).max
    for array, lines in ((vertex_array, vertex_lines), (edge_array, edge_lines)):
        too_large = np.abs(array) > largest
        if too_large.any():
            row, column = np.argwhere(too_large)[0]
            raise error(
                lines[row],
                f"value {float(array[row, column])!r} overflows {dtype} (largest {largest:.4g}); "
                "read with dtype=torch.float64",
            )
    vertex_array = vertex_array[order]
    size = 6 if dimension == 3 else 3
    bad = _not_semidefinite(
        _symmetric_from_upper(edge_array[:, width - size * (size + 1) // 2 :], size)
    )
    if bad is not None:
        raise error(edge_lines[bad], "the information matrix is not positive semidefinite")
    if dimension == 3:
        poses = _poses_3d(vertex_array)
        measurements = _poses_3d(edge_array[:, :7])
        information = _information_3d(edge_array[:, 7:])
    else:
        poses = _poses_2d(vertex_array)
        measurements = _poses_2d(edge_array[:, :3])
        information = _information_2d(edge_array[:, 3:])

    def tensor(a: np.ndarray) -> Tensor:
        return torch.from_numpy(np.ascontiguousarray(a)).to(dtype)

    return PoseGraph(
        ids=torch.tensor(sorted(vertex_ids), dtype=torch.int64),
        poses=tensor(poses),
        edges=torch.from_numpy(edges),
        measurements=tensor(measurements.reshape(-1, 4, 4)),
        information=tensor(information.reshape(-1, 6, 6)),
        dimension=dimension,
        fixed=torch.tensor(sorted(set(fixed)), dtype=torch.int64),
    )


def read_g2o(path: str | os.PathLike[str], *, dtype: torch.dtype = torch.float64) -> PoseGraph:
    """Read a g2o pose-graph file (3D ``SE3:QUAT`` or 2D ``SE2``; see the module docstring).

    Args:
        path: the file.
        dtype: floating dtype of the returned tensors (float64 by default).

    Returns:
        A :class:`PoseGraph`: poses (N, 4, 4) sorted by vertex id, edges (E, 2) as indices,
        measurements Z_ij ≈ T_i⁻¹ T_j (E, 4, 4), information (E, 6, 6) in (ω, v) order.

    Raises:
        ValueError: malformed line or unknown tag, or a file that is not UTF-8 text, naming the
            file and the line number.
        TypeError: ``path`` is not a str / os.PathLike or ``dtype`` not float32/float64.
        OSError: the file cannot be read.
    """
    from torchslam import _checks  # local: keeps this module's imports untouched

    path = _checks.check_path("read_g2o", path, is_file=True)
    _checks.check_float_dtype("read_g2o", dtype)
    lines = _text.decode_lines(Path(path).read_bytes(), path, "read_g2o", "text g2o file")
    return parse_g2o("\n".join(lines), source=path, dtype=dtype)


def _number(x: float) -> str:
    return repr(float(x))


def format_g2o(graph: PoseGraph, poses: Tensor | None = None) -> str:
    """The g2o text of a pose graph (3D or 2D after ``graph.dimension``; module docstring).

    Args:
        graph: the graph; vertex ids, edges, measurements and information come from it.
        poses: vertex poses to write instead of ``graph.poses`` (e.g. a solver's result),
            shape (N, 4, 4).

    Returns:
        The file's text: vertices, then edges, then ``FIX`` lines, one item per line.

    Raises:
        TypeError: ``graph`` is not a :class:`PoseGraph`, ``poses`` not a float tensor.
        ValueError: ``poses`` of another shape than ``graph.poses``, or (when validation is on)
            not finite rigid transforms.
    """
    return _format_g2o("format_g2o", graph, poses)


def _format_g2o(fn: str, graph: PoseGraph, poses: Tensor | None) -> str:
    if not isinstance(graph, PoseGraph):
        raise TypeError(f"{fn}: argument 'graph' must be a PoseGraph, got {describe(graph)}")
    if poses is None:
        poses = graph.poses
    else:
        check_tensor(fn, "poses", poses, (4, 4))
        if tuple(poses.shape) != tuple(graph.poses.shape):
            raise ValueError(
                f"{fn}: argument 'poses' must have shape {tuple(graph.poses.shape)} (one pose "
                f"per vertex of 'graph'), got {tuple(poses.shape)}"
            )
        check_pose_matrix(fn, "poses", poses)
    T = poses.detach().cpu().to(torch.float64)
    Z = graph.measurements.detach().cpu().to(torch.float64)
    information = graph.information.detach().cpu().to(torch.float64).numpy()
    ids = graph.ids.tolist()
    pairs = graph.edges.tolist()
    lines: list[str] = []
    if graph.dimension == 3:
        vertex_rows = _pose_rows_3d(T)
        edge_rows = _pose_rows_3d(Z)
        rows, cols = np.triu_indices(6)
        g2o_information = information[:, np.argsort(_G2O_TO_OURS)][:, :, np.argsort(_G2O_TO_OURS)]
        upper = g2o_information[:, rows, cols].tolist()
        vertex_tag, edge_tag = "VERTEX_SE3:QUAT", "EDGE_SE3:QUAT"
    else:
        vertex_rows = _pose_rows_2d(T)
        edge_rows = _pose_rows_2d(Z)
        rows, cols = np.triu_indices(3)
        planar = information[:, _SE2_TO_OURS][:, :, _SE2_TO_OURS]
        upper = planar[:, rows, cols].tolist()
        vertex_tag, edge_tag = "VERTEX_SE2", "EDGE_SE2"
    for vid, row in zip(ids, vertex_rows, strict=True):
        lines.append(" ".join([vertex_tag, str(vid), *map(_number, row)]))
    for (a, b), row, info in zip(pairs, edge_rows, upper, strict=True):
        lines.append(" ".join([edge_tag, str(ids[a]), str(ids[b]), *map(_number, row + info)]))
    lines.extend(f"FIX {ids[k]}" for k in graph.fixed.tolist())
    return "\n".join(lines) + "\n"


def _pose_rows_3d(T: Tensor) -> list[list[float]]:
    """(K, 4, 4) → rows (x, y, z, qx, qy, qz, qw) with qw ≥ 0."""
    with validation(False):  # the graph's poses, checked when it was built
        q = convert.matrix_to_quaternion(T[:, :3, :3])  # (w, x, y, z)
    return torch.cat((T[:, :3, 3], q[:, 1:], q[:, :1]), dim=-1).tolist()


def _pose_rows_2d(T: Tensor) -> list[list[float]]:
    """(K, 4, 4) → rows (x, y, θ), θ = atan2(R₁₀, R₀₀) ∈ (−π, π]; out-of-plane parts dropped."""
    theta = torch.atan2(T[:, 1, 0], T[:, 0, 0])
    return torch.cat((T[:, :2, 3], theta[:, None]), dim=-1).tolist()


def write_g2o(path: str | os.PathLike[str], graph: PoseGraph, poses: Tensor | None = None) -> None:
    """Write a pose graph as a g2o file (the text of :func:`format_g2o`).

    Args:
        path: the file to create or overwrite.
        graph: the graph to write.
        poses: vertex poses to write instead of ``graph.poses``, shape (N, 4, 4).

    Raises:
        TypeError, ValueError: as :func:`format_g2o` (naming ``write_g2o``), or a ``path``
            that is not a str or path-like; nothing is written then.
        OSError: the file cannot be written.
    """
    fn = "write_g2o"
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"{fn}: argument 'path' must be a str or os.PathLike, got {describe(path)}")
    text = _format_g2o(fn, graph, poses)
    Path(path).write_text(text)
