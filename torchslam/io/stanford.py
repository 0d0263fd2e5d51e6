"""Stanford 3D Scanning Repository ``.conf`` alignments (e.g. the bunny's ``bun.conf``).

A ``.conf`` file has one ``bmesh <file> tx ty tz qx qy qz qw`` line per scan (and a ``camera``
line for the viewer, which is ignored). The quaternion is written scalar-last. The rigid map
from scan coordinates into the common frame is (shared/data/README.md, checked numerically)::

    p_common = R(q)ᵀ p_scan + t

with R(q) the Hamilton rotation matrix of q: the *conjugate* rotation, then the translation.
In torchslam's convention this is the pose T = [[R(q)ᵀ, t], [0, 1]] with p' = R p + t; in the
seed's notation it is T_0i, the map from frame i into the common frame 0 (the inverse of the
seed's T_i0). Quaternions are converted explicitly from the file order (x, y, z, w) to
torchslam's (w, x, y, z) and normalized.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

import torch
from torch import Tensor

from torchslam import _checks
from torchslam.io import _text
from torchslam.lie import convert, se3, so3

__all__ = [
    "pose_errors",
    "read_conf",
    "relative_to_first",
    "scan_name",
    "stack",
]


def scan_name(path: str | os.PathLike) -> str:
    """Scan name of a file: its base name without the extension, e.g. ``"bun045"``."""
    path = _checks.check_path("scan_name", path)
    return os.path.splitext(os.path.basename(path))[0]


def read_conf(path: str | os.PathLike, *, dtype: torch.dtype = torch.float64) -> dict[str, Tensor]:
    """Read a Stanford ``.conf`` file into ``{scan name: T}`` in file order.

    Args:
        path: the ``.conf`` file.
        dtype: dtype of the poses, float64 by default.

    Returns:
        Ordered mapping from scan name (``bmesh`` file name without extension, e.g.
        ``"bun045"``) to T of shape (4, 4), the map from that scan's coordinates into the
        common frame: p_common = T[:3, :3] p_scan + T[:3, 3] with T[:3, :3] = R(q)ᵀ.

    Raises:
        ValueError: a malformed line: wrong keyword or field count, a number that is not a
            finite decimal (``nan``, ``inf``), a zero quaternion, a repeated scan, bytes that
            are not UTF-8 text (the message names the file and line); or no ``bmesh`` line.
        TypeError: ``path`` is not a str / os.PathLike or ``dtype`` not float32/float64.
        OSError: the file cannot be read.
    """
    fn = "read_conf"
    where = _checks.check_path(fn, path, is_file=True)
    _checks.check_float_dtype(fn, dtype)
    largest = torch.finfo(dtype).max
    with open(where, "rb") as f:
        lines = _text.decode_lines(f.read(), path, fn, "text .conf file")
    poses: dict[str, Tensor] = {}
    for number, raw in enumerate(lines, start=1):
        words = raw.split()
        if not words or words[0] == "camera" or words[0].startswith("#"):
            continue
        if words[0] != "bmesh":
            raise ValueError(
                f"{fn}: {where}: line {number}: expected 'camera' or 'bmesh', got {words[0][:40]!r}"
            )
        if len(words) != 9:
            raise ValueError(
                f"{fn}: {where}: line {number}: expected 'bmesh <file> tx ty tz qx qy qz qw', "
                f"got {len(words)} fields"
            )
        try:
            values = [_text.parse_finite_float(v) for v in words[2:]]
            # The file's 6 significant digits leave |q| − 1 ~ 1e-6: normalize (robustly).
            qx, qy, qz, qw = _text.unit_quaternion(values[3:], "quaternion")
        except _text.TokenError as error:
            kind = "zero quaternion" if "is zero" in str(error) else "not a number"
            raise ValueError(f"{fn}: {where}: line {number}: {kind}: {error}") from None
        too_large = [v for v in values[:3] if abs(v) > largest]
        if too_large:
            raise ValueError(
                f"{fn}: {where}: line {number}: translation {too_large[0]!r} overflows {dtype} "
                f"(largest {largest:.4g}); read with dtype=torch.float64"
            )
        t = torch.tensor(values[:3], dtype=dtype)
        q_wxyz = torch.tensor([qw, qx, qy, qz], dtype=dtype)  # file order is scalar-last
        R = convert.quaternion_to_matrix(q_wxyz).transpose(-1, -2)  # R(q)ᵀ
        name = scan_name(words[1])
        if name in poses:
            raise ValueError(f"{fn}: {where}: line {number}: scan {name!r} listed twice")
        poses[name] = se3.from_rotation_translation(R, t)
    if not poses:
        raise ValueError(f"{fn}: {where}: no 'bmesh' lines (not a Stanford .conf file?)")
    return poses


def relative_to_first(
    poses: Tensor | Mapping[str, Tensor], first: str | int = 0
) -> Tensor | dict[str, Tensor]:
    """Express poses in the frame of one scan: T_i ↦ T_first⁻¹ T_i.

    If T_i maps scan i into some common frame, the result maps scan i into the frame of scan
    ``first``, whose own pose becomes the identity.

    Args:
        poses: stacked poses of shape (M, 4, 4), or a mapping ``{name: T (4, 4)}``.
        first: index (stacked) or name or index (mapping) of the reference scan.

    Returns:
        The same container type: (M, 4, 4) or ``{name: (4, 4)}`` in the same order.
    """
    fn = "relative_to_first"
    if isinstance(poses, Mapping):
        names = list(poses)
        if not names:
            raise ValueError(f"{fn}: argument 'poses' must hold at least one pose, got none")
        for name in names:
            _checks.check_batched(fn, f"poses[{name!r}]", poses[name], (), (4, 4))
        if isinstance(first, str):
            key = first
        else:
            key = names[_checks.check_int(fn, "first", first, minimum=0, maximum=len(names) - 1)]
        if key not in poses:
            raise ValueError(f"{fn}: argument 'first': scan {key!r} not among {names}")
        reference = se3.inverse(poses[key])
        return {n: se3.compose(reference, T) for n, T in poses.items()}
    _checks.check_tensor(fn, "poses", poses, (4, 4), min_batch_dims=1)
    if isinstance(first, str):
        raise TypeError(
            f"{fn}: argument 'first' must be an int index for stacked poses, got {first!r}"
        )
    index = _checks.check_int(fn, "first", first, minimum=0, maximum=poses.shape[-3] - 1)
    return se3.compose(se3.inverse(poses[..., index, :, :])[..., None, :, :], poses)


def pose_errors(
    estimated: Tensor, reference: Tensor, first: int | None = 0
) -> tuple[Tensor, Tensor]:
    """Rotation and translation errors of estimated poses against reference poses.

    Both sets are first expressed in the frame of scan ``first`` (:func:`relative_to_first`,
    skipped when ``first`` is None), then the error of scan i is E_i = T_ref,i⁻¹ T_est,i:
    its rotation angle (degrees, from so3.log) and the distance ‖t_est,i − t_ref,i‖.

    Args:
        estimated: poses mapping each scan into a common frame, shape (M, 4, 4).
        reference: the same for the reference (e.g. :func:`read_conf`), shape (M, 4, 4).
        first: index of the scan whose frame both are expressed in, or None.

    Returns:
        ``(rotation_deg, translation)``, each of shape (M,); translation in the poses' units.
    """
    fn = "pose_errors"
    _checks.check_tensor(fn, "estimated", estimated, (4, 4), min_batch_dims=1)
    _checks.check_tensor(fn, "reference", reference, (4, 4), min_batch_dims=1)
    _checks.check_same_kind(fn, estimated=estimated, reference=reference)
    if estimated.shape != reference.shape:
        raise ValueError(
            f"{fn}: 'estimated' {tuple(estimated.shape)} and 'reference' "
            f"{tuple(reference.shape)} must have the same shape"
        )
    if first is not None:
        estimated = relative_to_first(estimated, first)
        reference = relative_to_first(reference, first)
    R_error = reference[..., :3, :3].transpose(-1, -2) @ estimated[..., :3, :3]
    rotation_deg = torch.rad2deg(torch.linalg.vector_norm(so3.log(so3.project(R_error)), dim=-1))
    translation = torch.linalg.vector_norm(estimated[..., :3, 3] - reference[..., :3, 3], dim=-1)
    return rotation_deg, translation


def stack(poses: Mapping[str, Tensor], names: Sequence[str]) -> Tensor:
    """Stack ``poses[name]`` for ``names`` into shape (len(names), 4, 4).

    Raises:
        TypeError: ``poses`` is not a mapping of (4, 4) float tensors or ``names`` not a
            sequence of str.
        ValueError: no names, or a name without a pose.
    """
    fn = "stack"
    if not isinstance(poses, Mapping):
        raise TypeError(
            f"{fn}: argument 'poses' must be a mapping name → (4, 4) tensor, "
            f"got {_checks.describe(poses)}"
        )
    names = _checks.check_names(fn, names, words=False)
    if not names:
        raise ValueError(f"{fn}: argument 'names' must hold at least one name, got none")
    missing = [n for n in names if n not in poses]
    if missing:
        raise ValueError(f"{fn}: no pose for scan(s) {missing}; known: {list(poses)}")
    for k, name in enumerate(names):
        _checks.check_batched(fn, f"poses[{name!r}]", poses[name], (), (4, 4))
        if k:
            _checks.check_same_kind(
                fn, **{f"poses[{names[0]!r}]": poses[names[0]], f"poses[{name!r}]": poses[name]}
            )
    return torch.stack([poses[n] for n in names])
