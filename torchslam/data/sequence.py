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

__all__ = ["SyntheticSequence", "make_sequence"]


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
    poses = np.tile(np.eye(4), (frames, 1, 1))
    for f in range(frames):
        cz, sz = math.cos(yaw[f]), math.sin(yaw[f])
        cy, sy = math.cos(pitch[f]), math.sin(pitch[f])
        cx, sx = math.cos(roll[f]), math.sin(roll[f])
        Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
        Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
        Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
        poses[f, :3, :3] = Rz @ Ry @ Rx
        poses[f, :3, 3] = position[f]

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


def _nearest(table: np.ndarray, point: np.ndarray) -> np.ndarray:
    """The point of each rectangle (origin, u, v) nearest to ``point``, (S, 3)."""
    offset = point - table[:, 0]
    u, v = table[:, 1], table[:, 2]
    a = np.clip(np.einsum("si,si->s", offset, u) / np.einsum("si,si->s", u, u), 0, 1)
    b = np.clip(np.einsum("si,si->s", offset, v) / np.einsum("si,si->s", v, v), 0, 1)
    return table[:, 0] + a[:, None] * u + b[:, None] * v
