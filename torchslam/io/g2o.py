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

Edge-only files
---------------
Several standard 2D benchmarks ship only EDGE lines. A file with edges and no VERTEX line is
read as follows: the vertices are the ids the edges name (sorted), and the initial poses
chain the measurements along a spanning tree of the edges, grown breadth-first from the
smallest id (at the identity) taking odometry edges (consecutive vertices, either direction)
before any loop closure, so a complete odometry chain is followed as recorded
(:func:`torchslam.posegraph.initialization.spanning_tree_poses`). A solver's initializer
(chordal, by default, in ``torchslam posegraph``) then starts from there; ``graph.source``
(:class:`torchslam.posegraph.GraphSource`) has ``has_vertices=False``. When the edges do not
connect every vertex to the smallest id, reading fails with a ValueError naming an unreachable
vertex: no chain of measurements places it, and the cost would not fix its relative pose.
A file with some VERTEX lines keeps the rule below: every edge must name defined vertices.

Information matrices that are not positive semidefinite
-------------------------------------------------------
Some real datasets store 6 × 6 information matrices that are indefinite although both diagonal
blocks (translation, rotation) are positive definite: the cross blocks look misplaced. The
``information`` argument of :func:`read_g2o` / :func:`parse_g2o` (``--information`` on the
command line) chooses what happens to the edges whose matrix fails the positive-semidefinite
test below:

- ``"repair"`` (the default): keep the translation and rotation blocks, set the cross blocks to
  zero (2D: keep the (x, y) block and I_θθ). That is exactly what SE-Sync uses (its weights
  τ, κ are computed from the diagonal blocks alone), so the SE-Sync objective and its
  certified optimum are the same as SE-Sync's. (GTSAM reads the matrix as it is, but the
  Cholesky factor of its Gaussian noise model of an indefinite matrix fails silently: it
  weighs the edge with another, positive-definite matrix RᵀR ≠ Ω, which depends on the
  order of the entries.) If a diagonal block itself is not positive semidefinite, reading fails
  (file and line).
- ``"nearest"``: the nearest symmetric matrix whose eigenvalues are at least 1e-6 × the largest
  (eigenvalue clipping, Frobenius norm): it keeps as much of the cross terms as possible, but
  changes the diagonal blocks too.
- ``"strict"``: refuse the file: ValueError naming the file and the line of the first such edge.

Untouched edges keep their matrices bit for bit. The adjusted edges and their lines are in
``graph.source.adjusted_edges`` / ``adjusted_lines``, and a UserWarning gives their count.

Other rules
-----------
- Blank lines are skipped, and so is everything from a ``#`` to the end of a line.
- ``FIX id …`` lines record fixed vertices in ``PoseGraph.fixed`` (indices, not ids).
- Tags in :data:`SKIPPED_TAGS` (parameter blocks, which only landmark edges use) are skipped.
  Every other tag (landmarks included) is an unknown tag and raises ValueError, as do a wrong
  number of fields, a non-numeric or non-finite number (``nan``, ``inf``, ``1e999``), an id
  that is not a decimal integer in [0, 2⁶³ − 1], a duplicate vertex id, an edge to a missing
  vertex (in a file with VERTEX lines), an information matrix that is not positive
  semidefinite (under ``information="strict"``; above), 2D and 3D lines in the same file, and
  (for :func:`read_g2o`) bytes that are not UTF-8 text. Every message names the file and the
  line number.
- Speed: well-formed files are parsed in bulk, per tag, with NumPy; any irregular line sends
  the file to a line-by-line parser that accepts the same files with the same numbers and
  produces the messages above.
- Vertices are sorted by id (``PoseGraph.ids``); edges keep the file's order.
- Numbers are written with ``repr`` (the shortest decimal that reads back to the same float64),
  so write → read reproduces the graph to round-off (the quaternion ↔ matrix conversions are the
  only inexact steps, about 1e-16).
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchslam._checks import check_pose_matrix, check_tensor, describe, validation
from torchslam.io import _text
from torchslam.lie import convert
from torchslam.posegraph.graph import GraphSource, PoseGraph

