"""Frame-to-model odometry of a moving range sensor (depth camera or LiDAR).

For each frame (points in the sensor frame):

1. points nearer than ``min_range`` or farther than ``max_range`` are dropped, the rest
   voxel-downsampled (``voxel``);
2. the pose is predicted at constant velocity, T̂_k = T_(k−1)·(T_(k−2)⁻¹ T_(k−1));
3. point-to-plane ICP (:mod:`torchslam.registration.icp`, the library's one ICP loop, with a
   Cauchy kernel) registers the frame against the local map (:class:`LocalMap`, the newest
   keyframes' clouds and normals near the sensor), from T̂_k, with a correspondence gate that
   follows the observed motion: 3σ of the past prediction errors, each measured as the
   RMS displacement of the frame's points between the prediction and the estimate (the
   adaptive threshold of KISS-ICP, measured on the points instead of at a lever arm); a
   gate wider than 1.5× the judging gate is followed by a run at the judging gate (with
   ``coarse_rotation_only``, the wide run only turns the frame about the sensor);
4. alternative starts (``start_rotation_deg`` > 0): the prediction, the last pose (zero
   velocity) and the prediction turned by ±``start_rotation_deg`` about each sensor axis
   of ``start_axes``
   are registered together (one batched ICP at the judging gate, on ``screen_points`` of
   the frame, ``screen_iterations`` passes) and
   scored, with the main alignment, by their tight overlap: the fraction of the sample with
   a map point within ``screen_voxels`` voxels. When the best start beats the main alignment
   by more than ``screen_margin``, it is refined on the whole frame and replaces the main
   alignment if it still wins and is trusted (:attr:`FrameInfo.start` says which start won).
   This catches the main ICP settling in a wrong basin when the prediction's rotation is off
   by degrees (hand-held keyframes): a wide gate then lets the map's structure pull the frame
   along a weakly constrained direction by a metre while overlap and RMS still look good;
5. the alignment is judged (:func:`torchslam.registration.quality.alignment_quality`:
   overlap and residual RMS of the correspondences within 3 voxels, conditioning). An
   untrusted one is retried with a 3× wider gate from the prediction and from the last pose
   (zero velocity), each retry the two-stage registration of step 3 (its wide stage turning
   the frame only, by default); when no attempt is trusted the frame
   is marked ``UNRELIABLE`` (its pose the best attempt's) and never becomes a keyframe;
6. a frame becomes a keyframe when it moved more than ``keyframe_translation`` or turned
   more than ``keyframe_rotation_deg`` since the last keyframe; keyframes enter the local map
   and the back end (:class:`torchslam.slam.SLAM`).

Poses are **frame → world** (T_wk maps points of frame k into the world; frame 0 is the world),
as TUM and KITTI trajectory files hold them.
"""

from __future__ import annotations

import enum
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from torchslam import _checks
from torchslam.lie import se3, so3
from torchslam.registration import icp as _icp
from torchslam.registration import quality as _quality
from torchslam.registration.config import RegisterConfig
from torchslam.registration.kdtree import KDTree
from torchslam.registration.neighbors import (
    _boundary_from_neighbours,
    _downsample,
    _host,
    _Matcher,
    _normals_and_neighbours,
    _query_host,
)
from torchslam.registration.quality import AlignmentQuality, QualityThresholds
from torchslam.slam.config import SLAMConfig
from torchslam.slam.local_map import LocalMap

__all__ = ["FrameInfo", "FrameStatus", "Keyframe", "Odometry"]

# Fewer points than this after range cropping and downsampling: the frame is not registered.
MIN_POINTS = 20
# An alignment is judged on the correspondences within this many voxels (whatever the gate).
JUDGE_VOXELS = 3.0


class FrameStatus(enum.IntEnum):
    """How a frame's pose was obtained."""

    FIRST = 0  # the first frame: the world frame
    TRACKED = 1  # trusted alignment at the adaptive gate
    RETRIED = 2  # trusted only after a retry from a wider gate
    UNRELIABLE = 3  # no trusted alignment: the best attempt's pose
    FEW_POINTS = 4  # too few points to register: the predicted pose
    # fits the map (overlap, RMS), but its points leave directions unconstrained (conditioning
    # below min_condition), along which ICP kept the prediction (degenerate_condition > 0);
    # trusted, so a keyframe when it moved: the map follows the sensor past a bare wall
    DEGENERATE = 5


