"""Bundle Adjustment in the Large (BAL) problem files: read and write.

The format (Agarwal et al., grail.cs.washington.edu/projects/bal)::

    <num_cameras> <num_points> <num_observations>
    <camera_index> <point_index> <x> <y>            × num_observations
    <camera value>                                   × 9 · num_cameras
    <point value>                                    × 3 · num_points

A camera is 9 values: the rotation r as an angle-axis vector (3), the translation t (3), the
focal length f and the radial distortion k1, k2: P = R(r) X + t is **world → camera**, and the
projection is :func:`torchslam.cameras.snavely_project` (the camera looks down −z, pixels from
the image centre, y up). Values may be spread over lines in any way after the observations;
errors name the file and the line.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchslam import _checks
from torchslam.io import _text
from torchslam.lie import se3, so3

__all__ = ["BALProblem", "read_bal", "write_bal"]


@dataclass
class BALProblem:
    """A BAL problem (module docstring); float64 tensors."""

    # (C, 9): angle-axis r (3), translation t (3), f, k1, k2 of each camera
    cameras: Tensor
    # (P, 3) world points
    points: Tensor
    # (O,) int64 camera and point of each observation
    camera_index: Tensor
    point_index: Tensor
    # (O, 2) observed pixels (origin at the image centre)
    observations: Tensor

    @property
    def poses(self) -> Tensor:
        """T (C, 4, 4) world → camera, from r and t."""
        return se3.from_rotation_translation(so3.exp(self.cameras[:, :3]), self.cameras[:, 3:6])

    @property
    def intrinsics(self) -> Tensor:
        """(f, k1, k2) of each camera, (C, 3)."""
        return self.cameras[:, 6:9]

    def residuals(self) -> Tensor:
        """predicted − observed pixels of every observation, (O, 2)."""
        from torchslam.cameras import snavely_project

        ci, pi = self.camera_index, self.point_index
        return snavely_project(self.poses[ci], self.points[pi], self.intrinsics[ci]) - (
            self.observations
        )

    def cost(self) -> float:
        """½ Σ ‖r‖² (Ceres' cost)."""
        return 0.5 * float(self.residuals().square().sum())


def _problem(
    values: np.ndarray,
    C: int,
    P: int,
    camera_index: np.ndarray,
    point_index: np.ndarray,
    observations: np.ndarray,
) -> BALProblem:
    """The problem of the parsed arrays: ``values`` the 9·C camera then 3·P point values."""
    return BALProblem(
        torch.from_numpy(values[: 9 * C].reshape(C, 9).copy()),
        torch.from_numpy(values[9 * C :].reshape(P, 3).copy()),
        torch.from_numpy(camera_index),
        torch.from_numpy(point_index),
        torch.from_numpy(observations),
    )


def _error(fn: str, path: object, line: int | None, what: str) -> ValueError:
    where = f"{os.fspath(path)}: line {line}: " if line is not None else f"{os.fspath(path)}: "
    return ValueError(f"{fn}: {where}{what}")


def read_bal(path: str | os.PathLike) -> BALProblem:
    """Read a BAL file (module docstring); ``.bz2`` files are decompressed.

    Raises:
        ValueError: a malformed header, observation or value (naming the file and the line),
            an index out of range, too few values (truncated) or values left over.
        TypeError, OSError: as the other readers.
    """
    fn = "read_bal"
    where = _checks.check_path(fn, path, is_file=True)
    if where.endswith(".bz2"):
        import bz2

        with bz2.open(where, "rb") as f:
            data = f.read()
    else:
        with open(where, "rb") as f:
            data = f.read()
    if not data:
        raise _error(fn, where, None, "the file is empty")
    lines = _text.decode_lines(data, where, fn, "text BAL file")
    rows = ((k, line.split()) for k, line in enumerate(lines, start=1))
    rows = ((k, words) for k, words in rows if words)
    try:
        number, header = next(rows)
    except StopIteration:
        raise _error(fn, where, None, "no header line") from None
    if len(header) != 3:
        raise _error(
            fn, where, number, f"expected 'num_cameras num_points num_observations', got "
            f"{len(header)} fields",
        )  # fmt: skip
    try:
        C, P, n_obs = (_text.parse_integer(w, 0, 2**40, "a count") for w in header)
    except _text.TokenError as error:
        raise _error(fn, where, number, str(error)) from None
    fast = _fast_body(lines, number, C, P, n_obs)
    if fast is not None:
        return fast
    camera_index = np.empty(n_obs, dtype=np.int64)
    point_index = np.empty(n_obs, dtype=np.int64)
    observations = np.empty((n_obs, 2), dtype=np.float64)
    for k in range(n_obs):
        try:
            number, words = next(rows)
        except StopIteration:
            raise _error(
                fn, where, None, f"truncated: {k} of {n_obs} observations (the header says {n_obs})"
            ) from None
        if len(words) != 4:
            raise _error(
                fn, where, number, f"expected 'camera_index point_index x y', got "
                f"{len(words)} fields",
            )  # fmt: skip
        try:
            camera_index[k] = _text.parse_integer(words[0], 0, C - 1, f"a camera index < {C}")
            point_index[k] = _text.parse_integer(words[1], 0, P - 1, f"a point index < {P}")
            observations[k] = [_text.parse_finite_float(w) for w in words[2:]]
        except _text.TokenError as error:
            raise _error(fn, where, number, str(error)) from None
    values = np.empty(9 * C + 3 * P, dtype=np.float64)
    filled = 0
    for number, words in rows:
        if filled + len(words) > values.size:
            raise _error(
                fn, where, number, f"values beyond the {9 * C} camera and {3 * P} point values "
                "the header announces",
            )  # fmt: skip
        try:
            values[filled : filled + len(words)] = [_text.parse_finite_float(w) for w in words]
        except _text.TokenError as error:
            raise _error(fn, where, number, str(error)) from None
        filled += len(words)
    if filled < values.size:
        raise _error(
            fn, where, None, f"truncated: {filled} of {values.size} camera and point values"
        )
    return _problem(values, C, P, camera_index, point_index, observations)


_NUMBERS = re.compile(r"(?:\s*" + _text._FLOAT.pattern + r")*\s*")
# one observation line: two indices and two numbers, on one line
_OBSERVATION = r"[ \t]*[0-9]+[ \t]+[0-9]+(?:[ \t]+" + _text._FLOAT.pattern + r"){2}[ \t\r]*"
_INDICES = re.compile(f"(?:{_OBSERVATION}\n)*(?:{_OBSERVATION})?")


def _fast_body(lines: list[str], header_line: int, C: int, P: int, n_obs: int) -> BALProblem | None:
    """The whole body in a few vectorized steps when it is well formed (one regex pass
    validates every token as :mod:`torchslam.io._text` would); None otherwise, and the
    line-by-line reader finds and names the faulty line."""
    body = lines[header_line:]
    observed: list[str] = []
    last = 0
    for last, line in enumerate(body, start=1):
        if len(observed) == n_obs:
            last -= 1
            break
        if line.strip():
            observed.append(line)
    else:
        if len(observed) < n_obs:
            return None
    obs_text = "\n".join(observed)
    rest = "\n".join(body[last:])
    if not (_INDICES.fullmatch(obs_text) and _NUMBERS.fullmatch(rest)):
        return None
    table = np.array(obs_text.split(), dtype=np.float64).reshape(-1, 4) if n_obs else None
    values = np.array(rest.split(), dtype=np.float64)
    if values.size != 9 * C + 3 * P or (n_obs and table.shape[0] != n_obs):
        return None
    if not np.isfinite(values).all() or (n_obs and not np.isfinite(table).all()):
        return None
    if n_obs:
        ci, pi = table[:, 0].astype(np.int64), table[:, 1].astype(np.int64)
        if (ci >= C).any() or (pi >= P).any():
            return None
        observations = table[:, 2:].copy()
    else:
        ci = pi = np.zeros(0, dtype=np.int64)
        observations = np.zeros((0, 2))
    return _problem(values, C, P, ci, pi, observations)


def write_bal(path: str | os.PathLike, problem: BALProblem) -> None:
    """Write ``problem`` as a BAL file (one value a line after the observations, as the
    published files; 17 significant digits, so that :func:`read_bal` reads the same numbers)."""
    fn = "write_bal"
    where = _checks.check_path(fn, path)
    if not isinstance(problem, BALProblem):
        raise TypeError(f"{fn}: argument 'problem' must be a BALProblem, got {type(problem)}")
    cameras = problem.cameras.detach().cpu().to(torch.float64).numpy()
    points = problem.points.detach().cpu().to(torch.float64).numpy()
    ci = problem.camera_index.cpu().numpy()
    pi = problem.point_index.cpu().numpy()
    obs = problem.observations.detach().cpu().to(torch.float64).numpy()
    if cameras.ndim != 2 or cameras.shape[1] != 9 or points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(
            f"{fn}: cameras must be (C, 9) and points (P, 3), got {cameras.shape}, {points.shape}"
        )
    if not (np.isfinite(cameras).all() and np.isfinite(points).all() and np.isfinite(obs).all()):
        raise ValueError(f"{fn}: cameras, points and observations must be finite")
    out = [f"{len(cameras)} {len(points)} {len(ci)}"]
    out += [
        f"{int(c)} {int(p)} {x!r} {y!r}" for c, p, (x, y) in zip(ci, pi, obs.tolist(), strict=True)
    ]
    out += [repr(float(v)) for v in cameras.reshape(-1)]
    out += [repr(float(v)) for v in points.reshape(-1)]
    Path(where).write_text("\n".join(out) + "\n")
