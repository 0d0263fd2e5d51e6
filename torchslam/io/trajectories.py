"""Trajectory files: the pose file of ``torchslam register`` (:func:`write_poses`), and the
TUM and KITTI trajectory formats that evo (``evo_traj``, ``evo_ape``) and most SLAM tools read
(:func:`write_trajectory`, :func:`read_trajectory`).

Every format holds the same poses T_0i (frame i → world/reference frame, p_world = R p_i + t;
the solver's :class:`~torchslam.PointMapProblem` poses are their inverses T_i0) and states its
convention in its header (comment lines starting with ``#``, which evo skips):

- ``torchslam``: ``name tx ty tz qw qx qy qz`` (below);
- ``tum``: ``timestamp tx ty tz qx qy qz qw`` (TUM RGB-D: quaternion scalar *last*); scans
  without times get their index 0, 1, 2, … as timestamp, the names go in the header;
- ``kitti``: 12 numbers, the first three rows of T_0i row-major (KITTI odometry: the pose of
  camera i in the frame of camera 0).

Pose convention: each line holds T_0i, the pose of frame (scan) i in the world frame, i.e. the
frame → world transform T_0i = [[R(q), t], [0, 1]] that maps the scan's coordinates into the
frame of the reference scan (the first scan unless chosen otherwise): p_ref = R(q) p_scan + t.
(The solver's poses are the inverses, T_i0 = T_0i⁻¹, world → frame.)

Format: one line per scan, in input order::

    name tx ty tz qw qx qy qz

q is a unit Hamilton quaternion written scalar first; t in the scans' units. Lines starting
with ``#`` are comments (the writer puts two header comments naming the format and the
reference frame). Names are single words without white space.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchslam import _checks
from torchslam.io import _text
from torchslam.lie import convert, se3

__all__ = ["FORMATS", "read_poses", "read_trajectory", "write_poses", "write_trajectory"]

# Trajectory formats of write_trajectory / read_trajectory (and of ``torchslam register --format``)
FORMATS = ("torchslam", "tum", "kitti")


def write_poses(
    path: str | os.PathLike, names: Sequence[str], poses: Tensor, *, frame: str | None = None
) -> None:
    """Write poses T_0i (frame i → world/reference frame) in the format of the module docstring.

    Args:
        path: output file.
        names: scan names, m of them (no white space).
        poses: T_0i mapping each scan into the reference frame, shape (m, 4, 4).
        frame: name of the reference scan, for the header comment.

    Raises:
        TypeError: a wrong type (``names`` must be a sequence of str, ``poses`` a float tensor
            or numpy array).
        ValueError: names that are empty, hold white space, start with ``#`` (a comment line
            on reading) or repeat; ``poses`` of the wrong shape, non-finite or not rigid.
    """
    fn = "write_poses"
    path = _checks.check_path(fn, path)
    names = _checks.check_names(fn, names)
    if not names:
        raise ValueError(f"{fn}: argument 'names' must hold at least one name, got none")
    if isinstance(poses, np.ndarray):
        poses = torch.from_numpy(poses)
    _checks.check_batched(
        fn, "poses", poses, ("m",), (4, 4), sizes=(len(names),), against="'names'"
    )
    _checks.check_pose_matrix(fn, "poses", poses)
    if frame is not None and (
        not isinstance(frame, str) or not frame or "\n" in frame or "\r" in frame
    ):
        raise ValueError(
            f"write_poses: argument 'frame' must be None or a one-line name, "
            f"got {_checks.describe(frame)}"
        )
    q = convert.matrix_to_quaternion(poses[:, :3, :3].detach().to(torch.float64))
    q = torch.where(q[:, :1] < 0, -q, q)  # qw ≥ 0
    t = poses[:, :3, 3].detach().to(torch.float64)
    lines = [
        "# torchslam register poses: name tx ty tz qw qx qy qz",
        f"# T_0i maps scan coordinates into the frame of {frame or (names[0] if names else '-')}: "
        "p = R(q) p_scan + t (Hamilton quaternion, scalar first)",
    ]
    for name, ti, qi in zip(names, t.tolist(), q.tolist(), strict=True):
        lines.append(" ".join([name, *(repr(float(x)) for x in (*ti, *qi))]))
    Path(path).write_text("\n".join(lines) + "\n")


def read_poses(
    path: str | os.PathLike, *, dtype: torch.dtype = torch.float64
) -> tuple[list[str], Tensor]:
    """Read a pose file of :func:`write_poses`: ``(names, T_0i of shape (m, 4, 4))``.

    Raises:
        ValueError: a malformed line (field count, a number that is not a finite decimal, a
            zero quaternion), a repeated name, no poses, bytes that are not UTF-8 text; the
            message names the file and the line.
        TypeError: ``path`` is not a str / os.PathLike or ``dtype`` not float32/float64.
        OSError: the file cannot be read.
    """
    fn = "read_poses"
    where = _checks.check_path(fn, path, is_file=True)
    _checks.check_float_dtype(fn, dtype)
    largest = torch.finfo(dtype).max
    with open(where, "rb") as f:
        lines = _text.decode_lines(f.read(), path, fn, "text pose file")
    names: list[str] = []
    rows: list[list[float]] = []
    for number, raw in enumerate(lines, start=1):
        words = raw.split()
        if not words or words[0].startswith("#"):
            continue
        if len(words) != 8:
            raise ValueError(
                f"{fn}: {where}: line {number}: expected 'name tx ty tz qw qx qy qz', got "
                f"{len(words)} fields"
            )
        try:
            values = [_text.parse_finite_float(v) for v in words[1:]]
            q = _text.unit_quaternion(values[3:], "quaternion (qw, qx, qy, qz)")
        except _text.TokenError as error:
            raise ValueError(f"{fn}: {where}: line {number}: {error}") from None
        too_large = [v for v in values[:3] if abs(v) > largest]
        if too_large:
            raise ValueError(
                f"{fn}: {where}: line {number}: translation {too_large[0]!r} overflows {dtype} "
                f"(largest {largest:.4g}); read with dtype=torch.float64"
            )
        if words[0] in names:
            raise ValueError(f"{fn}: {where}: line {number}: scan {words[0]!r} listed twice")
        names.append(words[0])
        rows.append([*values[:3], *q])
    if not rows:
        raise ValueError(f"{fn}: {where}: no poses")
    values_t = torch.tensor(rows, dtype=dtype)
    R = convert.quaternion_to_matrix(values_t[:, 3:])
    return names, se3.from_rotation_translation(R, values_t[:, :3])


def _check_format(fn: str, format: object) -> str:
    if not isinstance(format, str) or format not in FORMATS:
        raise ValueError(
            f"{fn}: argument 'format' must be one of {', '.join(map(repr, FORMATS))}, "
            f"got {_checks.describe(format)}"
        )
    return format


def write_trajectory(
    path: str | os.PathLike,
    poses: Tensor,
    format: str = "tum",
    *,
    names: Sequence[str] | None = None,
    timestamps: Sequence[float] | Tensor | np.ndarray | None = None,
    frame: str | None = None,
) -> None:
    """Write poses T_0i (frame i → world) as a trajectory file evo and SLAM tools read.

    Args:
        path: output file.
        poses: T_0i, shape (m, 4, 4), rigid and finite (a tensor or a numpy array).
        format: ``"tum"`` (``timestamp tx ty tz qx qy qz qw``), ``"kitti"`` (3×4 row-major)
            or ``"torchslam"`` (:func:`write_poses`; needs ``names``).
        names: scan names (listed in the header of tum/kitti files; required for torchslam).
        timestamps: m finite times, increasing (tum only; default 0, 1, …, m − 1).
        frame: name of the world/reference frame, for the header.

    The header (``#`` lines) states the convention: which frame maps into which, the
    quaternion order, the units (those of the poses' translations).

    Raises:
        TypeError, ValueError: bad arguments (messages name the argument).
    """
    fn = "write_trajectory"
    path = _checks.check_path(fn, path)
    format = _check_format(fn, format)
    if isinstance(poses, np.ndarray):
        poses = torch.from_numpy(np.ascontiguousarray(poses))
    _checks.check_batched(fn, "poses", poses, ("m",), (4, 4))
    _checks.check_pose_matrix(fn, "poses", poses)
    m = poses.shape[0]
    if m == 0:
        raise ValueError(f"{fn}: argument 'poses' must hold at least one pose, got none")
    if names is not None:
        names = _checks.check_names(fn, names, count=m)
    if format == "torchslam":
        if names is None:
            raise ValueError(f"{fn}: format 'torchslam' needs 'names' (one per pose)")
        write_poses(path, names, poses, frame=frame)
        return
    if timestamps is not None and format != "tum":
        raise ValueError(f"{fn}: 'timestamps' are for format 'tum' only, got format {format!r}")
    if timestamps is None:
        times = [float(k) for k in range(m)]
    else:
        array = np.asarray(
            timestamps.detach().cpu() if isinstance(timestamps, Tensor) else timestamps
        )
        if array.shape != (m,) or array.dtype.kind not in "fiu":
            raise ValueError(
                f"{fn}: argument 'timestamps' must hold {m} numbers (one per pose), got "
                f"shape {array.shape} of {array.dtype}"
            )
        times = [float(t) for t in array]
        if not all(np.isfinite(times)) or any(b <= a for a, b in itertools.pairwise(times)):
            raise ValueError(f"{fn}: argument 'timestamps' must be finite and increasing")
    T = poses.detach().to(torch.float64).cpu()
    reference = frame or (names[0] if names else "frame 0")
    header = [f"# torchslam trajectory, {format.upper()} format"]
    if format == "tum":
        q = convert.matrix_to_quaternion(T[:, :3, :3])
        q = torch.where(q[:, :1] < 0, -q, q)  # qw ≥ 0
        header += [
            "# timestamp tx ty tz qx qy qz qw: pose T_0i of frame i in the world frame "
            f"({reference}), p_world = R(q) p_i + t; Hamilton quaternion, scalar LAST",
        ]
        rows = [
            [t, *T[k, :3, 3].tolist(), *q[k, 1:].tolist(), float(q[k, 0])]
            for k, t in enumerate(times)
        ]
    else:
        header += [
            "# r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz: first three rows of T_0i "
            f"(row-major), frame i → world frame ({reference}), p_world = R p_i + t",
        ]
        rows = [T[k, :3, :].reshape(-1).tolist() for k in range(m)]
    if names is not None:
        header.append("# frames in order: " + " ".join(names))
    lines = [*header, *(" ".join(repr(float(x)) for x in row) for row in rows)]
    Path(path).write_text("\n".join(lines) + "\n")


def read_trajectory(
    path: str | os.PathLike, format: str = "tum", *, dtype: torch.dtype = torch.float64
) -> tuple[Tensor, list[str] | None, Tensor | None]:
    """Read a trajectory file: ``(T_0i (m, 4, 4), names or None, timestamps (m,) float64 or
    None)``.

    ``names`` come from a torchslam file or the ``# frames in order:`` header line of a
    file written by :func:`write_trajectory`; ``timestamps`` from a TUM file. KITTI rotations
    are projected onto SO(3) (files carry ~9 digits); TUM quaternions are normalized.

    Raises:
        ValueError: a malformed line (field count, a number that is not finite, a zero
            quaternion, a KITTI matrix that is not a rotation to 1e-4), no poses; messages
            name the file and the line.
        TypeError, OSError: as :func:`read_poses`.
    """
    fn = "read_trajectory"
    format = _check_format(fn, format)
    if format == "torchslam":
        names, poses = read_poses(path, dtype=dtype)
        return poses, names, None
    where = _checks.check_path(fn, path, is_file=True)
    _checks.check_float_dtype(fn, dtype)
    with open(where, "rb") as f:
        lines = _text.decode_lines(f.read(), path, fn, "text trajectory file")
    width = 8 if format == "tum" else 12
    names: list[str] | None = None
    rows: list[list[float]] = []
    for number, raw in enumerate(lines, start=1):
        words = raw.split()
        if not words:
            continue
        if words[0].startswith("#"):
            text = raw.strip().lstrip("#").strip()
            if text.startswith("frames in order:"):
                names = text[len("frames in order:") :].split()
            continue
        if len(words) != width:
            raise ValueError(
                f"{fn}: {where}: line {number}: expected {width} numbers ({format} format), "
                f"got {len(words)} fields"
            )
        try:
            values = [_text.parse_finite_float(v) for v in words]
            if format == "tum":
                qx, qy, qz, qw = values[4:]
                values[4:] = _text.unit_quaternion([qw, qx, qy, qz], "quaternion (qx qy qz qw)")
        except _text.TokenError as error:
            raise ValueError(f"{fn}: {where}: line {number}: {error}") from None
        if format == "kitti":
            R = np.array(values, dtype=np.float64).reshape(3, 4)[:, :3]
            if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or np.linalg.det(R) < 0:
                raise ValueError(
                    f"{fn}: {where}: line {number}: the 3×3 block is not a rotation matrix"
                )
        rows.append(values)
    if not rows:
        raise ValueError(f"{fn}: {where}: no poses")
    if names is not None and len(names) != len(rows):
        names = None  # a header that does not match the poses is ignored
    table = torch.tensor(rows, dtype=torch.float64)
    if format == "tum":
        R = convert.quaternion_to_matrix(table[:, 4:])  # (w, x, y, z) after the rewrite
        poses = se3.from_rotation_translation(R, table[:, 1:4])
        # Timestamps stay float64 whatever ``dtype``: epoch seconds (~1.7e9) in float32 would
        # round to 128 s.
        return poses.to(dtype), names, table[:, 0]
    M = table.reshape(-1, 3, 4)
    U, _, Vh = torch.linalg.svd(M[:, :, :3])
    R = U @ Vh
    return se3.from_rotation_translation(R, M[:, :, 3]).to(dtype), names, None