@dataclass
class FrameInfo:
    """What odometry did with one frame."""

    index: int
    timestamp: float | None
    # T_wk, frame → world, (4, 4)
    pose: Tensor
    status: FrameStatus
    is_keyframe: bool
    # the keyframe (index into Odometry.keyframes) this frame's pose is attached to
    anchor: int
    # the trusted/chosen alignment's measures (NaN for FIRST / FEW_POINTS)
    fitness: float
    rms: float
    condition: float
    gate: float
    iterations: int
    # points after cropping and downsampling
    points: int
    # non-finite input points dropped
    dropped: int
    seconds: float
    problem: str | None = None
    # which start gave the pose: 0 the main alignment (step 3), k ≥ 1 the k-th alternative
    # start (step 4: 1 the prediction at the judging gate, 2 the last pose, then 3, 4 the
    # prediction turned by −δ, +δ about the first axis of start_axes, 5, 6 about the second…)
    start: int = 0

    @property
    def trusted(self) -> bool:
        return self.status in (
            FrameStatus.FIRST,
            FrameStatus.TRACKED,
            FrameStatus.RETRIED,
            FrameStatus.DEGENERATE,
        )


@dataclass
class Keyframe:
    """A keyframe: its frame, odometry pose, cloud and normals (sensor frame)."""

    frame: int
    # T_wk from odometry, (4, 4)
    pose: Tensor
    points: Tensor
    normals: Tensor
    # information of the tracking alignment (6, 6), (ω, v), right perturbation, scaled
    information: Tensor
    # the points off the cloud's boundary, bool (N,) (from the normals' neighbourhoods, for the
    # joint refinement's tracks); None when the refinement is off
    interior: Tensor | None = None


class _AdaptiveGate:
    """3σ of the prediction errors (module docstring); ``initial`` before any is counted."""

    def __init__(self, initial: float, minimum: float, maximum: float, min_motion: float) -> None:
        self.initial, self.minimum, self.min_motion = initial, minimum, min_motion
        self.maximum = maximum
        self.sum_squares, self.count = 0.0, 0

    def value(self) -> float:
        if self.count == 0:
            return self.initial
        return min(max(3.0 * math.sqrt(self.sum_squares / self.count), self.minimum), self.maximum)

    def update(self, prediction: Tensor, estimate: Tensor, source: Tensor) -> None:
        with _checks.validation(False):  # poses odometry made: rigid by construction
            deviation = se3.compose(se3.inverse(prediction), estimate)
        moved = source @ deviation[:3, :3].T + deviation[:3, 3]
        error = float((moved - source).square().sum(-1).mean().sqrt())
        if error > self.min_motion:
            self.sum_squares += error * error
            self.count += 1


def turned_starts(T: Tensor, degrees: float, axes: str = "xyz") -> Tensor:
    """T (4, 4) turned by ∓``degrees`` about each of ``axes`` ("x", "y", "z": the axes of its
    own frame), T·Exp((±θ e_a, 0)): (2·len(axes), 4, 4), in the order −a, +a of each axis."""
    angle = math.radians(degrees)
    turns = torch.zeros(2 * len(axes), 3, dtype=T.dtype)
    for k, name in enumerate(axes):
        axis = "xyz".index(name)
        turns[2 * k, axis], turns[2 * k + 1, axis] = -angle, angle
    turned = T.expand(len(turns), 4, 4).clone()
    turned[:, :3, :3] = T[:3, :3] @ so3.exp(turns)
    return turned


def tight_overlap(tree: KDTree, sample: Tensor, transforms: Tensor, bound: float) -> Tensor:
    """Fraction of the points ``sample`` (n, 3), moved by each of ``transforms`` (S, 4, 4),
    with a point of ``tree`` within ``bound``: (S,). A tighter overlap than the judging
    gate's, it tells the right basin from a neighbouring one whose RMS looks as good."""
    T = transforms.numpy()
    moved = np.einsum("sij,nj->sni", T[:, :3, :3], sample.numpy()) + T[:, None, :3, 3]
    _, index = _query_host(tree, moved.reshape(-1, 3), bound)
    return torch.from_numpy((index >= 0).reshape(len(T), -1).mean(1))


def _angle_deg(T: Tensor) -> float:
    cos = float((T[0, 0] + T[1, 1] + T[2, 2] - 1) / 2)
    return math.degrees(math.acos(max(-1.0, min(1.0, cos))))


