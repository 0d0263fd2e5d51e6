"""Named real data sets, fetched from their public origin and checked by sha256 (``pooch``).

:data:`DATASETS` lists them: the Stanford bunny scans, the pose-graph benchmarks, the BAL
Ladybug problem, 7-Scenes depth frames and LiDAR sequences, each with its origin (a public
repository at a fixed commit), size and licence note. Every file's sha256 and size is in
``registry.txt`` beside this module.

Where the files come from, in this order:

1. an offline mirror, ``TORCHSLAM_DATA_MIRROR`` (a folder with the same layout, e.g. the
   project's ``../shared/data``): used in place, each file checked against its sha256;
2. the cache, ``TORCHSLAM_DATA`` or the platform's cache folder (``pooch.os_cache``);
3. a download into the cache: written to a temporary file and moved into place only when its
   sha256 matches (a wrong checksum is refused and leaves nothing behind).

:func:`fetch` returns the data set's folder (the layout of the shared data: ``bunny/``,
``lidar/hku2-loop/``, …). ``torchslam data list`` / ``torchslam data fetch NAME`` /
``torchslam data path NAME`` do the same from the command line.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

__all__ = [
    "DATASETS",
    "DataFile",
    "Dataset",
    "DatasetUnavailableError",
    "cache_folder",
    "fetch",
    "status",
]

_REGISTRY = Path(__file__).with_name("registry.txt")


class DatasetUnavailableError(OSError):
    """A data set is neither mirrored nor cached, and downloading it failed or is off."""


@dataclass(frozen=True)
class DataFile:
    """One file: its path in the data set's folder, sha256 and size in bytes."""

    path: str
    sha256: str
    size: int


@dataclass(frozen=True)
class Dataset:
    """A named data set: its folder (in the mirror and the cache), where it comes from."""

    name: str
    folder: str
    description: str
    # the origin: a public repository at a fixed commit, and the folder the files sit in
    base_url: str
    licence: str
    files: tuple[DataFile, ...] = ()

    @property
    def size(self) -> int:
        return sum(f.size for f in self.files)

    def url(self, file: DataFile) -> str:
        return f"{self.base_url.rstrip('/')}/{file.path}"


def _raw(repo: str, commit: str, folder: str) -> str:
    return f"https://raw.githubusercontent.com/{repo}/{commit}/{folder}"


_SOURCES = {
    "bunny": (
        "bunny",
        "Stanford Bunny: 10 raw range scans (PLY, metres) and the alignment bun.conf",
        _raw("somanshu25/GPU-Accelerated-Point-Cloud-Registration-Using-Hierarchical-GMM",
             "ff2ea430241dffa6175103802eac7e331ea8dcaa", "data"),
        "Stanford 3D Scanning Repository: research use, credit the Stanford Computer Graphics "
        "Laboratory; commercial use needs its permission",
    ),
    "posegraph": (
        "posegraph",
        "pose-graph benchmarks (g2o): sphere2500, parking-garage (3D), MIT Killian Court (2D)",
        _raw("david-m-rosen/SE-Sync", "9b631b6b82d8aa7d32ab846412ae1c070412b7b6", "data"),
        "research benchmarks distributed with SE-Sync (LGPL-3.0 code); no licence of their own",
    ),
    "bal-ladybug-21": (
        "bal",
        "Bundle Adjustment in the Large, Ladybug problem-21-11315-pre (21 cameras)",
        _raw("amin-abouee/apex-solver", "48e1f09c35c568ffbe7ac4a7d19b8d7995df20f4",
             "data/bundle_adjustment"),
        "BAL (Agarwal et al., ECCV 2010): no licence stated by the origin",
    ),
    "rgbd-7scenes": (
        "rgbd/7scenes-150-199",
        "7-Scenes: 50 Kinect depth frames (16-bit PNG, mm) with camera → world poses and K",
        _raw("andyzeng/tsdf-fusion", "afbd0d16dcb2afb95e71d19fcddb2f926055d08b",
             "data/rgbd-frames"),
        "Microsoft 7-Scenes: research use; not redistributed inside the package",
    ),
    "lidar-quick-shack": (
        "lidar/quick-shack",
        "241 hand-held LiDAR keyframes (PCD) with LiDAR-inertial poses (KITTI format)",
        _raw("daxuanzi515/Fast-LIO2_SC-SLAM", "d1990f802fe035afadb92deb87cf3fd6177c79ab",
             "output/2020-09-16-quick-shack_bag"),
        "no licence stated by the repository: testing only, not redistributed",
    ),
    "lidar-hku2-loop": (
        "lidar/hku2-loop",
        "266 LiDAR keyframes of a 58.5 m loop (PCD) with LiDAR-inertial poses",
        _raw("daxuanzi515/Fast-LIO2_SC-SLAM", "d1990f802fe035afadb92deb87cf3fd6177c79ab",
             "output/HKU_2_bag"),
        "no licence stated by the repository: testing only, not redistributed",
    ),
    "lidar-pair": (
        "lidar/pair",
        "one LiDAR scan pair (PLY) with a reference transform (small_gicp's test data)",
        _raw("koide3/small_gicp", "aea131352e0d362d3e579a334c477cfafa5ee5eb", "data"),
        "MIT, Copyright (c) 2024 Kenji Koide",
    ),
}  # fmt: skip


