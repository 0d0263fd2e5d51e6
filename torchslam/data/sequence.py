"""A synthetic range-sensor sequence: a room with pillars scanned along a closed loop.

The scene is a box room (floor, ceiling, four walls; 4:3, so that only a half turn maps it onto
itself) with square pillars and two large crates against the walls at seeded places (they break
that symmetry: a place seen from the far side of the room does not look the same);
the sensor (LiDAR-like: points all around it) moves along a circle around the room's centre,
heading along the path, with a small vertical wobble and tilt, for ``turns`` turns (more
than 1: the end revisits the start, a loop to close). Each frame samples fresh points
uniformly on the surfaces within ``max_range`` (no occlusion), adds Gaussian noise and
expresses them in the sensor frame, so that no two frames share a point.

Poses are **frame → world** (T_wf: p_world = R p_f + t), in the scene's world frame (not the
first frame's; compare after an SE(3) alignment, or map by ``poses[0]⁻¹``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from torchslam import _checks

__all__ = ["SyntheticDepthSequence", "SyntheticSequence", "make_depth_sequence", "make_sequence"]


@dataclass(frozen=True)
class SyntheticSequence:
    """Frames of :func:`make_sequence`."""

    # each frame's points in its sensor frame, (N_f, 3) float64
    clouds: list[Tensor]
    # T_wf of each frame, (F, 4, 4), frame → world
    poses: Tensor
    # the rectangles of the scene: origin, edge u, edge v, (S, 3, 3) (rows)
    surfaces: Tensor


def _box_faces(low: np.ndarray, high: np.ndarray, caps: bool) -> list[np.ndarray]:
    x0, y0, z0 = low
    x1, y1, z1 = high
    dx, dy, dz = high - low
    faces = [
        [[x0, y0, z0], [dx, 0, 0], [0, 0, dz]],
        [[x0, y1, z0], [dx, 0, 0], [0, 0, dz]],
        [[x0, y0, z0], [0, dy, 0], [0, 0, dz]],
        [[x1, y0, z0], [0, dy, 0], [0, 0, dz]],
    ]
    if caps:
        faces += [[[x0, y0, z0], [dx, 0, 0], [0, dy, 0]], [[x0, y0, z1], [dx, 0, 0], [0, dy, 0]]]
    return [np.array(f, dtype=np.float64) for f in faces]


def make_sequence(
    frames: int = 40,
    *,
    radius: float = 4.0,
    turns: float = 1.15,
    room: float = 16.0,
    height: float = 4.0,
    pillars: int = 8,
    crates: int = 2,
    points_per_frame: int = 4000,
    noise: float = 0.01,
    max_range: float = 12.0,
    seed: int = 0,
) -> SyntheticSequence:
    """A room scanned along a loop (module docstring).

    Args:
        frames: number of frames F ≥ 2.
        radius: radius of the circular path (m).
        turns: turns of the path (> 1 revisits the start).
        room: length of the room (m; its width is 3/4 of it); the sensor moves at mid-height.
        height: room height (m).
        pillars: number of 0.6 m square pillars, placed away from the path.
        crates: number of 3 × 1.2 × 1.5 m crates, against the long walls.
        points_per_frame: points sampled on the surfaces per frame (before the range crop).
        noise: standard deviation of the Gaussian noise on each coordinate (m).
        max_range: points farther from the sensor are dropped (m).
        seed: seeds the scene, the path's wobble and the sampling.
    """
    fn = "make_sequence"
    frames = _checks.check_int(fn, "frames", frames, minimum=2)
    points_per_frame = _checks.check_int(fn, "points_per_frame", points_per_frame, minimum=10)
    pillars = _checks.check_int(fn, "pillars", pillars, minimum=0)
    crates = _checks.check_int(fn, "crates", crates, minimum=0)
    for name, value in (("radius", radius), ("room", room), ("height", height)):
        _checks.check_real(fn, name, value, low=0.0, low_open=True)
    _checks.check_real(fn, "turns", turns, low=0.0, low_open=True)
    _checks.check_real(fn, "noise", noise, low=0.0)
    _checks.check_real(fn, "max_range", max_range, low=0.0, low_open=True)
    half = np.array([room / 2, 0.375 * room])
    if not radius + 1.5 < half[1]:
        raise ValueError(
            f"{fn}: the path (radius {radius:g}) must fit in the room ({room:g} × "
            f"{2 * half[1]:g}) with 1.5 m to spare"
        )
    rng = np.random.default_rng(_checks.check_seed(fn, seed))
    surfaces = _box_faces(np.array([*-half, 0.0]), np.array([*half, height]), True)
    for k in range(crates):
        x = rng.uniform(-half[0] + 0.5, half[0] - 3.5)
        y = half[1] - 1.2 if k % 2 == 0 else -half[1]
        low = np.array([x, y, 0.0])
        surfaces += _box_faces(low, low + np.array([3.0, 1.2, 1.5]), True)
    placed = 0
    while placed < pillars:
        centre = rng.uniform(-half + 1.0, half - 1.0)
        if abs(np.linalg.norm(centre) - radius) < 1.5 or abs(centre[1]) > half[1] - 1.5:
            continue  # keep the path and the crates clear
        low = np.array([*(centre - 0.3), 0.0])
        surfaces += _box_faces(low, low + np.array([0.6, 0.6, height]), False)
        placed += 1
    table = np.stack(surfaces)
    areas = np.linalg.norm(np.cross(table[:, 1], table[:, 2]), axis=1)

    angle = 2 * math.pi * turns * np.arange(frames) / frames
    wobble = rng.uniform(0, 2 * math.pi, size=3)
    position = np.stack(
        [
            radius * np.cos(angle),
            radius * np.sin(angle),
            height / 2 + 0.1 * np.sin(3 * angle + wobble[0]),
        ],
        axis=1,
    )
    yaw = angle + math.pi / 2
    roll = 0.03 * np.sin(2 * angle + wobble[1])
    pitch = 0.03 * np.sin(5 * angle + wobble[2])
    poses = _poses(position, yaw, pitch, roll)

    clouds = []
    for f in range(frames):
        # Sample the surfaces within range of the sensor, by area, then crop to the range.
        near = np.linalg.norm(_nearest(table, position[f]) - position[f], axis=1) <= max_range
        weights = np.where(near, areas, 0.0)
        which = rng.choice(len(table), size=points_per_frame, p=weights / weights.sum())
        a, b = rng.uniform(size=(2, points_per_frame, 1))
        world = table[which, 0] + a * table[which, 1] + b * table[which, 2]
        world += rng.normal(scale=noise, size=world.shape) if noise > 0 else 0.0
        local = (world - poses[f, :3, 3]) @ poses[f, :3, :3]
        local = local[np.linalg.norm(local, axis=1) <= max_range]
        clouds.append(torch.from_numpy(np.ascontiguousarray(local)))
    return SyntheticSequence(clouds, torch.from_numpy(poses), torch.from_numpy(table))


def _poses(
    position: np.ndarray,
    yaw: np.ndarray,
    pitch: np.ndarray,
    roll: np.ndarray,
    axes: np.ndarray | None = None,
) -> np.ndarray:
    """Frame → world poses (F, 4, 4) with R = Rz(yaw) Ry(pitch) Rx(roll) [· axes] (z up; a
    positive pitch turns the x axis down) and translation ``position`` (F, 3)."""
    poses = np.tile(np.eye(4), (len(position), 1, 1))
    for f in range(len(position)):
        cz, sz = math.cos(yaw[f]), math.sin(yaw[f])
        cy, sy = math.cos(pitch[f]), math.sin(pitch[f])
        cx, sx = math.cos(roll[f]), math.sin(roll[f])
        Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
        Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
        Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
        poses[f, :3, :3] = Rz @ Ry @ Rx if axes is None else Rz @ Ry @ Rx @ axes
        poses[f, :3, 3] = position[f]
    return poses


def _nearest(table: np.ndarray, point: np.ndarray) -> np.ndarray:
    """The point of each rectangle (origin, u, v) nearest to ``point``, (S, 3)."""
    offset = point - table[:, 0]
    u, v = table[:, 1], table[:, 2]
    a = np.clip(np.einsum("si,si->s", offset, u) / np.einsum("si,si->s", u, u), 0, 1)
    b = np.clip(np.einsum("si,si->s", offset, v) / np.einsum("si,si->s", v, v), 0, 1)
    return table[:, 0] + a[:, None] * u + b[:, None] * v


@dataclass(frozen=True)
class SyntheticDepthSequence:
    """Frames of :func:`make_depth_sequence`, rendered on demand (:meth:`depth`, :meth:`cloud`):
    a thousand 640 × 480 images would hold 600 MB."""

    # T_wc of each frame, (F, 4, 4), camera → world; the camera frame is the pinhole one
    # (x right, y down, z forward; torchslam.io.frames)
    poses: Tensor
    # K (3, 3), pixels, of the full-size image
    intrinsics: Tensor
    # image size (H, W), pixels
    size: tuple[int, int]
    # the rectangles of the scene: origin, edge u, edge v, (S, 3, 3) (rows)
    surfaces: Tensor
    # axial depth noise: standard deviation noise·z² (m, z in m)
    noise: float
    # depths beyond this (m) read as no return (0)
    max_range: float
    seed: int

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    def depth(self, index: int, stride: int = 1) -> np.ndarray:
        """Frame ``index``'s depth image in millimetres, uint16, 0 where there is no return
        (beyond ``max_range``, or no surface): every ``stride``-th row and column of the full
        image, (⌈H/stride⌉, ⌈W/stride⌉) (the pixels u = stride·u′, v = stride·v′). The
        same bits for the same (index, stride) on every call."""
        fn = "SyntheticDepthSequence.depth"
        index = _checks.check_int(fn, "index", index, minimum=0)
        if index >= len(self):
            raise ValueError(f"{fn}: argument 'index' must be < {len(self)}, got {index}")
        stride = _checks.check_int(fn, "stride", stride, minimum=1)
        height, width = self.size
        v, u = np.mgrid[0:height:stride, 0:width:stride].astype(np.float64)
        K = self.intrinsics.numpy()
        # ray directions in the camera frame with z = 1, so that the ray parameter is the depth
        rays = np.stack(((u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)), -1)
        T = self.poses[index].numpy()
        z = _cast(self.surfaces.numpy(), T[:3, 3], rays.reshape(-1, 3) @ T[:3, :3].T)
        rng = np.random.default_rng((self.seed, index, stride))
        z = z + rng.normal(size=z.shape) * self.noise * np.where(np.isfinite(z), z, 0.0) ** 2
        valid = np.isfinite(z) & (z > 0) & (z <= self.max_range)
        millimetres = np.where(valid, np.round(np.where(valid, z, 0.0) * 1000.0), 0.0)
        return millimetres.clip(0, 65534).astype(np.uint16).reshape(u.shape)

    def cloud(self, index: int, stride: int = 4, min_range: float = 0.2) -> Tensor:
        """Frame ``index``'s points in its camera frame (:meth:`depth` back-projected by
        :func:`torchslam.io.frames.depth_to_points`), (N, 3) float64."""
        from torchslam.io.frames import depth_to_points

        K = self.intrinsics.clone()
        K[:2] /= stride  # pixel u = stride·u′: fx′ = fx/stride, cx′ = cx/stride
        return depth_to_points(self.depth(index, stride), K, min_range=min_range)


def _cast(table: np.ndarray, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Ray parameter t ≥ 0 of the nearest rectangle (origin, u, v rows of ``table``, (S, 3, 3))
    hit by each ray origin + t·direction, (R,); inf where none is hit."""
    corner, u, v = table[:, 0], table[:, 1], table[:, 2]
    normal = np.cross(u, v)
    offset = origin - corner  # (S, 3)
    along = directions @ normal.T  # (R, S)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -(offset * normal).sum(1) / along
        a = ((offset * u).sum(1) + t * (directions @ u.T)) / (u * u).sum(1)
        b = ((offset * v).sum(1) + t * (directions @ v.T)) / (v * v).sum(1)
    hit = (t > 1e-9) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)
    return np.where(hit, t, np.inf).min(1)