class Odometry:
    """Streaming frame-to-model odometry (module docstring).

    Args:
        config: options; ``SLAMConfig.for_sensor(sensor)`` when None.
        sensor: "depth" or "lidar", used when ``config`` is None (default "lidar").
        on_keyframe: called with each new :class:`Keyframe` (the back end listens here).

    Example::

        odometry = Odometry(sensor="lidar")
        for cloud in clouds:
            T_wk = odometry.add(cloud)  # (4, 4), frame → world
    """

    def __init__(
        self,
        config: SLAMConfig | None = None,
        *,
        sensor: str | None = None,
        on_keyframe: Callable[[Keyframe], None] | None = None,
    ) -> None:
        fn = "Odometry"
        if config is None:
            config = SLAMConfig.for_sensor("lidar" if sensor is None else sensor)
        elif not isinstance(config, SLAMConfig):
            raise TypeError(
                f"{fn}: argument 'config' must be a SLAMConfig or None, got "
                f"{_checks.describe(config)}"
            )
        elif sensor is not None and sensor != config.sensor:
            raise ValueError(
                f"{fn}: 'sensor' {sensor!r} contradicts config.sensor {config.sensor!r}"
            )
        if on_keyframe is not None and not callable(on_keyframe):
            raise TypeError(f"{fn}: argument 'on_keyframe' must be callable or None")
        self.config = config
        self.on_keyframe = on_keyframe
        self.frames: list[FrameInfo] = []
        self.keyframes: list[Keyframe] = []
        self.map = LocalMap(
            config.voxel * config.map_voxel_fraction, config.map_keyframes, config.map_radius
        )
        self._gate = _AdaptiveGate(
            config.initial_gate,
            config.min_gate_voxels * config.voxel,
            config.max_gate,
            config.min_motion,
        )
        self._thresholds = QualityThresholds(
            config.min_fitness, config.max_rms_voxels * config.voxel, config.min_condition
        )
        self._last: Tensor | None = None  # T_w(k−1)
        self._velocity: Tensor | None = None  # T_w(k−2)⁻¹ T_w(k−1), of trusted frames only
        # (frame points, the lookups of the last single ICP run on them), see _judge
        self._lookups: tuple[Tensor, _Matcher] | None = None

    # ------------------------------------------------------------------ public

    @property
    def poses(self) -> Tensor:
        """T_wk of every frame so far, (F, 4, 4), frame → world (odometry, no back end)."""
        if not self.frames:
            return torch.zeros(0, 4, 4, dtype=torch.float64)
        return torch.stack([f.pose for f in self.frames])

    def add(self, points: object, timestamp: float | None = None) -> Tensor:
        """Register the next frame; returns its pose T_wk (4, 4), frame → world.

        Args:
            points: the frame's points in the sensor frame, (N, 3), N ≥ 1 (a tensor or a numpy
                array); non-finite rows are dropped (counted in :attr:`FrameInfo.dropped`).
            timestamp: optional time of the frame (seconds), kept in :attr:`frames`.
        """
        # The per-frame tensors are small: their algebra runs on one thread and only the
        # KD-tree queries use the caller's threads (registration.icp's policy; a second
        # OpenMP thread on a shared core made a frame 1.4× slower).
        with _icp._host_threads():
            return self._add(points, timestamp)

    def _add(self, points: object, timestamp: float | None) -> Tensor:
        fn = "Odometry.add"
        tic = time.perf_counter()
        cloud, dropped = self._check_points(fn, points)
        if timestamp is not None:
            timestamp = _checks.check_real(fn, "timestamp", timestamp)
        index = len(self.frames)
        dense, source = self._preprocess(cloud)
        cfg = self.config
        if self._last is None:
            pose = torch.eye(4, dtype=torch.float64)
            if source.shape[0] < MIN_POINTS:
                raise ValueError(
                    f"{fn}: the first frame has {source.shape[0]} point(s) within "
                    f"[{cfg.min_range:g}, {cfg.max_range:g}] m after downsampling; at least "
                    f"{MIN_POINTS} are needed to start (check the units and max_range)"
                )
            info = FrameInfo(
                index, timestamp, pose, FrameStatus.FIRST, True, 0, math.nan, math.nan,
                math.nan, math.nan, 0, source.shape[0], dropped, 0.0,
            )  # fmt: skip
            information = torch.eye(6, dtype=torch.float64)
            self._make_keyframe(info, dense, information)
            self._advance(pose, True)
            info.seconds = time.perf_counter() - tic
            self.frames.append(info)
            return pose.clone()

        prediction = self._predict()
        anchor = len(self.keyframes) - 1
        if source.shape[0] < MIN_POINTS:
            info = FrameInfo(
                index, timestamp, prediction, FrameStatus.FEW_POINTS, False, anchor, math.nan,
                math.nan, math.nan, math.nan, 0, source.shape[0], dropped, 0.0,
                f"{source.shape[0]} point(s) after cropping and downsampling",
            )  # fmt: skip
            self._advance(prediction, False)
            info.seconds = time.perf_counter() - tic
            self.frames.append(info)
            return prediction.clone()

        gate = self._gate.value()
        with _checks.validation(False):
            pose, quality, iterations, status, start = self._register(source, prediction, gate)
        # ICP composes its increments: re-orthonormalize so that round-off cannot accumulate.
        pose = se3.from_rotation_translation(so3.project(pose[:3, :3]), pose[:3, 3])
        if status != FrameStatus.UNRELIABLE:
            self._gate.update(prediction, pose, source)
        info = FrameInfo(
            index, timestamp, pose, status, False, anchor, quality.fitness, quality.rms,
            quality.condition, gate, iterations, source.shape[0], dropped, 0.0, quality.problem,
            start,
        )  # fmt: skip
        if status != FrameStatus.UNRELIABLE and self._moved_enough(pose):
            information = quality.information * (cfg.effective_points / max(quality.inliers, 1))
            self._make_keyframe(info, dense, information)
        self._advance(pose, status != FrameStatus.UNRELIABLE)
        info.seconds = time.perf_counter() - tic
        self.frames.append(info)
        return pose.clone()

    # ------------------------------------------------------------------ steps

    def _check_points(self, fn: str, points: object) -> tuple[Tensor, int]:
        if isinstance(points, np.ndarray):
            points = torch.from_numpy(np.ascontiguousarray(points))
        if not isinstance(points, Tensor):
            raise TypeError(
                f"{fn}: argument 'points' must be a tensor or numpy array of shape (N, 3), got "
                f"{_checks.describe(points)}"
            )
        if points.dim() != 2 or points.shape[-1] != 3:
            raise ValueError(
                f"{fn}: argument 'points' must have shape (N, 3), got {tuple(points.shape)}"
            )
        if not points.dtype.is_floating_point:
            raise TypeError(f"{fn}: argument 'points' must be floating point, got {points.dtype}")
        if points.shape[0] == 0:
            raise ValueError(f"{fn}: argument 'points' is an empty frame (0 points)")
        points = points.detach().to(device="cpu", dtype=torch.float64)
        finite = torch.isfinite(points).all(-1)
        dropped = int((~finite).sum())
        if dropped:
            points = points[finite]
            if points.shape[0] == 0:
                raise ValueError(f"{fn}: argument 'points' has no finite point ({dropped} NaN/Inf)")
        return points, dropped

    def _preprocess(self, cloud: Tensor) -> tuple[Tensor, Tensor]:
        cfg = self.config
        ranges = torch.linalg.vector_norm(cloud, dim=-1)
        kept = cloud[(ranges >= cfg.min_range) & (ranges <= cfg.max_range)]
        if cfg.map_voxel_fraction >= 1.0:
            dense = source = _downsample("Odometry.add", kept, cfg.voxel)
        else:
            dense = _downsample("Odometry.add", kept, cfg.voxel * cfg.map_voxel_fraction)
            source = _downsample("Odometry.add", dense, cfg.voxel)
        if source.shape[0] > cfg.max_source_points:
            # A dense scan (a 64-beam LiDAR): register an evenly spread subset, keep all in the
            # map. The same subset for the same input (a fixed generator): runs repeat exactly.
            generator = torch.Generator().manual_seed(source.shape[0])
            pick = torch.randperm(source.shape[0], generator=generator)[: cfg.max_source_points]
            source = source[pick.sort().values]
        return dense, source

    def _predict(self) -> Tensor:
        assert self._last is not None
        if self._velocity is None or self.config.prediction == "previous":
            return self._last.clone()
        with _checks.validation(False):  # poses odometry made: rigid by construction
            return se3.compose(self._last, self._velocity)

    def _advance(self, pose: Tensor, trusted: bool) -> None:
        """Make ``pose`` the last one. The velocity T_(k−1)⁻¹T_k of the prediction is
        measured on trusted frames only: an unreliable or unregistered frame keeps the one
        before it, so that a failed alignment (a sensor losing the map) is not predicted
        again, faster, at the next frame."""
        if self._last is not None and trusted:
            with _checks.validation(False):  # poses odometry made: rigid by construction
                self._velocity = se3.compose(se3.inverse(self._last), pose)
        self._last = pose

    def _moved_enough(self, pose: Tensor) -> bool:
        cfg = self.config
        with _checks.validation(False):  # poses odometry made: rigid by construction
            motion = se3.compose(se3.inverse(self.keyframes[-1].pose), pose)
        return (
            float(motion[:3, 3].norm()) > cfg.keyframe_translation
            or _angle_deg(motion) > cfg.keyframe_rotation_deg
        )

    def _icp(
        self,
        source: Tensor,
        initial: Tensor,
        gate: float,
        iterations: int | None = None,
        matcher: _Matcher | None = None,
        rotation_only: bool = False,
    ) -> _icp.ICPResult:
        """Point-to-plane ICP of ``source`` against the map from ``initial`` (4, 4) or a
        batch (S, 4, 4); a result per start. ``matcher``: the lookups of an earlier run of
        the same points (one start), which go on serving this one (the answers of a fresh
        query wherever the points are, :class:`~torchslam.registration.neighbors._Matcher`)."""
        cfg = self.config
        config = _icp.ICPConfig(
            method="point_to_plane",
            max_iterations=cfg.icp_iterations if iterations is None else iterations,
            relative_tolerance=1e-6,
            max_distance=gate,
            gate_scale=None,
            kernel="cauchy",
            kernel_scale=gate * cfg.kernel_fraction,
            rotation_tolerance_deg=cfg.icp_step_deg,
            translation_tolerance=cfg.icp_step_voxels * cfg.voxel,
            rotation_only=rotation_only,
            degenerate_condition=cfg.degenerate_condition or None,
        )
        target, normals = self.map.state()
        batch = initial if initial.dim() == 3 else initial[None]
        if matcher is None:
            matcher = _Matcher(self.map.tree, target.numpy(), batch.shape[0], source.shape[0])
        result = _icp._run(
            "Odometry.add", source, target, batch, config, normals, self.map.tree, matcher
        )
        # A run of one frame: its lookups, left at the final pose, serve the judging after it.
        self._lookups = (source, matcher) if initial.dim() == 2 else None
        return result if initial.dim() == 3 else result[0]

    def _judge(self, source: Tensor, T: Tensor) -> AlignmentQuality:
        target, normals = self.map.state()
        # The last single run's lookups on this frame, when there is one: the same
        # neighbours as a fresh query (neighbors._Matcher), most of them without a lookup.
        lookups = self._lookups
        matcher = lookups[1] if lookups is not None and lookups[0] is source else None
        return _quality._measure(
            "Odometry.add", source, target, normals, T, JUDGE_VOXELS * self.config.voxel,
            self._thresholds, 0.1 * self.config.voxel, self.map.tree, matcher,
        )  # fmt: skip

    @staticmethod
    def _sample(source: Tensor, count: int) -> Tensor:
        """An evenly spread subset of ``count`` rows of ``source`` (all when fewer), the same
        for the same input (a generator seeded by the size: runs repeat exactly)."""
        if source.shape[0] <= count:
            return source
        generator = torch.Generator().manual_seed(source.shape[0])
        pick = torch.randperm(source.shape[0], generator=generator)[:count]
        return source[pick.sort().values]

    def _starts(self, prediction: Tensor) -> Tensor:
        """The alternative starts (module docstring, step 4), (2 + 2·len(start_axes), 4, 4)."""
        assert self._last is not None
        cfg = self.config
        turned = turned_starts(prediction, cfg.start_rotation_deg, cfg.start_axes)
        return torch.cat((prediction[None], self._last[None], turned))

    def _screen(
        self, source: Tensor, prediction: Tensor, transform: Tensor
    ) -> tuple[Tensor, int, int]:
        """Step 4 of the module docstring: (the pose, its start, the extra ICP passes)."""
        cfg = self.config
        fine = JUDGE_VOXELS * cfg.voxel
        sample = self._sample(source, cfg.screen_points)
        starts = self._icp(sample, self._starts(prediction), fine, cfg.screen_iterations)
        bound = cfg.screen_voxels * cfg.voxel
        candidates = torch.cat((transform[None], starts.transform))
        scores = tight_overlap(self.map.tree, sample, candidates, bound)
        best = int(scores[1:].argmax())
        passes = int(starts.iterations.sum())
        if float(scores[best + 1]) <= float(scores[0]) + cfg.screen_margin:
            return transform, 0, passes
        refined = self._icp(source, starts.transform[best], fine)
        passes += int(refined.iterations)
        score = float(tight_overlap(self.map.tree, sample, refined.transform[None], bound)[0])
        if score <= float(scores[0]) + cfg.screen_margin:
            return transform, 0, passes
        return refined.transform, best + 1, passes

    def _align(self, source: Tensor, initial: Tensor, gate: float) -> tuple[_icp.ICPResult, int]:
        """ICP from ``initial`` (4, 4) at ``gate``; a gate wider than 1.5× the judging gate is
        a two-stage run (module docstring, step 3): that gate (with ``coarse_rotation_only``
        turning the frame only), then the judging gate. Returns the result and the passes."""
        fine = JUDGE_VOXELS * self.config.voxel
        two_stage = gate > 1.5 * fine
        turn = two_stage and self.config.coarse_rotation_only
        result = self._icp(source, initial, gate, rotation_only=turn)
        iterations = int(result.iterations)
        if two_stage:
            # A wide gate (fast or unknown motion) lets wrong matches bias the optimum: finish
            # with the gate the alignment is judged with, from the lookups of the run before.
            assert self._lookups is not None
            result = self._icp(source, result.transform, fine, matcher=self._lookups[1])
            iterations += int(result.iterations)
        return result, iterations

    def _register(
        self, source: Tensor, prediction: Tensor, gate: float
    ) -> tuple[Tensor, AlignmentQuality, int, FrameStatus, int]:
        result, iterations = self._align(source, prediction, gate)
        transform, start = result.transform, 0
        if self.config.start_rotation_deg > 0:
            screened, start, passes = self._screen(source, prediction, transform)
            iterations += passes
            if start:
                quality = self._judge(source, screened)
                if quality.trusted:
                    return screened, quality, iterations, FrameStatus.TRACKED, start
                start = 0
        quality = self._judge(source, transform)
        if quality.trusted:
            return transform, quality, iterations, FrameStatus.TRACKED, start
        assert self._last is not None
        attempts = [(transform, quality, iterations)]
        for initial in (prediction, self._last):
            # the same registration from a 3× wider gate: its wide stage (turning only, by
            # default) cannot slide the frame, the judging-gate stage after it solves all six
            refined, steps = self._align(source, initial, 3.0 * gate)
            q = self._judge(source, refined.transform)
            attempts.append((refined.transform, q, steps))
            if q.trusted:
                return refined.transform, q, steps, FrameStatus.RETRIED, 0
        for attempt in attempts:  # no trusted one: the first that only lacks conditioning
            if self._degenerate_only(attempt[1]):
                return attempt[0], attempt[1], attempt[2], FrameStatus.DEGENERATE, 0
        best = max(attempts, key=lambda a: (a[1].fitness, -a[1].rms))
        return best[0], best[1], best[2], FrameStatus.UNRELIABLE, 0

    def _degenerate_only(self, quality: AlignmentQuality) -> bool:
        """Whether an untrusted alignment fits the map (overlap and RMS pass) and fails only
        the conditioning test, while ICP keeps the prediction along the weak directions
        (``degenerate_condition`` > 0): a view of a bare wall and floor, not a wrong fit."""
        t = self._thresholds
        return (
            self.config.degenerate_condition > 0
            and quality.inliers >= 6
            and quality.fitness >= t.min_fitness
            and (t.max_rms is None or quality.rms <= t.max_rms)
            and quality.condition < t.min_condition
        )

    def _make_keyframe(self, info: FrameInfo, source: Tensor, information: Tensor) -> None:
        cfg = self.config
        k = min(cfg.normal_neighbors, source.shape[0])
        origin = source.new_zeros(3)
        normals, distance, index = _normals_and_neighbours("Odometry.add", source, k, origin)
        interior = None
        threshold = RegisterConfig.boundary_threshold  # refine's, from the same neighbourhoods
        if cfg.refine_rounds > 0 and threshold is not None:
            fn = "Odometry.add"
            boundary = _boundary_from_neighbours(
                _host(fn, "points", source), distance, index, threshold,
                _host(fn, "normals", normals),
            )  # fmt: skip
            interior = torch.from_numpy(~boundary).to(source.device)
        keyframe = Keyframe(info.index, info.pose, source, normals, information, interior)
        self.keyframes.append(keyframe)
        info.is_keyframe = True
        info.anchor = len(self.keyframes) - 1
        R, t = info.pose[:3, :3].numpy(), info.pose[:3, 3].numpy()
        self.map.add(source.numpy() @ R.T + t, normals.numpy() @ R.T, t)
        if self.on_keyframe is not None:
            self.on_keyframe(keyframe)
