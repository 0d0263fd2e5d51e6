"""ICP-SLAM on a sequence: odometry, keyframes, loop closure, the back end, every frame's pose.

:class:`SLAM` is the streaming object: ``add(points, timestamp=None)`` registers a frame
(:class:`torchslam.slam.Odometry`) and returns its odometry pose; each new keyframe looks for
loop closures (:mod:`torchslam.slam.loops`); ``finish()`` runs the back end
(:mod:`torchslam.slam.backend`) and returns a :class:`SLAMResult` in which every frame's pose
follows its keyframe: T_wf = T̂_wk · (T_wk⁻¹ T_wf) with T_wk, T_wf the odometry poses and T̂_wk
the optimized keyframe pose. :func:`run_sequence` does the whole thing for a folder of frames
or a list of clouds.

Poses are **frame → world** (T_wf maps points of frame f into the world, the first frame's
sensor frame), as TUM and KITTI trajectory files hold them.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchslam import _checks
from torchslam.lie import se3
from torchslam.registration.quality import AlignmentQuality
from torchslam.slam.backend import BackendResult, optimize_keyframes
from torchslam.slam.config import SLAMConfig
from torchslam.slam.loops import LoopClosure, find_candidates, verify_loop
from torchslam.slam.odometry import FrameInfo, Keyframe, Odometry

__all__ = ["SLAM", "SLAMResult", "frame_reader", "run_sequence"]


@dataclass
class SLAMResult:
    """The trajectory of a sequence and what each stage did."""

    # T_wf of every frame in input order, (F, 4, 4), frame → world, after the back end
    poses: Tensor
    # the same from odometry alone, (F, 4, 4)
    odometry_poses: Tensor
    # timestamps (F,) float64, or None when no frame had one
    timestamps: Tensor | None
    # what odometry did with each frame
    frames: list[FrameInfo]
    # the frame index of each keyframe (K,), and their optimized poses (K, 4, 4)
    keyframe_frames: list[int]
    keyframe_poses: Tensor
    # marginal covariances of the keyframe poses (K, 6, 6), (ω, v), right perturbation, or None
    keyframe_covariances: Tensor | None
    # every verified loop candidate, accepted or not
    loops: list[LoopClosure]
    backend: BackendResult | None
    # wall seconds per stage: odometry, loops, pose_graph, refine, covariance
    seconds: dict[str, float] = field(default_factory=dict)
    config: SLAMConfig = field(default_factory=SLAMConfig)
    # the keyframes' clouds (sensor frame), for the map
    keyframe_clouds: list[Tensor] = field(default_factory=list, repr=False)

    @property
    def num_frames(self) -> int:
        return self.poses.shape[0]

    @property
    def accepted_loops(self) -> list[LoopClosure]:
        return [c for c in self.loops if c.accepted and c.kept]

    @property
    def rejected_loops(self) -> list[LoopClosure]:
        return [c for c in self.loops if not (c.accepted and c.kept)]

    def map_points(self, voxel: float | None = None) -> Tensor:
        """The keyframes' clouds at their optimized poses, merged on a voxel grid, (M, 3)."""
        from torchslam.registration.neighbors import voxel_downsample

        voxel = self.config.voxel if voxel is None else voxel
        if not self.keyframe_clouds:
            return torch.zeros(0, 3, dtype=torch.float64)
        world = [
            c @ T[:3, :3].T + T[:3, 3]
            for c, T in zip(self.keyframe_clouds, self.keyframe_poses, strict=True)
        ]
        return voxel_downsample(torch.cat(world), voxel)

    def summary(self) -> str:
        """A few lines: frames, keyframes, loop closures, costs, time per stage."""
        unreliable = sum(not f.trusted for f in self.frames)
        accepted = len(self.accepted_loops)
        lines = [
            f"frames {self.num_frames} ({unreliable} unreliable), keyframes "
            f"{len(self.keyframe_frames)}",
            f"loop closures: {len(self.loops)} verified, {accepted} accepted, "
            f"{len(self.loops) - accepted} rejected",
        ]
        if self.backend is not None:
            b = self.backend
            lines.append(
                f"pose graph: cost {b.graph_initial_cost:.6g} → {b.graph_final_cost:.6g} in "
                f"{b.graph_iterations} iterations; joint refinement: {b.refine_rounds} round(s), "
                f"cost {b.refine_cost:.6g}"
            )
        lines.append(
            "time: " + ", ".join(f"{name} {value:.2f} s" for name, value in self.seconds.items())
        )
        return "\n".join(lines)