__all__ = [
    "INFORMATION_HANDLINGS",
    "SKIPPED_TAGS",
    "format_g2o",
    "parse_g2o",
    "read_g2o",
    "write_g2o",
]

# Handlings of information matrices that are not positive semidefinite (module docstring).
INFORMATION_HANDLINGS = ("repair", "nearest", "strict")

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
# information="nearest" raises every eigenvalue to at least this multiple of the largest:
# positive definite, and well enough conditioned (≤ 1e6) for a Cholesky factorization even in
# float32.
_NEAREST_FLOOR = 1e-6


def _int(token: str) -> int:
    return _text.parse_integer(token, 0, _MAX_ID, "an integer vertex id")


def _floats(tokens: Iterable[str]) -> list[float]:
    return [_text.parse_finite_float(token) for token in tokens]


# A quaternion whose norm is farther than this from 1 was not written as a unit quaternion
# (files written with 6 significant digits are within ~1e-6): reading it warns.
QUATERNION_NORM_TOLERANCE = 1e-3


def _normalize_quaternions(values: np.ndarray, start: int) -> np.ndarray:
    """Normalize the (K, 4) quaternions at columns ``start:start + 4`` in place, robustly:
    divided by their largest magnitude first (module docstring; none is zero). Returns the
    rows whose norm was not 1 within ``QUATERNION_NORM_TOLERANCE``."""
    q = values[:, start : start + 4]
    largest = np.abs(q).max(axis=1, keepdims=True)
    q /= largest
    norm = np.sqrt(np.square(q).sum(axis=1, keepdims=True))
    q /= norm
    with np.errstate(over="ignore"):
        given = (largest * norm)[:, 0]
    return np.flatnonzero(~(np.abs(given - 1.0) <= QUATERNION_NORM_TOLERANCE))


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


def _not_semidefinite(matrices: np.ndarray) -> np.ndarray:
    """Boolean mask (E,) of the (E, n, n) symmetric matrices that are not PSD (tolerance above)."""
    if matrices.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    # Scale each matrix by its largest entry first: eigvalsh of entries near 1e300 overflows.
    scale = np.abs(matrices).max(axis=(-2, -1), keepdims=True)
    eigenvalues = np.linalg.eigvalsh(matrices / np.where(scale > 0, scale, 1.0))
    return eigenvalues[:, 0] < -_PSD_TOLERANCE * np.abs(eigenvalues).max(-1)


def _clip_eigenvalues(matrices: np.ndarray) -> np.ndarray:
    """The matrices with their eigenvalues raised to at least _NEAREST_FLOOR × the largest
    magnitude (information="nearest"); scaled first like :func:`_not_semidefinite`."""
    scale = np.abs(matrices).max(axis=(-2, -1), keepdims=True)
    scale = np.where(scale > 0, scale, 1.0)
    eigenvalues, vectors = np.linalg.eigh(matrices / scale)
    floor = _NEAREST_FLOOR * np.abs(eigenvalues).max(-1, keepdims=True)
    clipped = np.maximum(eigenvalues, floor)
    out = (vectors * clipped[:, None, :]) @ vectors.transpose(0, 2, 1)
    return 0.5 * (out + out.transpose(0, 2, 1)) * scale


def _information_3d(full: np.ndarray) -> np.ndarray:
    """(E, 6, 6) in g2o's [translation, rotation] order → ours, (ω, v)."""
    return full[:, _G2O_TO_OURS][:, :, _G2O_TO_OURS]


def _information_2d(planar: np.ndarray) -> np.ndarray:
    """(E, 3, 3) over (x, y, θ) → the lifted (E, 6, 6) in (ω, v) order (module docstring)."""
    full = np.zeros((planar.shape[0], 6, 6))
    full[:, np.array(_SE2_TO_OURS)[:, None], np.array(_SE2_TO_OURS)[None, :]] = planar
    # Out-of-plane weights (module docstring): ω_x, ω_y like θ, v_z like the mean of x and y.
    full[:, 0, 0] = full[:, 1, 1] = planar[:, 2, 2]
    full[:, 5, 5] = 0.5 * (planar[:, 0, 0] + planar[:, 1, 1])
    return full


