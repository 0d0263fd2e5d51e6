"""Synthetic bundle-adjustment scenes in the BAL format, of any size.

C cameras on a ring (radius 4× the scene's) at the scene's height, each looking at the centre
(Snavely's camera looks down −z: the camera's z axis points away from the scene), N points in
a box around the centre; each point is seen by the ``views`` cameras nearest to it in
azimuth (a banded co-visibility, as along a real capture path). Pixels are Snavely
projections (:func:`torchslam.cameras.snavely_project`) with Gaussian noise; the initial
guess perturbs the cameras (rotation, translation, focal length, distortion zeroed) and the
points. A :class:`torchslam.io.BALProblem` holding the initial guess comes back with the
true values beside it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchslam.cameras import snavely_project
from torchslam.io.bal import BALProblem
from torchslam.lie import se3, so3

__all__ = ["BALScene", "make_bal_scene"]


@dataclass
class BALScene:
    """A synthetic BAL problem: ``problem`` holds the initial guess and the observations;
    ``cameras`` (C, 9) and ``points`` (N, 3) are the true values."""

    problem: BALProblem
    cameras: Tensor
    points: Tensor


def make_bal_scene(
    num_cameras: int = 10,
    num_points: int = 1000,
    *,
    views: int = 4,
    noise: float = 0.5,
    perturbation: float = 1.0,
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
) -> BALScene:
    """A :class:`BALScene` (module doc).

    Args:
        num_cameras: C ≥ 2 cameras; num_points: N ≥ 1 points.
        views: cameras that see each point, 2 ≤ views ≤ C.
        noise: pixel noise σ (pixels).
        perturbation: scale of the initial guess's errors (1: ≈ 1° and 5 cm per camera, 2 %
            focal length, distortion 0, 5 cm per point; 0: the truth).
        seed: of the random generator; dtype: of the tensors.
    """
    fn = "make_bal_scene"
    for name, value, low in (("num_cameras", num_cameras, 2), ("num_points", num_points, 1)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"{fn}: argument {name!r} must be an int ≥ {low}, got {value!r}")
    if isinstance(views, bool) or not isinstance(views, int) or not 2 <= views <= num_cameras:
        raise ValueError(
            f"{fn}: argument 'views' must be an int in [2, num_cameras = {num_cameras}], "
            f"got {views!r}"
        )
    for name, value in (("noise", noise), ("perturbation", perturbation)):
        if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
            raise ValueError(f"{fn}: argument {name!r} must be a finite number ≥ 0, got {value!r}")
    g = torch.Generator().manual_seed(seed)
    C, N = num_cameras, num_points

    def rand(*shape: int) -> Tensor:
        return torch.rand(*shape, generator=g, dtype=dtype)

    def randn(*shape: int) -> Tensor:
        return torch.randn(*shape, generator=g, dtype=dtype)

    points = (rand(N, 3) * 2 - 1) * torch.tensor([2.0, 2.0, 1.0], dtype=dtype)
    azimuth = 2 * math.pi * torch.arange(C, dtype=dtype) / C
    centres = 8.0 * torch.stack((azimuth.cos(), azimuth.sin(), torch.zeros_like(azimuth)), -1)
    z = centres / centres.norm(dim=-1, keepdim=True)  # away from the scene
    up = torch.tensor([0.0, 0.0, 1.0], dtype=dtype).expand(C, 3)
    x = torch.linalg.cross(up, z, dim=-1)
    x = x / x.norm(dim=-1, keepdim=True)
    y = torch.linalg.cross(z, x, dim=-1)
    R = torch.stack((x, y, z), dim=-2)  # rows: the camera axes in the world
    t = -(R @ centres[..., None])[..., 0]
    intrinsics = torch.stack(
        (600.0 + 50.0 * randn(C), -0.05 + 0.01 * randn(C), 0.005 + 0.001 * randn(C)), -1
    )
    cameras = torch.cat((so3.log(R), t, intrinsics), -1)
    # Each point seen by the `views` cameras nearest to it in azimuth.
    point_azimuth = torch.atan2(points[:, 1], points[:, 0])
    gap = (point_azimuth[:, None] - azimuth[None, :] + math.pi) % (2 * math.pi) - math.pi
    camera_index = torch.topk(-gap.abs(), views, dim=1).indices.reshape(-1)
    point_index = torch.arange(N).repeat_interleave(views)
    T = se3.from_rotation_translation(R, t)
    pixels = snavely_project(T[camera_index], points[point_index], intrinsics[camera_index])
    pixels = pixels + noise * randn(*pixels.shape)
    s = perturbation
    rotation = so3.exp(s * math.radians(1.0) * randn(C, 3)) @ R
    initial = torch.cat(
        (
            so3.log(rotation),
            t + s * 0.05 * randn(C, 3),
            (intrinsics[:, :1] * (1 + s * 0.02 * randn(C, 1))),
            intrinsics[:, 1:] * (1 - min(s, 1.0)),
        ),
        -1,
    )
    problem = BALProblem(
        initial, points + s * 0.05 * randn(N, 3), camera_index, point_index, pixels
    )
    return BALScene(problem, cameras, points)
