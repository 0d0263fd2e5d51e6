"""Trajectory files: the pose file of ``torchslam register`` (and of :func:`write_poses`).

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

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchslam import _checks
from torchslam.io import _text
from torchslam.lie import convert, se3

__all__ = ["read_poses", "write_poses"]


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