def _load() -> dict[str, Dataset]:
    files: dict[str, list[DataFile]] = {name: [] for name in _SOURCES}
    for line in _REGISTRY.read_text(encoding="utf-8").splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        name, path, sha256, size = line.split()
        files[name].append(DataFile(path, sha256, int(size)))
    return {
        name: Dataset(name, folder, description, url, licence, tuple(files[name]))
        for name, (folder, description, url, licence) in _SOURCES.items()
    }


DATASETS: dict[str, Dataset] = _load()


def cache_folder() -> Path:
    """``TORCHSLAM_DATA``, else the platform's cache folder for torchslam."""
    configured = os.environ.get("TORCHSLAM_DATA")
    if configured:
        return Path(configured).expanduser()
    import pooch

    return Path(pooch.os_cache("torchslam"))


def _mirror() -> Path | None:
    configured = os.environ.get("TORCHSLAM_DATA_MIRROR")
    return Path(configured).expanduser() if configured else None


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _dataset(fn: str, name: object) -> Dataset:
    if not isinstance(name, str) or name not in DATASETS:
        raise ValueError(
            f"{fn}: unknown data set {name!r}; the data sets are {', '.join(DATASETS)}"
        )
    return DATASETS[name]


def _check(fn: str, dataset: Dataset, file: DataFile, path: Path) -> None:
    size = path.stat().st_size
    if size != file.size or _sha256(path) != file.sha256:
        raise ValueError(
            f"{fn}: {path}: not the registered file of data set '{dataset.name}' (sha256 or "
            f"size differ; expected {file.size} bytes, sha256 {file.sha256[:16]}…)"
        )


def status(name: str) -> str:
    """Where :func:`fetch` would take ``name`` from: "mirror", "cached" or "missing" (sizes
    only: no checksum is computed)."""
    dataset = _dataset("status", name)
    for where, label in ((_mirror(), "mirror"), (cache_folder(), "cached")):
        if where is None:
            continue
        base = where / dataset.folder
        if all(
            (base / f.path).is_file() and (base / f.path).stat().st_size == f.size
            for f in dataset.files
        ):
            return label
    return "missing"


def fetch(name: str, *, download: bool = True, progress: bool = False) -> Path:
    """The folder of data set ``name`` (module docstring), every file checked by sha256.

    Args:
        name: a key of :data:`DATASETS`.
        download: fetch what the mirror and the cache lack from the origin (False: refuse).
        progress: show a progress bar while downloading.

    Raises:
        ValueError: an unknown name, or a mirrored or cached file whose sha256 differs.
        DatasetUnavailableError: not mirrored nor cached, and the download is off or failed
            (the message says how to get it).
    """
    fn = "fetch"
    dataset = _dataset(fn, name)
    mirror = _mirror()
    if mirror is not None and (mirror / dataset.folder).is_dir():
        base = mirror / dataset.folder
        missing = [f.path for f in dataset.files if not (base / f.path).is_file()]
        if not missing:
            for file in dataset.files:
                _check(fn, dataset, file, base / file.path)
            return base
    base = cache_folder() / dataset.folder
    for file in dataset.files:
        target = base / file.path
        if target.is_file():
            _check(fn, dataset, file, target)
            continue
        if not download:
            raise DatasetUnavailableError(
                f"{fn}: data set '{name}' is not available offline ({target} is missing); "
                f"fetch it with `torchslam data fetch {name}` or point TORCHSLAM_DATA_MIRROR "
                "at a folder that holds it"
            )
        _download(fn, dataset, file, target, progress)
    return base


def _download(fn: str, dataset: Dataset, file: DataFile, target: Path, progress: bool) -> None:
    import pooch

    target.parent.mkdir(parents=True, exist_ok=True)
    logger = pooch.get_logger()
    level = logger.level
    logger.setLevel("WARNING")  # its "Downloading …" lines: the progress bar says as much
    try:
        # pooch writes to a temporary file in the folder and moves it into place only once
        # its hash matches; on a mismatch it deletes it and raises ValueError.
        pooch.retrieve(
            dataset.url(file),
            known_hash=f"sha256:{file.sha256}",
            fname=target.name,
            path=target.parent,
            progressbar=progress,
        )
    except ValueError as error:
        raise ValueError(f"{fn}: {dataset.url(file)}: the download {error}") from None
    except Exception as error:  # network errors: requests' and urllib's many types
        raise DatasetUnavailableError(
            f"{fn}: could not download data set '{dataset.name}' ({dataset.url(file)}: "
            f"{type(error).__name__}: {error}); without network, point TORCHSLAM_DATA_MIRROR "
            "at a folder that holds it"
        ) from None
    finally:
        logger.setLevel(level)
