"""Options of the multiview registration pipeline, and the argument checks its modules share.

:class:`RegisterConfig` holds every option of :func:`torchslam.registration.register`;
:func:`default_stages` is its coarse-to-fine pairwise ICP schedule. Lengths are in the scans'
units (any unit: metres, millimetres, …) and scale with one length, ``voxel_size``, which by
default is derived from the scans themselves (:func:`scan_scale`, :func:`auto_voxel_size`): the
same scans in metres and in millimetres get the same voxels up to the factor 1000 and
register to the same poses up to that scale.
:func:`check_config`, :func:`check_clouds` and :func:`check_poses` validate the arguments of
the pipeline, report and figure functions (messages name the public function).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from torchslam import _checks
from torchslam.losses import CauchyLoss, HuberLoss
from torchslam.registration import icp
from torchslam.registration.kdtree import KDTree

__all__ = ["RegisterConfig", "ScanScale", "auto_voxel_size", "default_stages", "scan_scale"]


def default_stages(voxel_size: float = 0.002) -> tuple[icp.Stage, ...]:
    """Coarse-to-fine pairwise schedule: 5×, 2.5× and 1× ``voxel_size`` (10, 5, 2 mm).

    Point-to-plane at every level: from starts 30–60° off it converges in a few iterations,
    where point-to-point creeps along the surface. Level 1 runs all hypotheses for 8
    iterations and passes the best 8 on; level 2 the best one; level 3 refines it.

    Raises:
        TypeError, ValueError: ``voxel_size`` is not a finite number > 0.
    """
    v = _checks.check_real("default_stages", "voxel_size", voxel_size, low=0, low_open=True)
    return (
        icp.Stage(
            5 * v,
            icp.ICPConfig(
                method="point_to_plane",
                max_iterations=8,
                max_distance=25 * v,
                min_distance=5 * v,
                trim_fraction=0.9,
                relative_tolerance=1e-3,
            ),
            keep=8,
        ),
        icp.Stage(
            2.5 * v,
            icp.ICPConfig(
                method="point_to_plane",
                max_iterations=20,
                max_distance=10 * v,
                min_distance=2.5 * v,
                trim_fraction=0.9,
                relative_tolerance=1e-4,
            ),
            keep=1,
        ),
        icp.Stage(
            v,
            icp.ICPConfig(
                method="point_to_plane",
                max_iterations=40,
                max_distance=5 * v,
                min_distance=v,
                trim_fraction=0.9,
                relative_tolerance=1e-5,
            ),
        ),
    )


@dataclass(frozen=True)
class RegisterConfig:
    """Options of :func:`~torchslam.registration.register`. Lengths are in the scans' units
    (metres for the bunny)."""

    # finest voxel pitch: pairwise ICP's last level and the clouds the tracks are built on;
    # None: derived from the scans (auto_voxel_size; 2 mm for the bunny in metres, 2 for it
    # in millimetres)
    voxel_size: float | None = None
    # "any": the scans may come in any order (pairwise alignment of all pairs, an overlap
    # graph, a maximum spanning tree of the most reliable pairs); "chain": successive scans
    # overlap and are registered pairwise along the given order
    order: Literal["any", "chain"] = "any"
    # order "any": every scan's best `candidates` partners (by the coarse alignment's
    # overlap) are registered finely and compete for the spanning tree
    candidates: int = 3
    # initial rotations per chain pair (super-Fibonacci over SO(3), centroids aligned)
    hypotheses: int = 128
    # pairwise levels; None means default_stages(voxel_size)
    stages: tuple[icp.Stage, ...] | None = None
    # a pair is matched when each scan has ≥ this fraction of points within a voxel of the other
    min_overlap: float = 0.1
    # mutual-nearest-neighbour radius of the tracks, in units of voxel_size
    track_radius: float = 1.5
    # neighbours of the PCA normals of the track clouds (and of the boundary test)
    normal_neighbors: int = 12
    # points whose neighbour centroid is off by more than this × their mean neighbour
    # distance lie on a scan's boundary and make no tracks (None keeps them)
    boundary_threshold: float | None = 0.3
    # τ of Ω = n nᵀ + τ (I − n nᵀ): weight of residuals along the surface (1 = isotropic)
    tangent_weight: float = 0.01
    # robust kernel of the joint solve, on s = rᵀ Ω r
    loss: Literal["huber", "cauchy", "none"] = "huber"
    # its scale, in units of voxel_size
    loss_scale: float = 0.5
    # association + joint-solve rounds at most (0: chaining only)
    rounds: int = 4
    # stop the rounds when no pose moves more than this (degrees) ...
    rotation_tolerance_deg: float = 0.005
    # ... and this (in units of voxel_size) between two rounds
    translation_tolerance: float = 0.005
    # Levenberg–Marquardt iterations per round at most
    max_iterations: int = 30

    def __post_init__(self) -> None:
        fn, kind = "RegisterConfig", "field"
        if self.voxel_size is not None:
            _checks.check_real(fn, "voxel_size", self.voxel_size, low=0, low_open=True, kind=kind)
        for name in ("track_radius", "loss_scale"):
            _checks.check_real(fn, name, getattr(self, name), low=0, low_open=True, kind=kind)
        if not isinstance(self.order, str) or self.order not in ("any", "chain"):
            raise ValueError(
                f"{fn}: field 'order' must be 'any' or 'chain', got {_checks.describe(self.order)}"
            )
        _checks.check_int(fn, "candidates", self.candidates, minimum=1, kind=kind)
        _checks.check_real(
            fn, "tangent_weight", self.tangent_weight, low=0, high=1, low_open=True, kind=kind
        )
        _checks.check_real(fn, "min_overlap", self.min_overlap, low=0, high=1, kind=kind)
        for name in ("rotation_tolerance_deg", "translation_tolerance"):
            _checks.check_real(fn, name, getattr(self, name), low=0, kind=kind)
        if self.boundary_threshold is not None:
            _checks.check_real(
                fn, "boundary_threshold", self.boundary_threshold, low=0, low_open=True, kind=kind
            )
        _checks.check_int(fn, "hypotheses", self.hypotheses, minimum=1, kind=kind)
        _checks.check_int(fn, "normal_neighbors", self.normal_neighbors, minimum=3, kind=kind)
        _checks.check_int(fn, "rounds", self.rounds, minimum=0, kind=kind)
        _checks.check_int(fn, "max_iterations", self.max_iterations, minimum=0, kind=kind)
        if not isinstance(self.loss, str) or self.loss not in ("huber", "cauchy", "none"):
            raise ValueError(
                f"{fn}: field 'loss' must be 'huber', 'cauchy' or 'none', "
                f"got {_checks.describe(self.loss)}"
            )
        if self.stages is not None:
            stages = self.stages
            if isinstance(stages, (str, bytes)) or not isinstance(stages, Sequence):
                raise TypeError(
                    f"{fn}: field 'stages' must be None or a non-empty tuple of icp.Stage, "
                    f"got {_checks.describe(stages)}"
                )
            for k, stage in enumerate(stages):
                if not isinstance(stage, icp.Stage):
                    raise TypeError(
                        f"{fn}: field 'stages' must hold icp.Stage objects, got "
                        f"{_checks.describe(stage)} at index {k}"
                    )
            if not stages:
                raise ValueError(
                    f"{fn}: field 'stages' must be None or a non-empty tuple of icp.Stage, got ()"
                )
            object.__setattr__(self, "stages", tuple(stages))

    @property
    def voxel(self) -> float:
        """``voxel_size``, which must be set (ValueError if it is None: see :meth:`resolved`)."""
        if self.voxel_size is None:
            raise ValueError(
                "RegisterConfig: field 'voxel_size' is None (derived from the scans); use "
                "config.resolved(clouds) or give a voxel size"
            )
        return self.voxel_size

    def resolved(self, clouds: Sequence[Tensor], fn: str = "RegisterConfig.resolved"):
        """This config with ``voxel_size`` set: itself if given, else
        :func:`auto_voxel_size` of ``clouds`` (which also refuses implausible scans)."""
        if self.voxel_size is not None:
            return self
        voxel = auto_voxel_size(scan_scale(clouds, fn=fn))
        return replace(self, voxel_size=voxel)

    def pairwise_stages(self) -> tuple[icp.Stage, ...]:
        """The pairwise ICP levels in force."""
        return default_stages(self.voxel) if self.stages is None else self.stages

    def robust_loss(self) -> object | None:
        """The robust kernel object of the joint solve (None for plain least squares)."""
        scale = self.loss_scale * self.voxel
        if self.loss == "huber":
            return HuberLoss(scale)
        if self.loss == "cauchy":
            return CauchyLoss(scale)
        return None


# ----------------------------------------------------------------------------- units and scale


@dataclass(frozen=True)
class ScanScale:
    """Size and sampling of a set of scans, in their units (see :func:`scan_scale`)."""

    # per scan: median distance of a point to its nearest other point
    spacing: tuple[float, ...]
    # per scan: RMS distance of the points from their centroid
    radius: tuple[float, ...]
    # per scan: distance of the centroid from the origin of the scan's frame
    offset: tuple[float, ...]
    # messages about scans that look odd but are usable
    warnings: tuple[str, ...] = ()


# Largest ratio of two scans' sizes before they are refused as mixed units (m vs mm: 1000).
MAX_SIZE_RATIO = 100.0
# Ratio above which a size difference is reported (but accepted).
WARN_SIZE_RATIO = 10.0


def scan_scale(
    clouds: Sequence[object],
    names: Sequence[str] | None = None,
    *,
    fn: str = "scan_scale",
    sample: int = 2000,
) -> ScanScale:
    """Measure each scan's point spacing and size, and refuse implausible scans.

    Spacing: the median nearest-neighbour distance over up to ``sample`` evenly strided
    points (exact neighbours among all points). Radius: RMS distance from the centroid.

    Raises:
        TypeError, ValueError (messages name ``fn`` and the scan): not a list of (N, 3) float
        tensors/arrays; a scan whose points all coincide (radius 0); scans whose sizes differ
        by more than ×100 (mixed units?); coordinates so far from the origin compared with
        the spacing that the dtype cannot resolve the sampling (float32 at 1e5 × the point
        spacing; subtract an offset or use float64).
    """
    clouds = check_clouds(fn, clouds, min_points=2)
    labels = list(names) if names is not None else [f"clouds[{k}]" for k in range(len(clouds))]
    spacing, radius, offset = [], [], []
    for label, cloud in zip(labels, clouds, strict=True):
        x = cloud.detach().cpu().numpy().astype(np.float64, copy=False)
        centroid = x.mean(0)
        r = float(np.sqrt(((x - centroid) ** 2).sum(1).mean()))
        if not r > 0:
            raise ValueError(
                f"{fn}: scan {label!r}: all {len(x)} points coincide; not a scan of a surface"
            )
        probe = x[:: max(1, len(x) // sample)]
        distance, _ = KDTree(x).query(probe, k=2, workers=icp.query_workers())
        gaps = distance[:, 1]
        gaps = gaps[gaps > 0]
        h = float(np.median(gaps)) if len(gaps) else r
        resolution = float(np.abs(x).max()) * float(torch.finfo(cloud.dtype).eps)
        if resolution > 0.1 * h:
            raise ValueError(
                f"{fn}: scan {label!r}: coordinates up to {float(np.abs(x).max()):.4g} are too "
                f"far from the origin for {cloud.dtype} to resolve the point spacing "
                f"{h:.3g} (steps of {resolution:.3g}); subtract a common offset or use float64"
            )
        spacing.append(h)
        radius.append(r)
        offset.append(float(np.linalg.norm(centroid)))
    warnings = []
    big, small = int(np.argmax(radius)), int(np.argmin(radius))
    ratio = radius[big] / radius[small]
    if ratio > MAX_SIZE_RATIO:
        raise ValueError(
            f"{fn}: scan {labels[big]!r} is {ratio:.0f}× the size of scan {labels[small]!r} "
            f"(RMS radius {radius[big]:.4g} vs {radius[small]:.4g}): are they in different "
            "units (m vs mm)? Convert them to one unit"
        )
    if ratio > WARN_SIZE_RATIO:
        warnings.append(
            f"scan {labels[big]!r} is {ratio:.0f}× the size of scan {labels[small]!r}; check "
            "that all scans are in one unit"
        )
    return ScanScale(tuple(spacing), tuple(radius), tuple(offset), tuple(warnings))


def _nice(value: float) -> float:
    """The nearest of 1, 2, 5 × 10^k in log scale (scale-equivariant for powers of ten)."""
    exponent = math.floor(math.log10(value))
    base = 10.0**exponent
    mantissa = value / base
    choices = (1.0, 2.0, 5.0, 10.0)
    best = min(choices, key=lambda c: abs(math.log(mantissa / c)))
    # Round in decimal, so that 0.002 and 2.0 are the literals a user would type.
    return float(f"{best * base:.1g}") if best < 10 else float(f"{10 * base:.1g}")


def auto_voxel_size(scale: ScanScale) -> float:
    """The default finest voxel pitch: max(4 × point spacing, RMS radius / 30), medians over
    the scans, rounded to 1, 2 or 5 × 10^k (2 mm for the Stanford bunny in metres: spacing
    0.53 mm, radius 57 mm). Four spacings keep several points per voxel; radius / 30 bounds
    the voxels per scan (a few thousand) for densely sampled scans. The rounding is
    scale-equivariant: the same scans in millimetres get exactly 1000× the pitch."""
    if not isinstance(scale, ScanScale):
        raise TypeError(
            f"auto_voxel_size: argument 'scale' must be a ScanScale, got {_checks.describe(scale)}"
        )
    raw = max(4 * float(np.median(scale.spacing)), float(np.median(scale.radius)) / 30)
    return _nice(raw)


# ----------------------------------------------------------------------------- argument checks


def check_clouds(
    fn: str, clouds: object, *, minimum: int = 1, min_points: int = 1, name: str = "clouds"
) -> list[Tensor]:
    """A list of ≥ ``minimum`` float clouds (N_i, 3), N_i ≥ ``min_points``, of one dtype and
    device, finite when value checks are active. numpy arrays (float32/float64) are accepted
    and returned as tensors (sharing memory, on the CPU)."""
    if isinstance(clouds, Tensor) or not isinstance(clouds, Sequence) or isinstance(clouds, str):
        raise TypeError(
            f"{fn}: argument '{name}' must be a list of tensors of shape (N_i, 3), "
            f"got {_checks.describe(clouds)}"
        )
    out = list(clouds)
    if len(out) < minimum:
        raise ValueError(f"{fn}: argument '{name}' must hold ≥ {minimum} clouds, got {len(out)}")
    like = next((c for c in out if isinstance(c, Tensor)), None)
    for k, cloud in enumerate(out):
        if isinstance(cloud, np.ndarray):
            # numpy arrays (float32/float64) become tensors on the device of the first tensor
            cloud = _checks.as_points(fn, f"{name}[{k}]", cloud, like=like, finite=False)
            out[k] = cloud
        _checks.check_batched(fn, f"{name}[{k}]", cloud, ("N",), (3,))
        if cloud.shape[0] < min_points:
            raise ValueError(
                f"{fn}: argument '{name}[{k}]' must have ≥ {min_points} points, "
                f"got shape {tuple(cloud.shape)}"
            )
        if k:
            _checks.check_same_kind(fn, **{f"{name}[0]": out[0], f"{name}[{k}]": cloud})
        _checks.check_finite(fn, f"{name}[{k}]", cloud)
    return out


def check_poses(fn: str, poses: object, m: int, against: str = "'clouds'") -> Tensor:
    """T_0i of shape (m, 4, 4), rigid when value checks are active."""
    _checks.check_batched(fn, "poses", poses, ("m",), (4, 4), sizes=(m,), against=against)
    assert isinstance(poses, Tensor)
    _checks.check_pose_matrix(fn, "poses", poses)
    return poses


def check_config(fn: str, config: object) -> RegisterConfig:
    """``config`` itself, or the defaults for None (TypeError for anything else)."""
    if config is None:
        return RegisterConfig()
    if not isinstance(config, RegisterConfig):
        raise TypeError(
            f"{fn}: argument 'config' must be a RegisterConfig or None, "
            f"got {_checks.describe(config)}; build one with RegisterConfig(**options)"
        )
    return config