class SLAM:
    """Streaming ICP-SLAM (module docstring).

    Args:
        config: options; ``SLAMConfig.for_sensor(sensor)`` when None.
        sensor: "depth" or "lidar" when ``config`` is None (default "lidar").

    Example::

        slam = SLAM(sensor="depth")
        for cloud, t in frames:
            slam.add(cloud, timestamp=t)  # odometry pose, (4, 4)
        result = slam.finish()  # result.poses: (F, 4, 4), frame → world
    """

    def __init__(self, config: SLAMConfig | None = None, *, sensor: str | None = None) -> None:
        self.odometry = Odometry(config, sensor=sensor, on_keyframe=self._on_keyframe)
        self.config = self.odometry.config
        self.loops: list[LoopClosure] = []
        self._positions: list[np.ndarray] = []
        self._path: list[float] = []
        self._cooldown_until = -1
        self._loop_seconds = 0.0
        self._finished = False

    @property
    def keyframes(self) -> list[Keyframe]:
        return self.odometry.keyframes

    def add(self, points: object, timestamp: float | None = None) -> Tensor:
        """Register the next frame (:meth:`Odometry.add`); returns its odometry pose T_wf."""
        if self._finished:
            raise RuntimeError("SLAM.add: finish() was called; start a new SLAM object")
        return self.odometry.add(points, timestamp)

    def _on_keyframe(self, keyframe: Keyframe) -> None:
        position = keyframe.pose[:3, 3].numpy().copy()
        step = float(np.linalg.norm(position - self._positions[-1])) if self._positions else 0.0
        self._positions.append(position)
        self._path.append((self._path[-1] if self._path else 0.0) + step)
        k = len(self._positions) - 1
        cfg = self.config
        if not cfg.loops or cfg.loop_candidates == 0 or k <= self._cooldown_until:
            return
        tic = time.perf_counter()
        candidates = find_candidates(np.array(self._positions), np.array(self._path), k, cfg)
        for j in candidates[: cfg.loop_candidates]:
            closure = verify_loop(self.keyframes, j, k, cfg)
            self.loops.append(closure)
            if closure.accepted:
                self._cooldown_until = k + cfg.loop_cooldown
                break
        self._loop_seconds += time.perf_counter() - tic

    def add_loop(
        self,
        first: int,
        second: int,
        *,
        measurement: object = None,
        information: object = None,
    ) -> LoopClosure:
        """A loop candidate between keyframes ``first`` < ``second`` given by hand (e.g. by a
        place-recognition front end).

        Without ``measurement`` it is verified by ICP like a detected one and joins the graph
        when accepted. With ``measurement`` (Z = T_first⁻¹ T_second, (4, 4)) it is forced into
        the graph unverified, with ``information`` ((6, 6), (ω, v); default: the mean of the
        odometry edges'); the back end's χ² test and robust kernel still judge it.
        """
        fn = "SLAM.add_loop"
        K = len(self.keyframes)
        first = _checks.check_int(fn, "first", first, minimum=0, maximum=K - 1)
        second = _checks.check_int(fn, "second", second, minimum=0, maximum=K - 1)
        if first >= second:
            raise ValueError(f"{fn}: need first < second, got {first} and {second}")
        if measurement is None:
            if information is not None:
                raise ValueError(f"{fn}: 'information' needs 'measurement'")
            closure = verify_loop(self.keyframes, first, second, self.config)
        else:
            Z = _checks.from_numpy(measurement)
            _checks.check_batched(fn, "measurement", Z, (), (4, 4))
            Z = Z.detach().to(torch.float64).cpu()
            _checks.check_pose_matrix(fn, "measurement", Z)
            if information is None:
                omega = torch.stack([kf.information for kf in self.keyframes[1:]]).mean(0)
            else:
                omega = _checks.from_numpy(information)
                _checks.check_batched(fn, "information", omega, (), (6, 6))
                omega = omega.detach().to(torch.float64).cpu()
                _checks.check_finite(fn, "information", omega)
            quality = AlignmentQuality(math.nan, math.nan, math.nan, 0, omega, None)
            closure = LoopClosure(first, second, Z, omega, quality, True, forced=True)
        self.loops.append(closure)
        return closure

    def finish(self) -> SLAMResult:
        """Run the back end and return the trajectory of every frame (module docstring)."""
        if not self.odometry.frames:
            raise ValueError("SLAM.finish: no frame was added")
        self._finished = True
        frames = self.odometry.frames
        odometry = self.odometry.poses
        seconds = {
            "odometry": sum(f.seconds for f in frames) - self._loop_seconds,
            "loops": self._loop_seconds,
        }
        backend = optimize_keyframes(self.keyframes, self.loops, self.config)
        seconds.update(backend.seconds)
        optimized = backend.poses
        keyframe_odometry = torch.stack([kf.pose for kf in self.keyframes])
        anchors = torch.tensor([f.anchor for f in frames])
        relative = se3.compose(se3.inverse(keyframe_odometry[anchors]), odometry)
        poses = se3.compose(optimized[anchors], relative)
        times = [f.timestamp for f in frames]
        timestamps = (
            torch.tensor([np.nan if t is None else t for t in times], dtype=torch.float64)
            if any(t is not None for t in times)
            else None
        )
        return SLAMResult(
            poses,
            odometry,
            timestamps,
            list(frames),
            [kf.frame for kf in self.keyframes],
            optimized,
            backend.covariances,
            list(self.loops),
            backend,
            seconds,
            self.config,
            [kf.points for kf in self.keyframes],
        )


