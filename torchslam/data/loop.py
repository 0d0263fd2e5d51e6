"""A seeded closed-loop ICP-SLAM scene with odometry and one loop-closure measurement.

The trajectory goes once around a (wobbly) circle and comes back to its start: the heading
advances by 2π/m per frame, so frame m-1 is one ordinary step before frame 0 and the motion
from frame m-1 to frame 0 looks like any other step. Every periodic wobble (radius, height,
pitch, roll) has an integer number of periods per lap, so the trajectory closes smoothly.

Points are local to a stretch of the trajectory: frame i "births" ``points_per_frame`` world
points at 1–4 m from its sensor (in a uniformly random direction: a 360° range sensor, as in
:mod:`torchslam.data.synthetic`), and a point born at frame i is observed only by the frames
i, …, min(i + window, m) − 1. The last frame births no points (they would have a single view),
so n = (m − 1) · points_per_frame. Since ``window ≤ m − 1``, no point is seen by both frame 0
and frame m − 1: there is no data association across the loop, and the drift accumulated
along it can only be corrected by a loop-closure term.

Conventions (those of :mod:`torchslam.data.synthetic`):

- poses are T_i0 (world → frame i), T_00 = I exactly (the gauge: frame 0 is the world);
- observations X_ij = T_i0 X_j + ε, ε ~ N(0, noise_std² I₃), as padded edge lists sorted by
  (pose, point) (here B = 1 and there is no padding);
- a relative-pose measurement Z_ij ≈ T_i0 · T_j0⁻¹ is the pose of frame j expressed in frame
  i: it maps frame-j coordinates into frame i. Its noise is a right perturbation,
  Z_ij = T_i0 T_j0⁻¹ · Exp(ε), ε = (ε_ω, ε_v) ~ N(0, diag(σ_rot² I₃, σ_t² I₃)) in (ω, v) order,
  σ_rot in radians (the arguments give it in degrees);
- odometry measures Z_{i,i+1} for i = 0, …, m − 2; the loop closure measures Z_{m-1,0}.

Everything is drawn on the CPU from one ``torch.Generator`` seeded with ``seed`` in float64 and
then cast, so a seed gives the same scene on every device and dtype.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchslam import _checks
from torchslam.data.synthetic import MAX_TABLE_ENTRIES, SyntheticScene
from torchslam.lie import se3, so3

__all__ = ["LoopScene", "make_loop_scene"]

_POINT_DISTANCE = (1.0, 4.0)  # range of a point's distance to its birth frame's sensor


@dataclass(frozen=True, eq=False)
class LoopScene:
    """A closed-loop scene: point observations, odometry and one loop-closure measurement.

    Shapes: m poses, n = (m − 1) · points_per_frame points, E observations (B = 1 problem).
    Relative poses follow Z_ij ≈ T_i0 · T_j0⁻¹ (frame j expressed in frame i).
    """

    # The point observations and ground truth, batch size B = 1 (plugs into
    # PointMapProblem.from_scene).
    scene: SyntheticScene
    # Noisy odometry Z_{i,i+1} ≈ T_i0 T_{i+1,0}⁻¹, shape (m − 1, 4, 4).
    odometry: Tensor
    # The (i, j) = (i, i + 1) of each odometry measurement, int64, shape (m − 1, 2).
    odometry_pairs: Tensor
    # Noisy loop closure Z_{m-1,0} ≈ T_{m-1,0} T_00⁻¹ = T_{m-1,0}, shape (1, 4, 4).
    loop: Tensor
    # The (i, j) = (m − 1, 0) of the loop closure, int64, shape (1, 2).
    loop_pairs: Tensor
    # Frame that births each point (it is seen by frames birth, …, birth + window − 1 < m),
    # int64, shape (n,).
    birth_frame: Tensor
    # Frames that see each point (clipped at m − 1 for the last births).
    window: int
    # Std of the odometry noise: rotation in radians, translation in metres.
    odometry_rotation_std: float
    odometry_translation_std: float
    # Std of the loop-closure noise: rotation in radians, translation in metres.
    loop_rotation_std: float
    loop_translation_std: float

    @property
    def noise_std(self) -> float:
        """Std of the point observation noise in metres."""
        return self.scene.noise_std

    @property
    def num_poses(self) -> int:
        """m, the number of poses (frame 0 included)."""
        return self.scene.num_poses

    def odometry_information(self) -> Tensor:
        """Information matrix of an odometry measurement, diag(1/σ_rot² I₃, 1/σ_t² I₃), (6, 6).

        Raises ValueError when a std is 0 (the information would be infinite).
        """
        return _information(
            "odometry_information",
            self.odometry_rotation_std,
            self.odometry_translation_std,
            self.odometry,
        )

    def loop_information(self) -> Tensor:
        """Information matrix of the loop closure, diag(1/σ_rot² I₃, 1/σ_t² I₃), (6, 6).

        Raises ValueError when a std is 0 (the information would be infinite).
        """
        return _information(
            "loop_information", self.loop_rotation_std, self.loop_translation_std, self.loop
        )


def make_loop_scene(
    num_poses: int = 60,
    points_per_frame: int = 30,
    window: int = 4,
    noise_std: float = 0.01,
    odometry_rotation_deg: float = 0.5,
    odometry_translation: float = 0.02,
    loop_rotation_deg: float = 0.1,
    loop_translation: float = 0.005,
    radius: float = 4.0,
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> LoopScene:
    """Generate a seeded closed-loop scene (module docstring for the conventions).

    Well-posedness holds by construction: every frame sees ≥ points_per_frame ≥ 3 points,
    successive frames share ≥ points_per_frame points (window ≥ 2), and every point is seen
    by ≥ 2 frames.

    Args:
        num_poses: m ≥ 3, poses around the loop (frame 0 included).
        points_per_frame: points born at each frame but the last, ≥ 3.
        window: frames that see each point, in [2, num_poses − 1] (so that no point links
            frame 0 with frame m − 1).
        noise_std: std of the Gaussian point observation noise in metres, ≥ 0.
        odometry_rotation_deg: std of each rotation component of the odometry noise, in
            degrees, ≥ 0.
        odometry_translation: std of each translation component of the odometry noise, in
            metres, ≥ 0.
        loop_rotation_deg: same as ``odometry_rotation_deg`` for the loop closure, ≥ 0.
        loop_translation: same as ``odometry_translation`` for the loop closure, ≥ 0.
        radius: mean radius of the loop in metres, > 0.
        seed: seed of the CPU ``torch.Generator`` everything is drawn from.
        dtype: float32 or float64 (default) of the returned tensors.
        device: device of the returned tensors.

    Returns:
        The :class:`LoopScene`; ``scene`` has B = 1, m = num_poses poses,
        n = (num_poses − 1) · points_per_frame points.

    Raises:
        ValueError: on an argument out of range.
        TypeError: on an argument of the wrong type or an unsupported dtype.
    """
    _check_arguments(
        num_poses,
        points_per_frame,
        window,
        noise_std,
        odometry_rotation_deg,
        odometry_translation,
        loop_rotation_deg,
        loop_translation,
        radius,
        seed,
        dtype,
        device,
    )
    gen = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    m, k = num_poses, points_per_frame
    n = (m - 1) * k

    # 1. Sensor rotations R_w (sensor → raw world) and positions c_w around one lap.
    R_w, c_w = _closed_loop(m, radius, gen)

    # 2. Points: k per birth frame 0, …, m − 2, at 1–4 m from its sensor in a random direction.
    birth = torch.arange(m - 1).repeat_interleave(k)  # (n,)
    direction = torch.randn(n, 3, generator=gen, dtype=f64)
    direction = direction / direction.norm(dim=-1, keepdim=True)
    low, high = _POINT_DISTANCE
    distance = low + (high - low) * torch.rand(n, 1, generator=gen, dtype=f64)
    X_w = c_w[birth] + distance * direction

    # 3. Visibility: frame i sees point j iff birth_j ≤ i < birth_j + window.
    frames = torch.arange(m)[:, None]
    seen = (frames >= birth) & (frames < birth + window)  # (m, n)

    # 4. Re-express in frame 0 (the gauge T_00 = I): T_i0 = W_i⁻¹ W_0, X_j ← W_0⁻¹ X_j.
    W = se3.from_rotation_translation(R_w, c_w)  # (m, 4, 4), sensor → raw world
    poses_gt = se3.inverse(W) @ W[:1]
    poses_gt[0] = torch.eye(4, dtype=f64)
    points_gt = se3.act(se3.inverse(W[0]), X_w)

    # 5. Edge list sorted by (pose, point) (nonzero is row-major), no padding.
    pose_index, point_index = seen.nonzero(as_tuple=True)
    E = pose_index.shape[0]
    noise = noise_std * torch.randn(E, 3, generator=gen, dtype=f64)
    observations = se3.act(poses_gt[pose_index], points_gt[point_index]) + noise

    # 6. Relative-pose measurements Z_ij = T_i0 T_j0⁻¹ · Exp(ε).
    odometry_pairs = torch.stack((torch.arange(m - 1), torch.arange(1, m)), dim=-1)
    loop_pairs = torch.tensor([[m - 1, 0]])
    odometry_rot, loop_rot = math.radians(odometry_rotation_deg), math.radians(loop_rotation_deg)
    odometry = _measure(poses_gt, odometry_pairs, odometry_rot, odometry_translation, gen)
    loop = _measure(poses_gt, loop_pairs, loop_rot, loop_translation, gen)

    def cast(x: Tensor) -> Tensor:
        return x.to(device=device, dtype=dtype if x.is_floating_point() else x.dtype)

    scene = SyntheticScene(
        poses_gt=cast(poses_gt[None]),
        points_gt=cast(points_gt[None]),
        pose_index=cast(pose_index[None]),
        point_index=cast(point_index[None]),
        observations=cast(observations[None]),
        valid=cast(torch.ones(1, E, dtype=torch.bool)),
        is_outlier=cast(torch.zeros(1, E, dtype=torch.bool)),
        noise_std=float(noise_std),
        seed=seed,
    )
    return LoopScene(
        scene=scene,
        odometry=cast(odometry),
        odometry_pairs=cast(odometry_pairs),
        loop=cast(loop),
        loop_pairs=cast(loop_pairs),
        birth_frame=cast(birth),
        window=window,
        odometry_rotation_std=odometry_rot,
        odometry_translation_std=float(odometry_translation),
        loop_rotation_std=loop_rot,
        loop_translation_std=float(loop_translation),
    )


def _check_arguments(
    num_poses: int,
    points_per_frame: int,
    window: int,
    noise_std: float,
    odometry_rotation_deg: float,
    odometry_translation: float,
    loop_rotation_deg: float,
    loop_translation: float,
    radius: float,
    seed: int,
    dtype: torch.dtype,
    device: torch.device | str | None,
) -> None:
    fn = "make_loop_scene"
    for name, value, minimum in (
        ("num_poses", num_poses, 3),
        ("points_per_frame", points_per_frame, 3),
        ("window", window, None),
    ):
        _checks.check_int(fn, name, value, minimum=minimum)
    _checks.check_seed(fn, seed)
    if not 2 <= window <= num_poses - 1:
        raise ValueError(
            f"{fn}: argument 'window' must be an int in [2, num_poses - 1] = "
            f"[2, {num_poses - 1}], got {window!r}"
        )
    entries = num_poses * (num_poses - 1) * points_per_frame
    if entries > MAX_TABLE_ENTRIES:
        raise ValueError(
            f"{fn}: num_poses · (num_poses - 1) · points_per_frame = {entries} exceeds "
            f"{MAX_TABLE_ENTRIES}: the generator builds a dense (m, n) visibility table; "
            "use fewer poses or points per frame"
        )
    for name, value, positive in (
        ("noise_std", noise_std, False),
        ("odometry_rotation_deg", odometry_rotation_deg, False),
        ("odometry_translation", odometry_translation, False),
        ("loop_rotation_deg", loop_rotation_deg, False),
        ("loop_translation", loop_translation, False),
        ("radius", radius, True),
    ):
        _checks.check_real(fn, name, value, low=0, low_open=positive)
    _checks.check_float_dtype(fn, dtype)
    _checks.check_device(fn, device)


def _closed_loop(m: int, radius: float, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    """Sensor rotations (m, 3, 3) and positions (m, 3) of one closed lap in the raw world.

    Sensors face the centre, x along the motion; the radius, height, pitch and roll wobble
    with integer frequencies per lap so that the trajectory is smooth across frame m-1 → 0.
    """
    f64 = torch.float64
    u = torch.rand(8, generator=gen, dtype=f64)
    heading = 2 * math.pi * u[0] + (2 * math.pi / m) * torch.arange(m, dtype=f64)
    phase = 2 * math.pi * u[1:5]
    r = radius * (1 + 0.1 * torch.sin(3 * heading + phase[0]))
    height = 0.1 * radius * torch.sin(2 * heading + phase[1])
    pitch = (0.05 + 0.1 * u[5]) * torch.sin(2 * heading + phase[2])
    roll = (0.05 + 0.1 * u[6]) * torch.sin(3 * heading + phase[3])
    cos, sin = torch.cos(heading), torch.sin(heading)
    positions = torch.stack((r * cos, r * sin, height), dim=-1)
    z_axis = torch.stack((-cos, -sin, torch.zeros_like(cos)), dim=-1)
    x_axis = torch.stack((-sin, cos, torch.zeros_like(cos)), dim=-1)
    y_axis = torch.linalg.cross(z_axis, x_axis)
    facing = torch.stack((x_axis, y_axis, z_axis), dim=-1)
    zeros = torch.zeros_like(pitch)
    R_pitch = so3.exp(torch.stack((zeros, pitch, zeros), dim=-1))
    R_roll = so3.exp(torch.stack((roll, zeros, zeros), dim=-1))
    return facing @ R_pitch @ R_roll, positions


def _measure(
    poses: Tensor, pairs: Tensor, rotation_std: float, translation_std: float, gen: torch.Generator
) -> Tensor:
    """Z_ij = T_i0 T_j0⁻¹ · Exp(ε) for each (i, j) of ``pairs`` (K, 2), shape (K, 4, 4)."""
    relative = poses[pairs[:, 0]] @ se3.inverse(poses[pairs[:, 1]])
    eps = torch.randn(pairs.shape[0], 6, generator=gen, dtype=poses.dtype)
    eps[:, :3] *= rotation_std
    eps[:, 3:] *= translation_std
    return relative @ se3.exp(eps)


def _information(fn: str, rotation_std: float, translation_std: float, like: Tensor) -> Tensor:
    if rotation_std <= 0 or translation_std <= 0:
        raise ValueError(
            f"LoopScene.{fn}: the noise stds must be > 0 to define an information matrix, "
            f"got rotation {rotation_std!r} rad and translation {translation_std!r} m"
        )
    diag = [rotation_std**-2] * 3 + [translation_std**-2] * 3
    return torch.diag(torch.tensor(diag, dtype=like.dtype, device=like.device))