@dataclass
class _Scan:
    """The lines of a file, checked one by one, before the graph-level checks.

    Quaternions are as written (not yet normalized, none zero); ids are Python ints in
    [0, 2⁶³ − 1]; ``*_lines`` are the file's line numbers of the rows.
    """

    dimension: int = 0
    vertex_ids: list[int] = field(default_factory=list)
    vertex_values: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    vertex_lines: list[int] = field(default_factory=list)
    edge_ids: list[tuple[int, int]] = field(default_factory=list)
    edge_values: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    edge_lines: list[int] = field(default_factory=list)
    fixed_ids: list[tuple[int, int]] = field(default_factory=list)  # (id, line number)


def _width(dimension: int, kind: str) -> int:
    """Number of float fields of a vertex or edge line (after the tag and the ids)."""
    tag = {(3, "vertex"): "VERTEX_SE3:QUAT", (3, "edge"): "EDGE_SE3:QUAT"}.get(
        (dimension, kind), "VERTEX_SE2" if kind == "vertex" else "EDGE_SE2"
    )
    return _FIELD_COUNTS[tag] - (1 if kind == "vertex" else 2)


def _scan_lines(lines: list[str], error: Callable[[int, str], ValueError]) -> _Scan:
    """Check the lines one by one in file order; the first bad line raises (line number)."""
    scan = _Scan()
    vertex_values: list[list[float]] = []
    edge_values: list[list[float]] = []
    dimension_line = 0
    for lineno, raw in enumerate(lines, start=1):
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
                scan.fixed_ids.extend((_int(f), lineno) for f in fields)
                continue
            if tag not in _FIELD_COUNTS:
                known = ", ".join([*_FIELD_COUNTS, "FIX", *sorted(SKIPPED_TAGS)])
                raise _LineError(f"unknown tag {tag!r} (known tags: {known})")
            if len(fields) != _FIELD_COUNTS[tag]:
                raise _LineError(
                    f"{tag} expects {_FIELD_COUNTS[tag]} fields after the tag, got {len(fields)}"
                )
            if scan.dimension == 0:
                scan.dimension, dimension_line = _DIMENSION[tag], lineno
            elif _DIMENSION[tag] != scan.dimension:
                raise _LineError(
                    f"{tag} is a {_DIMENSION[tag]}D tag but line {dimension_line} made this a "
                    f"{scan.dimension}D graph; mixed 2D/3D files are not supported"
                )
            if tag.startswith("VERTEX"):
                vid = _int(fields[0])
                values = _floats(fields[1:])
                if tag == "VERTEX_SE3:QUAT":
                    _text.unit_quaternion(values[3:7], "quaternion (qx, qy, qz, qw)")
                scan.vertex_ids.append(vid)
                vertex_values.append(values)
                scan.vertex_lines.append(lineno)
            else:
                pair = (_int(fields[0]), _int(fields[1]))
                values = _floats(fields[2:])
                if tag == "EDGE_SE3:QUAT":
                    _text.unit_quaternion(values[3:7], "quaternion (dqx, dqy, dqz, dqw)")
                scan.edge_ids.append(pair)
                edge_values.append(values)
                scan.edge_lines.append(lineno)
        except _LineError as exc:
            raise error(lineno, str(exc)) from None
    dimension = scan.dimension or 3
    scan.vertex_values = np.asarray(vertex_values, dtype=np.float64).reshape(
        len(vertex_values), _width(dimension, "vertex")
    )
    scan.edge_values = np.asarray(edge_values, dtype=np.float64).reshape(
        len(edge_values), _width(dimension, "edge")
    )
    return scan


class _Unsure(Exception):
    """The fast scan cannot vouch for the file; :func:`_scan_lines` decides (and explains)."""