Progress = Callable[[int, int], None]


def run_sequence(
    frames: str | os.PathLike | Sequence[object],
    config: SLAMConfig | None = None,
    *,
    sensor: str | None = None,
    intrinsics: object = None,
    depth_scale: float = 1000.0,
    timestamps: Sequence[float] | None = None,
    every: int = 1,
    progress: Callable[[Iterable], Iterable] | None = None,
) -> SLAMResult:
    """ICP-SLAM on a whole sequence in one call (what :class:`SLAM` does frame by frame).

    Args:
        frames: a folder of frames (:func:`torchslam.io.frames.list_frames`: every ``.png``
            for depth, every ``.pcd``/``.bin``/``.ply``/``.npy`` for LiDAR, sorted by name), or
            a sequence of clouds ((N_i, 3) tensors or arrays, sensor frame) or of file paths.
        config: options; ``SLAMConfig.for_sensor(sensor)`` when None.
        sensor: "depth" or "lidar"; inferred from the folder's files when None.
        intrinsics: depth frames only: a 3 × 3 K (or (fx, fy, cx, cy)) or a file holding K; by
            default the folder's ``camera-intrinsics.txt``.
        depth_scale: depth units per metre (1000: millimetres, as Open3D; TUM files use 5000).
        timestamps: one per frame (before ``every``); by default the folder's ``times.txt``
            when it has one.
        every: use every ``every``-th frame (≥ 1).
        progress: wraps the frame iterable (e.g. ``tqdm.tqdm``).

    Returns:
        :class:`SLAMResult`; ``poses`` has one pose per frame used (frame → world).
    """
    fn = "run_sequence"
    every = _checks.check_int(fn, "every", every, minimum=1)
    if config is not None and sensor is not None and sensor != config.sensor:
        raise ValueError(f"{fn}: 'sensor' {sensor!r} contradicts config.sensor {config.sensor!r}")
    loader, count, times, sensor = _frames(fn, frames, sensor, intrinsics, depth_scale, config)
    if timestamps is not None:
        times = np.asarray(timestamps, dtype=np.float64).reshape(-1)
        if times.shape[0] != count:
            raise ValueError(f"{fn}: {times.shape[0]} timestamps for {count} frames")
    if config is None:
        config = SLAMConfig.for_sensor(sensor or "lidar")
    slam = SLAM(config)
    indices: Iterable[int] = range(0, count, every)
    if progress is not None:
        indices = progress(indices)
    read_seconds = 0.0
    for i in indices:
        tic = time.perf_counter()
        cloud = loader(i)
        read_seconds += time.perf_counter() - tic
        slam.add(cloud, None if times is None else float(times[i]))
    result = slam.finish()
    result.seconds = {"read": read_seconds, **result.seconds}
    return result


