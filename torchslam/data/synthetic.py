"""Seeded synthetic ICP-SLAM scenes: trajectories, points, visibility, noise and outliers.

A scene is B independent problems with the same m poses and n points each. Conventions (the
seed's, kept across torchslam):

- ``poses_gt[b, i]`` is T_i0, mapping world (frame 0) points into frame i, T = [[R, t], [0, 1]],
  p' = R p + t; frame 0 is the origin: T_00 = I (the gauge). T_0i = T_i0⁻¹ is frame i's pose
  in the world, its translation the sensor position.
- ``points_gt[b, j]`` is X_j in the world (frame 0).
- An observation is X_ij = T_i0 X_j + ε with ε ~ N(0, noise_std² I₃) (seed eq. 0.1 plus noise);
  an outlier replaces it by T_i0 U with U uniform in the bounding box of the scene's points.

Units: metres. Trajectories have radius ~4 m (loop, helix) or steps of 0.5 m (random walk);
points lie 1–4 m from the sensor position of a random "anchor" frame in a uniformly random
direction (the sensor is a LiDAR-like 360° range sensor, as in the seed), so a noise std of
0.01 is 1 cm.

Observations are padded edge lists sorted by (pose, point) within each problem; problems may
have different numbers of observations E_b, padded to E = max_b E_b with ``valid`` False (the
padding has pose_index = point_index = 0 and zero observations, so it is safe to gather with).

Well-posedness is guaranteed deterministically (no resampling), in this order, by adding
visibility only (never removing it):

1. every pair of successive frames (i, i+1) shares ≥ 3 points (the 3 points closest to both
   sensors are added to both frames where needed), so the pose graph is a connected chain
   and the pairwise alignment of :mod:`torchslam.initialization` is always defined; this
   implies that every frame sees ≥ 3 points;
2. every point is seen by ≥ 2 frames (its 2 nearest frames are added where needed).

Generation is vectorized over B, m, n and observations (only the random-walk trajectory has a
loop over frames); everything is drawn on the CPU from one ``torch.Generator`` seeded with
``seed`` in float64, then cast, so a seed gives the same scene on every device and dtype.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Literal

import torch
from torch import Tensor

from torchslam import _checks
from torchslam.lie import se3, so3

__all__ = ["BENCHMARK_CASES", "SyntheticScene", "benchmark_case", "make_scene"]

Trajectory = Literal["loop", "helix", "random_walk"]
Visibility = Literal["fraction", "range"]

# Geometry of the generated scenes (metres).
_LOOP_RADIUS = 4.0  # mean radius of the loop and helix, jittered ±20% per problem
_HELIX_CLIMB = 0.1  # rise of the helix per frame
_WALK_STEP = 0.5  # distance between successive random-walk positions
_POINT_DISTANCE = (1.0, 4.0)  # range of a point's distance to its anchor frame's sensor
_MIN_SHARED = 3  # points shared by successive frames (guarantee 1)
_MIN_VIEWS = 2  # frames seeing each point (guarantee 2)
# Largest B·m·n of make_scene: its dense (B, m, n) tables and per-observation (B, E, 3, 3)
# rotations take about 10 GB of host memory there.
MAX_TABLE_ENTRIES = 5 * 10**7


@dataclass(frozen=True, eq=False)
class SyntheticScene:
    """A batch of B synthetic ICP-SLAM problems with ground truth.

    Shapes: B problems, m poses, n points, E = max_b E_b padded observations.
    """

    # Ground-truth poses T_i0 (world → frame i), T_00 = I, shape (B, m, 4, 4).
    poses_gt: Tensor
    # Ground-truth points X_j in the world (frame 0), shape (B, n, 3).
    points_gt: Tensor
    # Frame i of each observation, int64, shape (B, E); 0 on padding.
    pose_index: Tensor
    # Point j of each observation, int64, shape (B, E); 0 on padding.
    point_index: Tensor
    # Observed X_ij in frame i, shape (B, E, 3); 0 on padding.
    observations: Tensor
    # True for real observations, False for padding, shape (B, E).
    valid: Tensor
    # True where the observation was replaced by an outlier, shape (B, E).
    is_outlier: Tensor
    # Standard deviation of the isotropic Gaussian noise on inlier observations (metres).
    noise_std: float
    # Seed of the generator that produced the scene.
    seed: int

    @property
    def batch_size(self) -> int:
        """B, the number of problems."""
        return self.poses_gt.shape[0]

    @property
    def num_poses(self) -> int:
        """m, the number of poses per problem (frame 0 included)."""
        return self.poses_gt.shape[1]

    @property
    def num_points(self) -> int:
        """n, the number of points per problem."""
        return self.points_gt.shape[1]

    @property
    def num_observations(self) -> Tensor:
        """E_b, the number of real observations of each problem, int64, shape (B,)."""
        return self.valid.sum(-1)

    def to_dense(self) -> tuple[Tensor, Tensor]:
        """Dense form of the observations.

        Returns:
            (observations, visibility): X_ij of shape (B, m, n, 3), zero where not observed,
            and the bool visibility mask of shape (B, m, n).
        """
        B, m, n = self.batch_size, self.num_poses, self.num_points
        b, e = self.valid.nonzero(as_tuple=True)
        i, j = self.pose_index[b, e], self.point_index[b, e]
        dense = self.observations.new_zeros(B, m, n, 3)
        dense[b, i, j] = self.observations[b, e]
        visibility = torch.zeros(B, m, n, dtype=torch.bool, device=self.valid.device)
        visibility[b, i, j] = True
        return dense, visibility


def make_scene(
    num_poses: int,
    num_points: int,
    *,
    batch_size: int = 1,
    trajectory: Trajectory = "loop",
    visibility: Visibility = "fraction",
    visible_fraction: float = 0.3,
    max_range: float = 5.0,
    noise_std: float = 0.01,
    outlier_fraction: float = 0.0,
    rotation_per_frame_deg: float = 10.0,
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> SyntheticScene:
    """Generate B seeded synthetic ICP-SLAM problems (module docstring for the conventions).

    Trajectories (each problem gets its own random radius, phase and wobble):

    - ``"loop"``: sensors on a circle of radius ~4 m facing its centre, heading advancing by
      ``rotation_per_frame_deg`` per frame (so long sequences go round several times and revisit
      places), with pitch/roll wobble of 8–17° and a small vertical oscillation;
    - ``"helix"``: the loop rising 0.1 m per frame;
    - ``"random_walk"``: each relative rotation has angle exactly ``rotation_per_frame_deg``
      about a slowly varying random axis (a tumbling handheld sensor), steps of 0.5 m roughly
      along the sensor's z axis.

    Visibility:

    - ``"fraction"``: each point is seen by exactly k = max(2, round(visible_fraction · m))
      frames drawn uniformly without replacement, always including its anchor frame, so
      E_b ≈ visible_fraction · m · n (exact unless a guarantee adds observations);
    - ``"range"``: frame i sees point j iff the sensor of frame i is within ``max_range`` of it.

    Both are then completed by the module's two well-posedness guarantees, which only add
    observations. Outliers: round(outlier_fraction · E_b) observations per problem, drawn
    uniformly among the real ones, are replaced by T_i0 U with U uniform in the bounding box of
    the problem's points (``is_outlier`` marks them); they are not protected from breaking the
    guarantees (a point may be left with a single inlier view).

    Args:
        num_poses: m ≥ 2, poses per problem (frame 0 included).
        num_points: n ≥ 3, points per problem.
        batch_size: B ≥ 1, independent problems.
        trajectory: ``"loop"``, ``"helix"`` or ``"random_walk"``.
        visibility: ``"fraction"`` or ``"range"``.
        visible_fraction: fraction of frames seeing each point, in (0, 1] (``"fraction"``).
        max_range: sensor range in metres, > 0 (``"range"``).
        noise_std: std of the Gaussian observation noise in metres, ≥ 0.
        outlier_fraction: fraction of observations replaced by outliers, in [0, 1).
        rotation_per_frame_deg: heading change (loop, helix) or rotation angle (random walk)
            between successive frames, in degrees, ≥ 0.
        seed: seed of the CPU ``torch.Generator`` everything is drawn from, an int in
            [-2**63, 2**64 - 1].
        dtype: float32 or float64 (default) of the returned tensors.
        device: device of the returned tensors.

    Returns:
        The :class:`SyntheticScene`.

    Raises:
        ValueError: on an argument out of range (NaN included) or an unknown option name; a
            scene with B·m·n above :data:`MAX_TABLE_ENTRIES`; an unparsable device string.
        TypeError: on an argument of the wrong type (e.g. a float count or seed, a str number)
            or an unsupported dtype.
    """
    _check_arguments(
        num_poses,
        num_points,
        batch_size,
        trajectory,
        visibility,
        visible_fraction,
        max_range,
        noise_std,
        outlier_fraction,
        rotation_per_frame_deg,
        seed,
        dtype,
        device,
    )
    gen = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    B, m, n = batch_size, num_poses, num_points
    delta = math.radians(rotation_per_frame_deg)

    # 1. Sensor poses in a raw world frame: rotations R_wi (sensor → world), positions c_i.
    if trajectory == "random_walk":
        R_w, c_w = _random_walk(B, m, delta, gen)
    else:
        climb = _HELIX_CLIMB if trajectory == "helix" else 0.0
        R_w, c_w = _loop(B, m, delta, climb, gen)

    # 2. Points: a random anchor frame each, at 1–4 m from its sensor in a random direction.
    anchor = torch.randint(0, m, (B, n), generator=gen)
    direction = torch.randn(B, n, 3, generator=gen, dtype=f64)
    direction = direction / direction.norm(dim=-1, keepdim=True)
    low, high = _POINT_DISTANCE
    distance = low + (high - low) * torch.rand(B, n, 1, generator=gen, dtype=f64)
    X_w = torch.gather(c_w, 1, anchor[..., None].expand(B, n, 3)) + distance * direction

    # 3. Visibility (B, m, n), then the guarantees, which only add observations.
    sensor_distance = torch.cdist(c_w, X_w)  # (B, m, n)
    if visibility == "fraction":
        k = min(m, max(_MIN_VIEWS, round(visible_fraction * m)))
        keys = torch.rand(B, n, m, generator=gen, dtype=f64)
        keys.scatter_(-1, anchor[..., None], -1.0)  # the anchor frame always sees its point
        chosen = keys.topk(k, dim=-1, largest=False).indices
        seen = torch.zeros(B, n, m, dtype=torch.bool).scatter_(-1, chosen, True)
        seen = seen.transpose(1, 2)
    else:
        seen = sensor_distance <= max_range
    seen = _ensure_well_posed(seen, sensor_distance)

    # 4. Re-express in frame 0 (the gauge T_00 = I): T_i0 = W_i⁻¹ W_0, X_j ← W_0⁻¹ X_j.
    W = se3.from_rotation_translation(R_w, c_w)  # (B, m, 4, 4), sensor → raw world
    W0_inv = se3.inverse(W[:, :1])
    poses_gt = se3.inverse(W) @ W[:, :1]
    poses_gt[:, 0] = torch.eye(4, dtype=f64)  # exact identity, not round-off of W_0⁻¹ W_0
    points_gt = se3.act(W0_inv, X_w)

    # 5. Padded edge lists, sorted by (pose, point) because nonzero is row-major.
    pose_index, point_index, valid = _edge_lists(seen)
    E = valid.shape[1]

    # 6. Observations X_ij = T_i0 X_j + noise; padding stays zero.
    R_e = poses_gt[..., :3, :3].gather(1, pose_index[..., None, None].expand(B, E, 3, 3))
    t_e = poses_gt[..., :3, 3].gather(1, pose_index[..., None].expand(B, E, 3))
    X_e = points_gt.gather(1, point_index[..., None].expand(B, E, 3))
    noise = noise_std * torch.randn(B, E, 3, generator=gen, dtype=f64)
    observations = (R_e @ X_e[..., None]).squeeze(-1) + t_e + noise

    # 7. Outliers: exactly round(f · E_b) of the real observations of each problem.
    lower = points_gt.amin(dim=1, keepdim=True)
    upper = points_gt.amax(dim=1, keepdim=True)
    uniform = lower + (upper - lower) * torch.rand(B, E, 3, generator=gen, dtype=f64)
    keys = torch.rand(B, E, generator=gen, dtype=f64).masked_fill(~valid, 2.0)
    num_outliers = torch.round(outlier_fraction * valid.sum(-1).to(f64)).long()
    rank = torch.empty_like(pose_index).scatter_(
        -1, keys.argsort(dim=-1), torch.arange(E).expand(B, E).contiguous()
    )
    is_outlier = (rank < num_outliers[:, None]) & valid
    outliers = (R_e @ uniform[..., None]).squeeze(-1) + t_e
    observations = torch.where(is_outlier[..., None], outliers, observations)
    observations = observations.masked_fill(~valid[..., None], 0.0)

    def cast(x: Tensor) -> Tensor:
        return x.to(device=device, dtype=dtype if x.is_floating_point() else x.dtype)

    return SyntheticScene(
        poses_gt=cast(poses_gt),
        points_gt=cast(points_gt),
        pose_index=cast(pose_index),
        point_index=cast(point_index),
        observations=cast(observations),
        valid=cast(valid),
        is_outlier=cast(is_outlier),
        noise_std=float(noise_std),
        seed=seed,
    )


# The benchmark cases of issue 4; all use the defaults of make_scene otherwise (loop
# trajectory, 10° per frame, noise std 0.01 m).
BENCHMARK_CASES: MappingProxyType[str, MappingProxyType[str, Any]] = MappingProxyType(
    {
        "S": MappingProxyType({"num_poses": 10, "num_points": 200, "visible_fraction": 0.7}),
        "M": MappingProxyType({"num_poses": 50, "num_points": 1000, "visible_fraction": 0.3}),
        "L": MappingProxyType({"num_poses": 200, "num_points": 5000, "visible_fraction": 0.1}),
        "O": MappingProxyType(
            {
                "num_poses": 50,
                "num_points": 1000,
                "visible_fraction": 0.3,
                "outlier_fraction": 0.1,
            }
        ),
        "BATCH": MappingProxyType(
            {"num_poses": 10, "num_points": 200, "visible_fraction": 0.7, "batch_size": 64}
        ),
    }
)


def benchmark_case(
    name: Literal["S", "M", "L", "O", "BATCH"],
    seed: int = 0,
    *,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> SyntheticScene:
    """The named benchmark scene of issue 4 (parameters in :data:`BENCHMARK_CASES`).

    - ``"S"``: m = 10, n = 200, 70% visibility (E = 1,400);
    - ``"M"``: m = 50, n = 1,000, 30% (E = 15,000);
    - ``"L"``: m = 200, n = 5,000, 10% (E = 100,000);
    - ``"O"``: M with 10% of the observations replaced by outliers;
    - ``"BATCH"``: 64 independent S problems (B = 64).

    All: loop trajectory with 10° heading change per frame, noise std 0.01 m, ``"fraction"``
    visibility (E exact unless a well-posedness guarantee adds observations).

    Args:
        name: the case.
        seed: generator seed.
        dtype: float32 or float64 (default).
        device: device of the returned tensors.

    Returns:
        The :class:`SyntheticScene`.
    """
    if name not in BENCHMARK_CASES:
        raise ValueError(
            f"benchmark_case: argument 'name' must be one of {sorted(BENCHMARK_CASES)}, "
            f"got {name!r}"
        )
    return make_scene(**BENCHMARK_CASES[name], seed=seed, dtype=dtype, device=device)


def _check_arguments(
    num_poses: int,
    num_points: int,
    batch_size: int,
    trajectory: str,
    visibility: str,
    visible_fraction: float,
    max_range: float,
    noise_std: float,
    outlier_fraction: float,
    rotation_per_frame_deg: float,
    seed: int,
    dtype: torch.dtype,
    device: torch.device | str | None,
) -> None:
    fn = "make_scene"
    for name, value, minimum in (
        ("num_poses", num_poses, 2),
        ("num_points", num_points, 3),
        ("batch_size", batch_size, 1),
    ):
        _checks.check_int(fn, name, value, minimum=minimum)
    entries = batch_size * num_poses * num_points
    if entries > MAX_TABLE_ENTRIES:
        raise ValueError(
            f"{fn}: batch_size · num_poses · num_points = {batch_size} · {num_poses} · "
            f"{num_points} = {entries} exceeds {MAX_TABLE_ENTRIES}: the generator builds dense "
            "(B, m, n) visibility and distance tables (tens of GB at that size); generate "
            "smaller scenes or several batches"
        )
    if trajectory not in ("loop", "helix", "random_walk"):
        raise ValueError(
            f"{fn}: argument 'trajectory' must be 'loop', 'helix' or 'random_walk', "
            f"got {trajectory!r}"
        )
    if visibility not in ("fraction", "range"):
        raise ValueError(
            f"{fn}: argument 'visibility' must be 'fraction' or 'range', got {visibility!r}"
        )
    for name, value, low, high, low_open, high_open, expected in (
        ("visible_fraction", visible_fraction, 0, 1, True, False, "in (0, 1]"),
        ("max_range", max_range, 0, None, True, False, "> 0"),
        ("noise_std", noise_std, 0, None, False, False, ">= 0"),
        ("outlier_fraction", outlier_fraction, 0, 1, False, True, "in [0, 1)"),
        ("rotation_per_frame_deg", rotation_per_frame_deg, 0, None, False, False, ">= 0"),
    ):
        try:  # TypeError for a non-number; ValueError (reworded here) for NaN, Inf, range
            _checks.check_real(
                fn, name, value, low=low, high=high, low_open=low_open, high_open=high_open
            )
        except ValueError:
            raise ValueError(
                f"{fn}: argument '{name}' must be {expected} (finite), got {value!r}"
            ) from None
    _checks.check_seed(fn, seed)
    _checks.check_float_dtype(fn, dtype)
    _checks.check_device(fn, device)


def _rotation_about(axis: int, angle: Tensor) -> Tensor:
    """Rotations by ``angle`` (...,) about coordinate axis 0, 1 or 2, shape (..., 3, 3)."""
    omega = torch.zeros(*angle.shape, 3, dtype=angle.dtype)
    omega[..., axis] = angle
    return so3.exp(omega)


def _loop(
    B: int, m: int, delta: float, climb: float, gen: torch.Generator
) -> tuple[Tensor, Tensor]:
    """Loop/helix sensor rotations (B, m, 3, 3) and positions (B, m, 3) in the raw world."""
    f64 = torch.float64
    u = torch.rand(B, 8, generator=gen, dtype=f64)
    radius = _LOOP_RADIUS * (0.8 + 0.4 * u[:, :1])
    heading = 2 * math.pi * u[:, 1:2] + delta * torch.arange(m, dtype=f64)  # (B, m)
    pitch = (0.15 + 0.15 * u[:, 2:3]) * torch.sin(1.5 * heading + 2 * math.pi * u[:, 3:4])
    roll = (0.15 + 0.15 * u[:, 4:5]) * torch.sin(2.5 * heading + 2 * math.pi * u[:, 5:6])
    height = 0.3 * torch.sin(2 * heading + 2 * math.pi * u[:, 6:7])
    height = height + climb * torch.arange(m, dtype=f64)
    cos, sin = torch.cos(heading), torch.sin(heading)
    positions = torch.stack((radius * cos, radius * sin, height), dim=-1)
    # Sensor axes in the world: z towards the centre, x along the motion, y = z × x (down).
    z_axis = torch.stack((-cos, -sin, torch.zeros_like(cos)), dim=-1)
    x_axis = torch.stack((-sin, cos, torch.zeros_like(cos)), dim=-1)
    y_axis = torch.linalg.cross(z_axis, x_axis)
    facing = torch.stack((x_axis, y_axis, z_axis), dim=-1)
    R = facing @ _rotation_about(1, pitch) @ _rotation_about(0, roll)
    return R, positions


def _random_walk(B: int, m: int, delta: float, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    """Random-walk sensor rotations (B, m, 3, 3) and positions (B, m, 3) in the raw world."""
    f64 = torch.float64
    axis_noise = torch.randn(B, m, 3, generator=gen, dtype=f64)
    step_noise = torch.randn(B, m, 3, generator=gen, dtype=f64)
    # A slowly varying unit axis: each step nudges the previous one.
    axes = [axis_noise[:, 0] / axis_noise[:, 0].norm(dim=-1, keepdim=True)]
    for i in range(1, m):
        a = axes[-1] + 0.5 * axis_noise[:, i]
        axes.append(a / a.norm(dim=-1, keepdim=True))
    increments = so3.exp(delta * torch.stack(axes, dim=1))  # (B, m, 3, 3), [0] unused
    forward = torch.tensor([0.0, 0.0, 1.0], dtype=f64) + 0.3 * step_noise
    forward = _WALK_STEP * forward / forward.norm(dim=-1, keepdim=True)
    rotations = [torch.eye(3, dtype=f64).expand(B, 3, 3)]
    positions = [torch.zeros(B, 3, dtype=f64)]
    for i in range(1, m):
        positions.append(positions[-1] + (rotations[-1] @ forward[:, i, :, None]).squeeze(-1))
        rotations.append(rotations[-1] @ increments[:, i])
    return torch.stack(rotations, dim=1), torch.stack(positions, dim=1)


def _ensure_well_posed(seen: Tensor, sensor_distance: Tensor) -> Tensor:
    """Add visibility so that the guarantees of the module docstring hold (B, m, n) bool."""
    B, m, n = seen.shape
    # 1. Successive frames share ≥ 3 points: add the points closest to both sensors.
    shared = (seen[:, :-1] & seen[:, 1:]).sum(-1)  # (B, m-1)
    pair_score = sensor_distance[:, :-1] + sensor_distance[:, 1:]
    closest = pair_score.topk(_MIN_SHARED, dim=-1, largest=False).indices
    add = torch.zeros(B, m - 1, n, dtype=torch.bool).scatter_(-1, closest, True)
    add &= (shared < _MIN_SHARED)[..., None]
    seen = seen.clone()
    seen[:, :-1] |= add
    seen[:, 1:] |= add
    # 2. Every point is seen by ≥ 2 frames: add its nearest frames.
    views = seen.sum(1)  # (B, n)
    nearest = sensor_distance.topk(_MIN_VIEWS, dim=1, largest=False).indices
    add = torch.zeros(B, m, n, dtype=torch.bool).scatter_(1, nearest, True)
    add &= (views < _MIN_VIEWS)[:, None, :]
    return seen | add


def _edge_lists(seen: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Padded (pose_index, point_index, valid), each (B, E), from visibility (B, m, n)."""
    B, m, n = seen.shape
    flat = seen.reshape(B, m * n)
    counts = flat.sum(-1)
    E = int(counts.max())
    b, k = flat.nonzero(as_tuple=True)  # row-major: sorted by (b, pose, point)
    start = torch.cumsum(counts, 0) - counts
    position = torch.arange(b.shape[0]) - start[b]
    pose_index = torch.zeros(B, E, dtype=torch.long)
    point_index = torch.zeros(B, E, dtype=torch.long)
    valid = torch.zeros(B, E, dtype=torch.bool)
    pose_index[b, position] = k // n
    point_index[b, position] = k % n
    valid[b, position] = True
    return pose_index, point_index, valid