# Characters of the numeric fields the fast scan accepts: ASCII digits, the characters of a
# decimal literal, and blanks. With these, numpy's float parsing (correctly rounded like
# float()) accepts exactly the literals of _text.parse_finite_float; letters (nan, inf),
# underscores and non-ASCII digits send the file to the line-by-line scan.
_NUMERIC_CHARACTERS = str.maketrans("", "", "0123456789+-.eE \t\n")


def _scan_fast(lines: list[str]) -> _Scan:
    """The result of :func:`_scan_lines` on a well-formed file, in bulk (per tag, NumPy).

    Raises:
        _Unsure: for anything unusual (a bad number, a wrong field count, an unknown tag, mixed
            dimensions, a zero quaternion, …); the caller reruns the line-by-line scan, which
            raises the precise error, so both scans accept the same files with the same result.
    """
    groups: dict[str, tuple[list[int], list[str]]] = {}
    for lineno, raw in enumerate(lines, start=1):
        if "#" in raw:
            raw = raw[: raw.index("#")]
        parts = raw.split(None, 1)
        if not parts:
            continue
        group = groups.get(parts[0])
        if group is None:
            group = groups[parts[0]] = ([], [])
        group[0].append(lineno)
        group[1].append(parts[1] if len(parts) > 1 else "")
    scan = _Scan()
    dimensions = {_DIMENSION[tag] for tag in groups if tag in _DIMENSION}
    if len(dimensions) > 1 or any(
        tag not in _FIELD_COUNTS and tag not in SKIPPED_TAGS and tag != "FIX" for tag in groups
    ):
        raise _Unsure
    scan.dimension = dimensions.pop() if dimensions else 0
    for lineno, rest in zip(*groups.get("FIX", ([], [])), strict=True):
        try:
            scan.fixed_ids.extend((_int(f), lineno) for f in rest.split() or [""])
        except _LineError:
            raise _Unsure from None
    dimension = scan.dimension or 3
    for kind, tag in (
        ("vertex", "VERTEX_SE3:QUAT" if dimension == 3 else "VERTEX_SE2"),
        ("edge", "EDGE_SE3:QUAT" if dimension == 3 else "EDGE_SE2"),
    ):
        line_numbers, rests = groups.get(tag, ([], []))
        count = len(rests)
        width = _width(dimension, kind)
        id_count = _FIELD_COUNTS[tag] - width
        values = np.zeros((0, _FIELD_COUNTS[tag]))
        if count:
            if "\n".join(rests).translate(_NUMERIC_CHARACTERS):
                raise _Unsure
            try:
                values = np.loadtxt(rests, dtype=np.float64, ndmin=2)
                ids = [rest.split(None, id_count)[:id_count] for rest in rests]
                ids = [[int(token) for token in row] for row in ids]
            except ValueError:
                raise _Unsure from None
            if values.shape != (count, _FIELD_COUNTS[tag]) or not np.isfinite(values).all():
                raise _Unsure
            low = min(min(row) for row in ids)
            high = max(max(row) for row in ids)
            if low < 0 or high > _MAX_ID:
                raise _Unsure
            if dimension == 3:
                quaternion = values[:, id_count + 3 : id_count + 7]
                if not (quaternion != 0).any(axis=1).all():
                    raise _Unsure
        else:
            ids = []
        floats = np.ascontiguousarray(values[:, id_count:])
        if kind == "vertex":
            scan.vertex_ids = [row[0] for row in ids]
            scan.vertex_values, scan.vertex_lines = floats, line_numbers
        else:
            scan.edge_ids = [(row[0], row[1]) for row in ids]
            scan.edge_values, scan.edge_lines = floats, line_numbers
    return scan