def frame_reader(
    frames: str | os.PathLike | Sequence,
    config: SLAMConfig | None = None,
    *,
    sensor: str | None = None,
    intrinsics: object = None,
    depth_scale: float = 1000.0,
) -> tuple[Callable[[int], Tensor], int, np.ndarray | None, str | None]:
    """How :func:`run_sequence` reads a sequence: ``(read(i) → cloud (N, 3) in the sensor
    frame, number of frames, timestamps (before any ``every``) or None, sensor)``; arguments as
    :func:`run_sequence`. Depth frames are back-projected with the config's range and
    ``pixel_stride``."""
    return _frames("frame_reader", frames, sensor, intrinsics, depth_scale, config)


def _frames(fn, frames, sensor, intrinsics, depth_scale, config):
    """(loader(i) → cloud, count, timestamps or None, sensor)."""
    from torchslam.io import frames as frame_io

    if isinstance(frames, (str, os.PathLike)):
        folder = Path(frames)
        paths, found = frame_io.list_frames(folder, sensor)
        sensor = found
        times_path = frame_io.find_timestamps(paths[0].parent)
        times = None if times_path is None else frame_io.read_timestamps(times_path, len(paths))
    elif isinstance(frames, Sequence) and not isinstance(frames, (str, bytes)):
        if len(frames) == 0:
            raise ValueError(f"{fn}: argument 'frames' is empty")
        paths, times = list(frames), None
        if all(isinstance(p, (str, os.PathLike)) for p in paths):
            paths = [Path(p) for p in paths]
            if sensor is None:
                sensor = "depth" if paths[0].suffix.lower() == ".png" else "lidar"
    else:
        raise TypeError(
            f"{fn}: argument 'frames' must be a folder or a sequence of clouds or paths, got "
            f"{_checks.describe(frames)}"
        )
    if config is not None:
        sensor = sensor or config.sensor
    cfg = config or SLAMConfig.for_sensor(sensor or "lidar")
    K = None
    if sensor == "depth" and any(isinstance(p, Path) for p in paths):
        if intrinsics is None:
            found_k = frame_io.find_intrinsics(paths[0].parent)
            if found_k is None:
                raise ValueError(
                    f"{fn}: depth frames need intrinsics: pass 'intrinsics' (a 3×3 K, "
                    "(fx, fy, cx, cy) or a file) or put camera-intrinsics.txt beside the frames"
                )
            intrinsics = found_k
        if isinstance(intrinsics, (str, os.PathLike)):
            K = frame_io.read_intrinsics(intrinsics)
        else:
            K = frame_io.check_intrinsics(fn, intrinsics)

    def loader(i: int):
        item = paths[i]
        if not isinstance(item, Path):
            return item
        if item.suffix.lower() == ".png":
            return frame_io.read_depth(
                item, K, depth_scale=depth_scale, max_range=cfg.max_range,
                min_range=cfg.min_range, stride=cfg.pixel_stride,
            )  # fmt: skip
        return frame_io.read_points(item)

    return loader, len(paths), times, sensor
