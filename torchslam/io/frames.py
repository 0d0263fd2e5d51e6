"""Range-sensor frames as users have them: depth images, PCD/KITTI/PLY/NPY/XYZ point clouds,
frame folders, timestamps and camera intrinsics.

Conventions (written once):

- **Depth back-projection.** A depth image is indexed ``depth[v, u]`` (v the row, u the
  column, both from the top-left pixel's centre at 0). With z = depth / ``depth_scale`` metres
  and K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], the point in the **camera frame** (x right,
  y down, z forward, the pinhole/OpenCV convention) is ``x = (u − cx)·z/fx``,
  ``y = (v − cy)·z/fy``, ``z``. Invalid depths: 0, 65535 (the "no return" codes of 16-bit
  sensors), non-finite, ≤ 0, outside [min_range, max_range].
- **Point clouds** are (N, 3) float64 tensors in the file's frame and units (metres for the
  sensors here). Non-finite points (missed returns, stored as NaN by many drivers) are dropped
  by default, with a count (``return_dropped=True``); ``nonfinite="raise"`` refuses them.
- **Folders.** Frames sorted by name, numbers compared as numbers (``frame-2`` < ``frame-10``).

Readers raise ``ValueError`` naming the file (and the line, for text files) for bad contents,
``FileNotFoundError`` for a missing file, ``TypeError`` for arguments of the wrong type.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchslam import _checks
from torchslam.io import _text

__all__ = [
    "DEPTH_SUFFIXES",
    "POINT_SUFFIXES",
    "associate_timestamps",
    "check_intrinsics",
    "depth_to_points",
    "find_intrinsics",
    "find_timestamps",
    "list_frames",
    "read_depth",
    "read_intrinsics",
    "read_points",
    "read_reference_poses",
    "read_timestamps",
]

DEPTH_SUFFIXES = (".png", ".tif", ".tiff", ".pgm")
POINT_SUFFIXES = (".pcd", ".bin", ".ply", ".npy", ".xyz", ".txt", ".pts", ".las", ".laz")
# The suffixes a folder of LiDAR frames is scanned for (text files hold timestamps and poses too).
_FOLDER_POINT_SUFFIXES = (".pcd", ".bin", ".ply", ".npy")
_INTRINSICS_NAMES = ("camera-intrinsics.txt", "intrinsics.txt", "K.txt", "camera.txt")
_TIMESTAMP_NAMES = ("times.txt", "timestamps.txt", "depth.txt", "associations.txt", "associate.txt")
_INVALID_DEPTH_CODE = 65535


def _float_array(fn: str, name: str, value: object, expected: str) -> np.ndarray:
    """``value`` (a tensor, array or nested sequence) as a float64 numpy array; TypeError
    naming ``fn``, the argument and ``expected`` when it holds no numbers."""
    if isinstance(value, Tensor):
        return value.detach().cpu().to(torch.float64).numpy()
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(
            f"{fn}: argument '{name}' must be {expected}, got {_checks.describe(value)}"
        ) from None


def _natural_key(path: Path) -> tuple:
    parts = re.split(r"([0-9]+)", path.name)
    # numbers compare as numbers (the ASCII digit runs only); the name breaks ties (a01, a1)
    return (
        [(0, int(t), "") if i % 2 else (1, 0, t.lower()) for i, t in enumerate(parts)],
        path.name,
    )


def _error(fn: str, path: object, what: str) -> ValueError:
    return ValueError(f"{fn}: {os.fspath(path)}: {what}")


# ------------------------------------------------------------------------------- intrinsics


def check_intrinsics(fn: str, intrinsics: object, name: str = "intrinsics") -> Tensor:
    """A pinhole K as a (3, 3) float64 tensor, from a 3 × 3 matrix or (fx, fy, cx, cy).

    Raises ``ValueError`` (naming ``fn`` and the argument) for another shape, non-finite values,
    fx or fy ≤ 0, a bottom row other than (0, 0, 1) or a non-zero K[1, 0]/K[2, :2].
    """
    array = _float_array(fn, name, intrinsics, "a 3×3 K or (fx, fy, cx, cy)")
    if array.shape == (4,):
        fx, fy, cx, cy = array
        array = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    if array.shape != (3, 3):
        raise ValueError(
            f"{fn}: argument '{name}' must be a 3×3 K or (fx, fy, cx, cy), got shape "
            f"{tuple(array.shape)}"
        )
    if not np.isfinite(array).all():
        raise ValueError(f"{fn}: argument '{name}' must be finite, got {array.tolist()}")
    if array[0, 0] <= 0 or array[1, 1] <= 0:
        raise ValueError(
            f"{fn}: argument '{name}' must have fx, fy > 0, got fx={array[0, 0]}, fy={array[1, 1]}"
        )
    if not np.array_equal(array[2], [0.0, 0.0, 1.0]) or array[1, 0] != 0:
        raise ValueError(
            f"{fn}: argument '{name}' must be a pinhole K [[fx, s, cx], [0, fy, cy], [0, 0, 1]], "
            f"got {array.tolist()}"
        )
    return torch.from_numpy(array.copy())


def _numbers(fn: str, path: str | os.PathLike, kind: str) -> list[float]:
    """Every number of a small text file, in order (``#`` comments skipped, commas as spaces);
    errors name the file and the line."""
    with open(path, "rb") as f:
        lines = _text.decode_lines(f.read(), path, fn, kind)
    values: list[float] = []
    for number, raw in enumerate(lines, start=1):
        text = raw.split("#", 1)[0].replace(",", " ")
        try:
            values += [_text.parse_finite_float(t) for t in text.split()]
        except _text.TokenError as error:
            raise _error(fn, path, f"line {number}: {error}") from None
    return values


def read_intrinsics(path: str | os.PathLike) -> Tensor:
    """Read a camera matrix K (3, 3) float64 from a text file: 9 numbers (3 × 3, row-major, as
    7-Scenes' ``camera-intrinsics.txt``) or 4 (fx fy cx cy); ``#`` comments are skipped."""
    fn = "read_intrinsics"
    where = _checks.check_path(fn, path, is_file=True)
    values = _numbers(fn, where, "text intrinsics file")
    if len(values) not in (4, 9):
        raise _error(
            fn, where, f"expected 9 numbers (a 3×3 K) or 4 (fx fy cx cy), got {len(values)}"
        )
    try:
        return check_intrinsics(fn, values if len(values) == 4 else np.reshape(values, (3, 3)))
    except ValueError as error:
        raise _error(fn, where, str(error).split(": ", 1)[1]) from None


def _find(folder: Path, names: Sequence[str]) -> Path | None:
    for base in (folder, folder.parent):
        for name in names:
            if (base / name).is_file():
                return base / name
    return None


def find_intrinsics(folder: str | os.PathLike) -> Path | None:
    """The intrinsics file beside a folder of depth frames (``camera-intrinsics.txt``,
    ``intrinsics.txt``, ``K.txt``, ``camera.txt``, in the folder or its parent), or None."""
    return _find(Path(folder), _INTRINSICS_NAMES)


# ------------------------------------------------------------------------------------ depth


def depth_to_points(
    depth: object,
    intrinsics: object,
    *,
    depth_scale: float = 1000.0,
    min_range: float = 0.0,
    max_range: float = float("inf"),
    stride: int = 1,
) -> Tensor:
    """Back-project a depth image into camera-frame points (module docstring's convention).

    Args:
        depth: (H, W) image (numpy array or tensor; integer or float depth units).
        intrinsics: K (3, 3) or (fx, fy, cx, cy), pixels.
        depth_scale: depth units per metre (1000 for millimetres, as Open3D; TUM uses 5000).
        min_range: valid depths z are at least this, in metres (others dropped).
        max_range: and at most this, in metres.
        stride: use every ``stride``-th row and column (pixel coordinates stay the image's).

    Returns:
        (N, 3) float64 points, in row-major pixel order.
    """
    fn = "depth_to_points"
    K = check_intrinsics(fn, intrinsics).numpy()
    scale = _checks.check_real(fn, "depth_scale", depth_scale, low=0.0, low_open=True)
    low = _checks.check_real(fn, "min_range", min_range, low=0.0)
    high = _checks.check_real(fn, "max_range", max_range, low=0.0, allow_inf=True)
    if not high > low:
        raise ValueError(f"{fn}: 'max_range' must exceed 'min_range', got {high} ≤ {low}")
    stride = _checks.check_int(fn, "stride", stride, minimum=1)
    if isinstance(depth, Tensor):
        depth = depth.detach().cpu().numpy()
    image = np.asarray(depth)
    if image.ndim != 2:
        raise ValueError(
            f"{fn}: argument 'depth' must be a single-channel (H, W) image, got shape "
            f"{tuple(image.shape)}"
        )
    if image.dtype.kind not in "uif":
        raise TypeError(f"{fn}: argument 'depth' must hold numbers, got dtype {image.dtype}")
    v, u = np.mgrid[0 : image.shape[0] : stride, 0 : image.shape[1] : stride]
    raw = image[::stride, ::stride]
    valid = np.isfinite(raw) & (raw > 0)
    if image.dtype.kind == "u" and image.dtype.itemsize == 2:
        valid &= raw != _INVALID_DEPTH_CODE
    z = np.where(valid, raw, 0).astype(np.float64) / scale
    valid &= (z >= low) & (z <= high)
    z, u, v = z[valid], u[valid].astype(np.float64), v[valid].astype(np.float64)
    x = (u - K[0, 2] - K[0, 1] * (v - K[1, 2]) / K[1, 1]) * z / K[0, 0]
    y = (v - K[1, 2]) * z / K[1, 1]
    return torch.from_numpy(np.stack([x, y, z], axis=1))


# Pillow's single-channel modes whose pixels np.asarray returns as they are stored (16-bit,
# 32-bit integer, float, 8-bit): what imageio's Pillow plugin returns for them too.
_RAW_MODES = ("I;16", "I;16B", "I;16L", "I", "F", "L")


def _single_channel_image(where: str) -> np.ndarray | None:
    """The pixels of a one-frame single-channel image that Pillow opens, read directly (a
    millisecond per 640×480 frame less than through imageio's plugin lookup); None for
    anything else (colour, palette, multi-page, a format Pillow does not know), which goes
    through imageio."""
    try:
        from PIL import Image
    except ImportError:  # pragma: no cover - Pillow comes with imageio
        return None
    try:
        with Image.open(where) as image:
            if image.mode not in _RAW_MODES or getattr(image, "n_frames", 1) != 1:
                return None
            return np.asarray(image)
    except Exception:  # Pillow raises many types for a file it cannot decode: imageio says why
        return None


def read_depth(
    path: str | os.PathLike,
    intrinsics: object,
    *,
    depth_scale: float = 1000.0,
    min_range: float = 0.0,
    max_range: float = float("inf"),
    stride: int = 1,
) -> Tensor:
    """Read a depth image (16-bit PNG or anything ``imageio`` reads) as camera-frame points
    (N, 3) float64; arguments as :func:`depth_to_points`. A colour image is refused."""
    fn = "read_depth"
    where = _checks.check_path(fn, path, is_file=True)
    try:
        import imageio.v3 as iio
    except ImportError as error:  # pragma: no cover - imageio is a dependency
        raise ImportError(
            f"{fn}: reading depth images needs imageio (pip install imageio)"
        ) from error
    image = _single_channel_image(where)
    if image is None:
        try:
            image = iio.imread(where)
        except Exception as error:  # imageio raises many types for a file it cannot decode
            raise _error(
                fn, where, f"not a readable image ({type(error).__name__}: {error})"
            ) from None
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.dtype.kind in "iu" and image.size and 0 <= image.min() and image.max() <= 65535:
        # Pillow reads 16-bit PGM (and some TIFF) as int32: keep the 16-bit "no return" code
        image = image.astype(np.uint16)
    if image.ndim != 2:
        raise _error(
            fn, where, f"expected a single-channel depth image, got shape {tuple(image.shape)} "
            "(a colour image?)",
        )  # fmt: skip
    return depth_to_points(
        image, intrinsics, depth_scale=depth_scale, min_range=min_range, max_range=max_range,
        stride=stride,
    )  # fmt: skip


# ----------------------------------------------------------------------------- point clouds


def _text_points(fn: str, where: str) -> np.ndarray:
    """x y z (first three columns; spaces or commas) of a text cloud; ``#``/``//`` comments and
    a leading single-integer count line (the .pts header) are skipped."""
    with open(where, "rb") as f:
        lines = _text.decode_lines(f.read(), where, fn, "text point cloud")
    rows: list[list[float]] = []
    for number, raw in enumerate(lines, start=1):
        text = raw.split("#", 1)[0].split("//", 1)[0].replace(",", " ").split()
        if not text:
            continue
        if not rows and len(text) == 1 and text[0].isdigit():
            continue  # a point count
        if len(text) < 3:
            raise _error(fn, where, f"line {number}: expected x y z, got {len(text)} field(s)")
        row = []
        for token in text[:3]:
            if token.lower().lstrip("+-") in ("nan", "inf", "infinity"):
                row.append(float(token))
                continue
            try:
                row.append(_text.parse_finite_float(token))
            except _text.TokenError as error:
                raise _error(fn, where, f"line {number}: {error}") from None
        rows.append(row)
    return np.array(rows, dtype=np.float64).reshape(-1, 3)


def _pcd_points(fn: str, where: str) -> np.ndarray:
    try:
        from pypcd4 import PointCloud
    except ImportError as error:  # pragma: no cover - pypcd4 is a dependency
        raise ImportError(f"{fn}: reading PCD files needs pypcd4 (pip install pypcd4)") from error
    try:
        cloud = PointCloud.from_path(where)
    except Exception as error:  # pypcd4 raises many types for a malformed file
        raise _error(
            fn, where, f"not a readable PCD file ({type(error).__name__}: {error})"
        ) from None
    missing = [k for k in ("x", "y", "z") if k not in cloud.fields]
    if missing:
        raise _error(fn, where, f"PCD file has no field {', '.join(missing)} (has {cloud.fields})")
    return np.asarray(cloud.numpy(("x", "y", "z")), dtype=np.float64).reshape(-1, 3)


def _ply_points(fn: str, where: str) -> np.ndarray:
    import plyfile

    try:
        data = plyfile.PlyData.read(where)
        vertex = data["vertex"]
        return np.stack([np.asarray(vertex[k], dtype=np.float64) for k in "xyz"], axis=1)
    except Exception as error:  # plyfile raises many types for a malformed file
        raise _error(
            fn, where, f"not a PLY file with vertex x, y, z ({type(error).__name__}: {error})"
        ) from None


def _bin_points(fn: str, where: str) -> np.ndarray:
    size = os.path.getsize(where)
    if size % 16:
        raise _error(
            fn, where, f"a KITTI .bin holds float32 (x, y, z, intensity) records of 16 bytes; "
            f"the file has {size} bytes",
        )  # fmt: skip
    return np.fromfile(where, dtype="<f4").reshape(-1, 4)[:, :3].astype(np.float64)


def _npy_points(fn: str, where: str) -> np.ndarray:
    try:
        array = np.load(where, allow_pickle=False)
    except Exception as error:
        raise _error(
            fn, where, f"not a readable .npy array ({type(error).__name__}: {error})"
        ) from None
    if array.ndim != 2 or array.shape[1] < 3 or array.dtype.kind not in "uif":
        raise _error(
            fn, where, f"expected a numeric (N, ≥3) array, got shape {array.shape} of {array.dtype}"
        )
    return array[:, :3].astype(np.float64)


def _las_points(fn: str, where: str) -> np.ndarray:
    try:
        import laspy
    except ImportError:
        raise ImportError(
            f"{fn}: reading LAS/LAZ files needs laspy: pip install 'torchslam[las]'"
        ) from None
    try:
        data = laspy.read(where)
    except Exception as error:  # laspy raises many types for a malformed file
        raise _error(
            fn, where, f"not a readable LAS file ({type(error).__name__}: {error})"
        ) from None
    # x, y, z: the scaled, offset coordinates (the file's units)
    return np.stack([np.asarray(data.x), np.asarray(data.y), np.asarray(data.z)], axis=1).astype(
        np.float64
    )


_READERS = {
    ".pcd": _pcd_points, ".bin": _bin_points, ".ply": _ply_points, ".npy": _npy_points,
    ".xyz": _text_points, ".txt": _text_points, ".pts": _text_points,
    ".las": _las_points, ".laz": _las_points,
}  # fmt: skip


def read_points(
    path: str | os.PathLike,
    *,
    nonfinite: str = "drop",
    return_dropped: bool = False,
    dtype: torch.dtype = torch.float64,
) -> Tensor | tuple[Tensor, int]:
    """Read a point cloud file as (N, 3) points x, y, z (the file's frame and units).

    Formats by suffix: ``.pcd`` (``pypcd4``: ascii, binary, binary_compressed), ``.bin`` (KITTI
    velodyne: float32 x y z intensity), ``.ply`` (any vertex with x, y, z), ``.npy`` (an (N, ≥3)
    array), ``.xyz``/``.txt``/``.pts`` (text, x y z first on each line), ``.las``/``.laz``
    (``laspy``, the optional extra ``torchslam[las]``: scaled coordinates).

    Args:
        nonfinite: ``"drop"`` (default) removes points with a NaN/±Inf coordinate; ``"raise"``
            refuses the file.
        return_dropped: also return the number of points dropped.
        dtype: float32 or float64.

    Returns:
        points (N, 3), or ``(points, dropped)`` with ``return_dropped``.
    """
    fn = "read_points"
    where = _checks.check_path(fn, path, is_file=True)
    _checks.check_float_dtype(fn, dtype)
    if nonfinite not in ("drop", "raise"):
        raise ValueError(
            f"{fn}: argument 'nonfinite' must be 'drop' or 'raise', got "
            f"{_checks.describe(nonfinite)}"
        )
    suffix = Path(where).suffix.lower()
    reader = _READERS.get(suffix)
    if reader is None:
        raise _error(
            fn, where, f"unknown point-cloud suffix {suffix!r}; accepted: "
            + ", ".join(POINT_SUFFIXES),
        )  # fmt: skip
    if os.path.getsize(where) == 0:
        raise _error(fn, where, "the file is empty")
    points = reader(fn, where)
    finite = np.isfinite(points).all(axis=1)
    dropped = int(points.shape[0] - finite.sum())
    if dropped:
        if nonfinite == "raise":
            first = int(np.argmin(finite))
            raise _error(
                fn, where, f"point {first} is {points[first].tolist()} ({dropped} non-finite "
                "point(s); nonfinite='drop' removes them)",
            )  # fmt: skip
        points = points[finite]
    result = torch.from_numpy(np.ascontiguousarray(points)).to(dtype)
    if not bool(torch.isfinite(result).all()):
        raise _error(fn, where, f"coordinates overflow {dtype}")
    return (result, dropped) if return_dropped else result


# ------------------------------------------------------------------------------ sequences


def _matching(folder: Path, suffixes: Sequence[str]) -> list[Path]:
    return [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in suffixes]


def list_frames(folder: str | os.PathLike, sensor: str | None = None) -> tuple[list[Path], str]:
    """The frames of a sequence folder, sorted by name (numbers as numbers): ``(paths, sensor)``.

    Depth (``sensor="depth"``): every ``.png``/``.tif``/``.pgm`` (only the ``*.depth.*`` ones when
    some are named so, as 7-Scenes' ``frame-XXXXXX.depth.png`` beside colour frames). LiDAR: every
    ``.pcd``/``.bin``/``.ply``/``.npy``. Other files are ignored. A folder with no frames but a
    ``depth/``, ``Scans/``, ``velodyne/`` subfolder (or a single subfolder) holding them is looked
    into. ``sensor=None`` infers it from what the folder holds.
    """
    fn = "list_frames"
    if sensor not in (None, "depth", "lidar"):
        raise ValueError(
            f"{fn}: argument 'sensor' must be 'depth', 'lidar' or None, got "
            f"{_checks.describe(sensor)}"
        )
    if not isinstance(folder, (str, os.PathLike)):
        raise TypeError(f"{fn}: argument 'folder' must be a path, got {_checks.describe(folder)}")
    root = Path(folder)
    if not root.is_dir():
        if root.exists():
            raise ValueError(f"{fn}: {root}: not a folder")
        raise FileNotFoundError(2, f"{fn}: no such folder", str(root))

    def scan(base: Path) -> tuple[list[Path], str] | None:
        depth = _matching(base, DEPTH_SUFFIXES) if sensor != "lidar" else []
        named = [p for p in depth if ".depth." in p.name.lower()]
        depth = named or depth
        lidar = _matching(base, _FOLDER_POINT_SUFFIXES) if sensor != "depth" else []
        if depth and lidar:
            raise ValueError(
                f"{fn}: {base}: holds both depth images and point clouds; pass sensor='depth' "
                "or 'lidar'"
            )
        if depth:
            return sorted(depth, key=_natural_key), "depth"
        if lidar:
            suffixes = {p.suffix.lower() for p in lidar}
            if len(suffixes) > 1:
                raise ValueError(
                    f"{fn}: {base}: holds point clouds of several formats {sorted(suffixes)}"
                )
            return sorted(lidar, key=_natural_key), "lidar"
        return None

    found = scan(root)
    if found is None:
        subfolders = sorted(p for p in root.iterdir() if p.is_dir())
        preferred = [p for p in subfolders if p.name.lower() in ("depth", "scans", "velodyne")]
        for sub in preferred or (subfolders if len(subfolders) == 1 else []):
            found = scan(sub)
            if found is not None:
                break
    if found is None:
        kinds = {"depth": DEPTH_SUFFIXES, "lidar": _FOLDER_POINT_SUFFIXES}
        wanted = kinds[sensor] if sensor else DEPTH_SUFFIXES + _FOLDER_POINT_SUFFIXES
        raise ValueError(f"{fn}: {root}: no frames ({', '.join(wanted)} files)")
    return found


def find_timestamps(folder: str | os.PathLike) -> Path | None:
    """The timestamps file of a sequence folder (``times.txt``, ``timestamps.txt``, TUM's
    ``depth.txt``/``associations.txt``; in the folder or its parent), or None."""
    return _find(Path(folder), _TIMESTAMP_NAMES)


def read_timestamps(
    path: str | os.PathLike, count: int | None = None, names: Sequence[str] | None = None
) -> np.ndarray:
    """Timestamps (float64 seconds) from a text file, one per frame.

    A line is ``t`` (KITTI's ``times.txt``) or ``t file [t file …]`` (TUM's ``depth.txt`` and
    association files). With ``names`` (the frames' file names) and lines that name files, each
    frame takes the time written before its name; otherwise the first column, in order. ``#``
    lines are skipped. ``count`` (the number of frames) must match.
    """
    fn = "read_timestamps"
    where = _checks.check_path(fn, path, is_file=True)
    with open(where, "rb") as f:
        lines = _text.decode_lines(f.read(), where, fn, "text timestamps file")
    first: list[float] = []
    by_name: dict[str, float] = {}
    for number, raw in enumerate(lines, start=1):
        words = raw.split()
        if not words or words[0].startswith("#"):
            continue
        try:
            first.append(_text.parse_finite_float(words[0]))
            for t, name in zip(words[0::2], words[1::2], strict=False):
                by_name[Path(name).name] = _text.parse_finite_float(t)
        except _text.TokenError as error:
            raise _error(fn, where, f"line {number}: {error}") from None
    if names is not None and by_name:
        missing = [n for n in names if Path(n).name not in by_name]
        if missing:
            raise _error(fn, where, f"no timestamp for frame {missing[0]!r}")
        times = np.array([by_name[Path(n).name] for n in names], dtype=np.float64)
    else:
        times = np.array(first, dtype=np.float64)
    if count is not None and times.shape[0] != count:
        raise _error(fn, where, f"{times.shape[0]} timestamps for {count} frames")
    return times


def read_reference_poses(
    path: str | os.PathLike, count: int | None = None
) -> tuple[Tensor, np.ndarray | None]:
    """Reference poses of a sequence, **frame → world** (m, 4, 4) float64, and timestamps.

    ``path`` is a TUM file (``t tx ty tz qx qy qz qw``), a KITTI file (12 numbers a line, the
    3 × 4 rows of frame → world, as also written by LiDAR SLAM systems), or a folder of
    per-frame ``*.pose.txt`` files (4 × 4 camera → world, as 7-Scenes). The format is told by
    the number of values on a line. Timestamps come from a TUM file only (else None). ``count``
    (the number of frames) must match.
    """
    from torchslam.io import trajectories

    fn = "read_reference_poses"
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"{fn}: argument 'path' must be a path, got {_checks.describe(path)}")
    where = Path(path)
    times = None
    if where.is_dir():
        files = sorted(where.glob("*.pose.txt"), key=_natural_key)
        if not files:
            raise ValueError(f"{fn}: {where}: no *.pose.txt files")
        poses = []
        for file in files:
            numbers = _numbers(fn, file, "text pose file")
            if len(numbers) not in (12, 16):
                raise _error(fn, file, f"expected a 4×4 or 3×4 matrix, got {len(numbers)} numbers")
            T = np.eye(4)
            T[:3] = np.reshape(numbers[:12], (3, 4))
            poses.append(T)
        array = np.stack(poses)
        U, _, Vt = np.linalg.svd(array[:, :3, :3])  # 7-Scenes' rotations carry ~7 digits
        array[:, :3, :3] = U @ Vt
        result = torch.from_numpy(array)
    else:
        file = _checks.check_path(fn, path, is_file=True)
        with open(file, "rb") as f:
            lines = _text.decode_lines(f.read(), file, fn, "text trajectory file")
        widths = {len(line.split()) for line in lines if line.strip() and line[0] != "#"}
        if widths == {8}:
            result, _, times_t = trajectories.read_trajectory(file, "tum")
            times = times_t.numpy()
        elif widths == {12}:
            result = trajectories.read_trajectory(file, "kitti")[0]
        else:
            raise _error(
                fn, file, f"lines of {sorted(widths)} values: expected 8 (TUM) or 12 (KITTI)"
            )
    if count is not None and result.shape[0] != count:
        raise ValueError(f"{fn}: {where}: {result.shape[0]} poses for {count} frames")
    return result, times


def associate_timestamps(
    times: object, reference_times: object, max_difference: float = 0.01
) -> tuple[np.ndarray, np.ndarray]:
    """Match frames to reference poses by time, as ``evo`` does (``--t_max_diff``, 0.01 s):
    each frame takes the reference sample nearest in time, kept when at most
    ``max_difference`` seconds away. For a reference sampled at another rate than the frames
    (TUM RGB-D's ``groundtruth.txt``: 100 Hz motion capture beside 30 Hz depth frames).

    Args:
        times: the frames' timestamps (F,), seconds, finite.
        reference_times: the reference poses' timestamps (R,), seconds, finite, any order.
        max_difference: the largest time difference of a match, seconds, ≥ 0.

    Returns:
        ``(frames, reference)``: int64 index arrays (M,), M ≤ F, the matched frames in
        increasing order and the reference sample each one takes.
    """
    fn = "associate_timestamps"
    arrays = []
    for name, value in (("times", times), ("reference_times", reference_times)):
        array = _float_array(fn, name, value, "a 1-D sequence of numbers")
        if array.ndim != 1 or array.size == 0:
            raise ValueError(
                f"{fn}: argument {name!r} must be a non-empty 1-D sequence of times, got shape "
                f"{array.shape}"
            )
        if not np.isfinite(array).all():
            raise ValueError(f"{fn}: argument {name!r} holds non-finite times")
        arrays.append(array)
    limit = _checks.check_real(fn, "max_difference", max_difference, low=0.0)
    frame_times, reference = arrays
    order = np.argsort(reference, kind="stable")
    sorted_times = reference[order]
    right = np.clip(np.searchsorted(sorted_times, frame_times), 1, len(sorted_times) - 1)
    left = right - 1
    if len(sorted_times) == 1:
        left = right = np.zeros_like(right)
    # the nearer neighbour; a tie takes the earlier sample
    nearer = np.where(
        np.abs(sorted_times[right] - frame_times) < np.abs(frame_times - sorted_times[left]),
        right,
        left,
    )
    kept = np.abs(sorted_times[nearer] - frame_times) <= limit
    return np.flatnonzero(kept).astype(np.int64), order[nearer[kept]].astype(np.int64)