def _adjust_information(
    full: np.ndarray,
    handling: str,
    lines: list[int],
    error: Callable[[int, str], ValueError],
) -> tuple[np.ndarray, np.ndarray]:
    """Apply the ``information`` handling to the (E, n, n) matrices in the file's order.

    Returns the matrices (a copy where some changed) and the indices of the changed edges.
    """
    bad = np.flatnonzero(_not_semidefinite(full))
    if bad.size == 0:
        return full, bad
    first = lines[int(bad[0])]
    if handling == "strict":
        raise error(
            first,
            f"the information matrix is not positive semidefinite (information='strict'; "
            f"{bad.size} of {full.shape[0]} edges are not; the default information='repair' "
            "keeps their diagonal blocks)",
        )
    full = full.copy()
    if handling == "nearest":
        full[bad] = _clip_eigenvalues(full[bad])
        return full, bad
    # "repair": keep the translation and rotation blocks, drop the cross blocks.
    split = full.shape[-1] // 2 if full.shape[-1] == 6 else 2
    repaired = full[bad]
    repaired[:, :split, split:] = 0.0
    repaired[:, split:, :split] = 0.0
    still = _not_semidefinite(repaired)
    if still.any():
        raise error(
            lines[int(bad[np.argmax(still)])],
            "the information matrix is not positive semidefinite, nor is its translation or "
            "rotation block, which information='repair' keeps (information='nearest' clips "
            "the eigenvalues instead)",
        )
    full[bad] = repaired
    return full, bad


def parse_g2o(
    text: str,
    *,
    source: str = "<string>",
    dtype: torch.dtype = torch.float64,
    information: str = "repair",
) -> PoseGraph:
    """Parse the text of a g2o pose-graph file (rules and conventions: module docstring).

    Args:
        text: the file's contents.
        source: the name used in error messages (the file's path for :func:`read_g2o`).
        dtype: floating dtype of the returned tensors (float64 by default).
        information: the handling of information matrices that are not positive
            semidefinite: "repair" (the default), "nearest" or "strict" (module docstring).

    Returns:
        A :class:`PoseGraph` with N vertices sorted by id and E edges in file order:
        poses (N, 4, 4), edges (E, 2) as indices, measurements Z_ij ≈ T_i⁻¹ T_j (E, 4, 4),
        information (E, 6, 6) in (ω, v) order, and ``source``, a :class:`GraphSource` saying
        whether the file had VERTEX lines and whose information matrices were adjusted.

    Raises:
        ValueError: for a malformed line, an unknown tag, an inconsistent graph; the message
            names ``source`` and the line number (module docstring, "Other rules"), or a value
            that overflows ``dtype``; an unknown ``information`` handling.
        TypeError: ``text`` or ``source`` is not a str, ``dtype`` not float32/float64.
    """
    from torchslam import _checks  # local: keeps this module's imports untouched

    for name, value in (("text", text), ("source", source)):
        if not isinstance(value, str):
            raise TypeError(
                f"parse_g2o: argument '{name}' must be a str, got {_checks.describe(value)}"
            )
    _check_options("parse_g2o", dtype, information)
    return _parse_lines(text.split("\n"), source, dtype, information)


def _check_options(fn: str, dtype: torch.dtype, information: object) -> None:
    from torchslam import _checks

    _checks.check_float_dtype(fn, dtype)
    if not isinstance(information, str):
        raise TypeError(
            f"{fn}: argument 'information' must be a str, one of {INFORMATION_HANDLINGS}; got "
            f"{_checks.describe(information)}"
        )
    if information not in INFORMATION_HANDLINGS:
        raise ValueError(
            f"{fn}: argument 'information' must be one of {INFORMATION_HANDLINGS}, got "
            f"{information!r}"
        )