def make_depth_sequence(
    frames: int = 300,
    *,
    radius: float = 0.8,
    turns: float = 1.2,
    room: float = 6.0,
    height: float = 2.6,
    boxes: int = 10,
    pillars: int = 2,
    size: tuple[int, int] = (480, 640),
    focal: float = 525.0,
    pitch_deg: float = 15.0,
    noise: float = 0.0015,
    max_range: float = 4.0,
    seed: int = 0,
) -> SyntheticDepthSequence:
    """A room scanned by a hand-held depth camera walking a loop, looking at the walls.

    The room is a box (floor, ceiling, walls; 4:3) with ``boxes`` pieces of furniture against
    the walls and ``pillars`` square pillars, at seeded places and sizes (they make each view
    distinct: bare walls would leave a camera free to slide along them). The camera circles the
    room's centre at ``radius``, facing outward (towards the walls, 1.5–3 m away) and tilted
    down by ``pitch_deg`` (it sees the floor too), with a small wobble in height, radius,
    heading and roll, for ``turns`` turns (more than 1: the end revisits the start, a loop to
    close). Each frame is ray-cast at the pixel centres of a pinhole camera (K with ``focal``
    and the image centre), with occlusion, Kinect-like axial noise of standard deviation
    ``noise``·z² (1.5 mm at 1 m, 6 mm at 2 m by default) and millimetre quantization; depths
    beyond ``max_range`` read 0 (no return), as a sensor's do. With the defaults a frame
    moves about 2 cm and turns about 1.4°, a 30 Hz camera carried at a slow walk.

    Poses are **camera → world** (T_wc: p_world = R p_c + t), in the scene's world frame
    (z up; compare after an SE(3) alignment).
    """
    fn = "make_depth_sequence"
    frames = _checks.check_int(fn, "frames", frames, minimum=2)
    boxes = _checks.check_int(fn, "boxes", boxes, minimum=0)
    pillars = _checks.check_int(fn, "pillars", pillars, minimum=0)
    for name, value in (("radius", radius), ("room", room), ("height", height)):
        _checks.check_real(fn, name, value, low=0.0, low_open=True)
    _checks.check_real(fn, "turns", turns, low=0.0, low_open=True)
    _checks.check_real(fn, "focal", focal, low=0.0, low_open=True)
    _checks.check_real(fn, "pitch_deg", pitch_deg, low=-80.0, high=80.0)
    _checks.check_real(fn, "noise", noise, low=0.0)
    _checks.check_real(fn, "max_range", max_range, low=0.0, low_open=True)
    if not (
        isinstance(size, tuple | list)
        and len(size) == 2
        and all(isinstance(s, int) and not isinstance(s, bool) and s >= 2 for s in size)
    ):
        raise ValueError(f"{fn}: argument 'size' must be (H, W), two ints ≥ 2, got {size!r}")
    half = np.array([room / 2, 0.375 * room])
    if not radius + 1.0 < half[1]:
        raise ValueError(
            f"{fn}: the path (radius {radius:g}) must fit in the room ({room:g} × "
            f"{2 * half[1]:g}) with 1 m to spare"
        )
    rng = np.random.default_rng(_checks.check_seed(fn, seed))
    surfaces = _box_faces(np.array([*-half, 0.0]), np.array([*half, height]), True)
    for _ in range(boxes):  # furniture against a wall: width along it, depth, height
        extent = rng.uniform((0.4, 0.3, 0.4), (1.2, 0.8, 1.8))
        wall = int(rng.integers(4))
        along_x = wall < 2
        length = 2 * half[0] if along_x else 2 * half[1]
        start = rng.uniform(0.0, length - extent[0]) - length / 2
        if along_x:
            y = half[1] - extent[1] if wall == 0 else -half[1]
            low = np.array([start, y, 0.0])
            high = low + np.array([extent[0], extent[1], extent[2]])
        else:
            x = half[0] - extent[1] if wall == 2 else -half[0]
            low = np.array([x, start, 0.0])
            high = low + np.array([extent[1], extent[0], extent[2]])
        surfaces += _box_faces(low, high, True)
    placed = 0
    while placed < pillars:
        centre = rng.uniform(-half + 0.5, half - 0.5)
        if np.linalg.norm(centre) < radius + 0.6:
            continue  # keep the path clear
        low = np.array([*(centre - 0.15), 0.0])
        surfaces += _box_faces(low, low + np.array([0.3, 0.3, height]), False)
        placed += 1
    table = np.stack(surfaces)

    angle = 2 * math.pi * turns * np.arange(frames) / frames
    phase = rng.uniform(0, 2 * math.pi, size=5)
    reach = radius * (1.0 + 0.15 * np.sin(1.7 * angle + phase[0]))
    position = np.stack(
        [
            reach * np.cos(angle),
            reach * np.sin(angle),
            1.4 + 0.08 * np.sin(2.3 * angle + phase[1]),
        ],
        axis=1,
    )
    yaw = angle + 0.25 * np.sin(1.3 * angle + phase[2])
    pitch = math.radians(pitch_deg) + 0.05 * np.sin(2.9 * angle + phase[3])
    roll = 0.04 * np.sin(3.1 * angle + phase[4])
    # camera axes (x right, y down, z forward) in the body frame (x forward, y left, z up)
    optical = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    poses = _poses(position, yaw, pitch, roll, optical)
    H, W = (int(s) for s in size)
    K = torch.tensor([[focal, 0.0, (W - 1) / 2], [0.0, focal, (H - 1) / 2], [0.0, 0.0, 1.0]])
    return SyntheticDepthSequence(
        torch.from_numpy(poses), K.to(torch.float64), (H, W), torch.from_numpy(table),
        float(noise), float(max_range), int(seed),
    )  # fmt: skip
