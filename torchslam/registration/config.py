"""Options of the multiview registration pipeline, and the argument checks its modules share.

:class:`RegisterConfig` holds every option of :func:`torchslam.registration.register`;
:func:`default_stages` is its coarse-to-fine pairwise ICP schedule. Lengths are in the scans'
units (metres for the Stanford bunny) and scale with one length, ``voxel_size``.
:func:`check_config`, :func:`check_clouds` and :func:`check_poses` validate the arguments of
the pipeline, report and figure functions (messages name the public function).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from torch import Tensor

from torchslam import _checks
from torchslam.losses import CauchyLoss, HuberLoss
from torchslam.registration import icp

__all__ = ["RegisterConfig", "default_stages"]


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

    # finest voxel pitch: pairwise ICP's last level and the clouds the tracks are built on
    voxel_size: float = 0.002
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
        for name in ("voxel_size", "track_radius", "loss_scale"):
            _checks.check_real(fn, name, getattr(self, name), low=0, low_open=True, kind=kind)
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

    def pairwise_stages(self) -> tuple[icp.Stage, ...]:
        """The pairwise ICP levels in force."""
        return default_stages(self.voxel_size) if self.stages is None else self.stages

    def robust_loss(self) -> object | None:
        """The robust kernel object of the joint solve (None for plain least squares)."""
        scale = self.loss_scale * self.voxel_size
        if self.loss == "huber":
            return HuberLoss(scale)
        if self.loss == "cauchy":
            return CauchyLoss(scale)
        return None


# ----------------------------------------------------------------------------- argument checks


def check_clouds(
    fn: str, clouds: object, *, minimum: int = 1, min_points: int = 1, name: str = "clouds"
) -> list[Tensor]:
    """A list of ≥ ``minimum`` float clouds (N_i, 3), N_i ≥ ``min_points``, of one dtype and
    device, finite when value checks are active."""
    if isinstance(clouds, Tensor) or not isinstance(clouds, Sequence) or isinstance(clouds, str):
        raise TypeError(
            f"{fn}: argument '{name}' must be a list of tensors of shape (N_i, 3), "
            f"got {_checks.describe(clouds)}"
        )
    out = list(clouds)
    if len(out) < minimum:
        raise ValueError(f"{fn}: argument '{name}' must hold ≥ {minimum} clouds, got {len(out)}")
    for k, cloud in enumerate(out):
        if isinstance(cloud, np.ndarray):
            raise TypeError(
                f"{fn}: argument '{name}' must hold torch tensors, got a numpy array at index "
                f"{k}; convert with torch.from_numpy"
            )
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