def _parse_lines(lines: list[str], source: str, dtype: torch.dtype, information: str) -> PoseGraph:
    """The graph of a file's lines (split at "\\n" only: str.splitlines also splits at form
    feeds etc., shifting the line numbers)."""

    def error(lineno: int, message: str) -> ValueError:
        return ValueError(f"parse_g2o: {source}, line {lineno}: {message}")

    try:
        scan = _scan_fast(lines)
    except _Unsure:
        scan = _scan_lines(lines, error)
    dimension = scan.dimension
    has_vertices = bool(scan.vertex_ids)
    if not has_vertices and not scan.edge_ids:
        raise ValueError(
            f"parse_g2o: {source}: no vertices (no VERTEX_SE3:QUAT or VERTEX_SE2 line) and no edges"
        )
    if has_vertices:
        ids, index_of = _vertex_index(scan, error)
    else:  # edge-only: the vertices are the ids the edges name
        ids = sorted({vid for pair in scan.edge_ids for vid in pair})
        index_of = {vid: index for index, vid in enumerate(ids)}
    defined_by = "VERTEX line defines" if has_vertices else "edge names (edge-only file)"
    edge_ids = np.array(scan.edge_ids, dtype=np.int64).reshape(-1, 2)
    sorted_ids = np.array(ids, dtype=np.int64)
    edges = np.searchsorted(sorted_ids, edge_ids).clip(max=len(ids) - 1)
    missing = sorted_ids[edges] != edge_ids
    if missing.any():
        e, k = np.argwhere(missing)[0]  # the first in file order
        raise error(
            scan.edge_lines[e], f"edge refers to vertex id {edge_ids[e, k]}, which no {defined_by}"
        )
    fixed = []
    for vid, lineno in scan.fixed_ids:
        if vid not in index_of:
            raise error(lineno, f"FIX refers to vertex id {vid}, which no {defined_by}")
        fixed.append(index_of[vid])

    vertex_array, edge_array = scan.vertex_values, scan.edge_values
    if dimension == 3:
        for array, lines_of, what in (
            (vertex_array, scan.vertex_lines, "vertices"),
            (edge_array, scan.edge_lines, "edges"),
        ):
            off = _normalize_quaternions(array, 3)
            if off.size:
                warnings.warn(
                    f"parse_g2o: {source}: {off.size} of {len(lines_of)} {what} have a "
                    f"quaternion whose norm is not 1 (the first on line {lines_of[int(off[0])]}"
                    "); normalized, as g2o does. Check that the file holds (qx, qy, qz, qw)",
                    UserWarning,
                    stacklevel=3,
                )
    largest = torch.finfo(dtype).max
    for array, lines_of in ((vertex_array, scan.vertex_lines), (edge_array, scan.edge_lines)):
        too_large = np.abs(array) > largest
        if too_large.any():
            row, column = np.argwhere(too_large)[0]
            raise error(
                lines_of[row],
                f"value {float(array[row, column])!r} overflows {dtype} (largest {largest:.4g}); "
                "read with dtype=torch.float64",
            )
    size = 6 if dimension == 3 else 3
    width = edge_array.shape[1]
    full, adjusted = _adjust_information(
        _symmetric_from_upper(edge_array[:, width - size * (size + 1) // 2 :], size),
        information,
        scan.edge_lines,
        error,
    )
    if dimension == 3:
        measurements = _poses_3d(edge_array[:, :7])
        information_ours = _information_3d(full)
    else:
        measurements = _poses_2d(edge_array[:, :3])
        information_ours = _information_2d(full)
    if has_vertices:
        poses = (_poses_3d if dimension == 3 else _poses_2d)(vertex_array)
    else:
        poses = _spanning_tree(len(ids), edges, measurements, ids, source)

    if adjusted.size:
        what = {
            "repair": "kept their translation and rotation blocks, dropped the cross blocks",
            "nearest": "replaced them by the nearest positive-definite matrices",
        }[information]
        warnings.warn(
            f"parse_g2o: {source}: {adjusted.size} of {len(scan.edge_lines)} edges have an "
            f"information matrix that is not positive semidefinite (the first on line "
            f"{scan.edge_lines[int(adjusted[0])]}); information={information!r} {what} "
            "(graph.source.adjusted_edges lists them; information='strict' refuses the file)",
            UserWarning,
            stacklevel=3,
        )

    def tensor(a: np.ndarray) -> Tensor:
        return torch.from_numpy(np.ascontiguousarray(a)).to(dtype)

    return PoseGraph(
        ids=torch.tensor(ids, dtype=torch.int64),
        poses=tensor(poses),
        edges=torch.from_numpy(edges),
        measurements=tensor(measurements.reshape(-1, 4, 4)),
        information=tensor(information_ours.reshape(-1, 6, 6)),
        dimension=dimension or 3,
        fixed=torch.tensor(sorted(set(fixed)), dtype=torch.int64),
        source=GraphSource(
            path=source,
            has_vertices=has_vertices,
            information=information,
            adjusted_edges=tuple(adjusted.tolist()),
            adjusted_lines=tuple(scan.edge_lines[e] for e in adjusted.tolist()),
        ),
    )


def _vertex_index(
    scan: _Scan, error: Callable[[int, str], ValueError]
) -> tuple[list[int], dict[int, int]]:
    """Sorted vertex ids, the index of each id, and the rows of ``scan.vertex_values`` sorted
    by id (in place); a duplicate id raises (its line and the first definition's)."""
    first_line: dict[int, int] = {}
    for vid, lineno in zip(scan.vertex_ids, scan.vertex_lines, strict=True):
        if vid in first_line:
            raise error(
                lineno, f"duplicate vertex id {vid} (first defined on line {first_line[vid]})"
            )
        first_line[vid] = lineno
    order = sorted(range(len(scan.vertex_ids)), key=scan.vertex_ids.__getitem__)
    ids = [scan.vertex_ids[k] for k in order]
    scan.vertex_values = scan.vertex_values[order]
    return ids, {vid: index for index, vid in enumerate(ids)}


def _spanning_tree(
    n: int, edges: np.ndarray, measurements: np.ndarray, ids: list[int], source: str
) -> np.ndarray:
    """Poses of an edge-only file: the measurements chained along a spanning tree from the
    smallest id (at the identity), odometry edges first (module docstring)."""
    from torchslam.posegraph.initialization import spanning_tree_poses  # SciPy: only here

    poses, unreachable = spanning_tree_poses(n, edges, measurements, np.eye(4))
    if unreachable is not None:
        raise ValueError(
            f"parse_g2o: {source}: edge-only file (no VERTEX lines): vertex id "
            f"{ids[unreachable]} is not connected to vertex id {ids[0]} by the edges, so no "
            "initial guess can be chained to it (add VERTEX lines, or keep the connected "
            "component of the first vertex)"
        )
    return poses


def read_g2o(
    path: str | os.PathLike[str],
    *,
    dtype: torch.dtype = torch.float64,
    information: str = "repair",
) -> PoseGraph:
    """Read a g2o pose-graph file (3D ``SE3:QUAT`` or 2D ``SE2``; see the module docstring).

    Args:
        path: the file.
        dtype: floating dtype of the returned tensors (float64 by default).
        information: the handling of information matrices that are not positive
            semidefinite: "repair" (the default: keep their translation and rotation blocks,
            drop the cross blocks), "nearest" (clip their eigenvalues) or "strict" (refuse).
            The adjusted edges are in ``graph.source.adjusted_edges``.

    Returns:
        A :class:`PoseGraph`: poses (N, 4, 4) sorted by vertex id, edges (E, 2) as indices,
        measurements Z_ij ≈ T_i⁻¹ T_j (E, 4, 4), information (E, 6, 6) in (ω, v) order, and
        ``source`` (:class:`GraphSource`). An edge-only file's poses chain the measurements
        along a spanning tree of the edges (module docstring).

    Raises:
        ValueError: malformed line or unknown tag, or a file that is not UTF-8 text, naming the
            file and the line number; an edge-only file whose edges do not connect the graph;
            an unknown ``information`` handling.
        TypeError: ``path`` is not a str / os.PathLike or ``dtype`` not float32/float64.
        OSError: the file cannot be read.
    """
    from torchslam import _checks  # local: keeps this module's imports untouched

    path = _checks.check_path("read_g2o", path, is_file=True)
    _check_options("read_g2o", dtype, information)
    lines = _text.decode_lines(Path(path).read_bytes(), path, "read_g2o", "text g2o file")
    return _parse_lines(lines, str(path), dtype, information)


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
