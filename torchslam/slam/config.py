"""Options of the sequence pipeline (:mod:`torchslam.slam`), with defaults per sensor.

Distances are metres. ``SLAMConfig.for_sensor("depth")`` suits a hand-held depth camera
(Kinect-like: 0.2–4 m, 30 Hz, small motions between frames); ``for_sensor("lidar")`` a LiDAR
(keyframe scans of a few thousand points, ranges up to tens of metres, 10 Hz).
``dataclasses.replace`` (or keyword overrides of :meth:`SLAMConfig.for_sensor`) changes any of
them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

from torchslam import _checks

__all__ = ["SENSORS", "SLAMConfig"]

SENSORS = ("depth", "lidar")
# the smallest max_source_points accepted (ICP needs enough correspondences to be judged)
MIN_SOURCE_POINTS = 100
# the smallest screen_points accepted (a tight-overlap score needs a sample to be measured on)
MIN_POINTS_SCREEN = 50


@dataclass(frozen=True)
class SLAMConfig:
    """Options of :class:`torchslam.slam.Odometry` and :class:`torchslam.slam.SLAM`."""

    sensor: Literal["depth", "lidar"] = "lidar"
    # --- frames
    # voxel pitch of the downsampled frame, the local map and the keyframe clouds
    voxel: float = 0.25
    # points nearer than min_range or farther than max_range (from the sensor) are dropped
    min_range: float = 0.5
    # depth images read by run_sequence / the CLI: every pixel_stride-th row and column is
    # back-projected (the voxel grid keeps one point per cell anyway: at 2 m a Kinect pixel is
    # 3.4 mm, so a stride of 4 still leaves ~3 samples across a 4 cm voxel)
    pixel_stride: int = 1
    max_range: float = 60.0
    # --- odometry (frame-to-model point-to-plane ICP against the local map)
    # correspondence gate before the motion statistics exist; then 3σ of the prediction error
    initial_gate: float = 1.5
    # pose prediction: "constant_velocity" (T_(k−1)·(T_(k−2)⁻¹ T_(k−1))) or "previous" (T_(k−1))
    prediction: Literal["constant_velocity", "previous"] = "constant_velocity"
    # the adaptive gate stays within [min_gate_voxels · voxel, max_gate]
    min_gate_voxels: float = 1.0
    max_gate: float = 3.0
    # scale of the Cauchy kernel on the point-to-plane distances: this fraction of the gate
    kernel_fraction: float = 1.0 / 3.0
    # prediction errors below this (metres, at the lever arm) are not counted in σ
    min_motion: float = 0.02
    # iteration cap and the step tolerances of the ICP: it stops when a step turns the frame
    # by less than icp_step_deg and moves its centroid by less than icp_step_voxels · voxel
    icp_iterations: int = 30
    icp_step_voxels: float = 0.01
    icp_step_deg: float = 0.01
    # alternative starts (odometry's module docstring, step 4): the prediction turned by
    # ± start_rotation_deg about each of the sensor axes start_axes (a string of "x", "y",
    # "z"), and the last pose, screened against the main alignment; 0 disables them.
    # Hand-held LiDAR keyframes are often mispredicted by several degrees, mostly in yaw
    # (about the sensor's z, up for a LiDAR held or mounted level), where the main ICP can
    # settle in a wrong basin.
    start_rotation_deg: float = 5.0
    start_axes: str = "z"
    # the wide-gate stage of the odometry's ICP (the gate above 1.5× the judging gate) turns
    # the frame about the sensor and keeps the predicted translation (ICPConfig
    # rotation_only); the tight stage after it solves all six, so a wide gate cannot make
    # the frame slide (the retries' wide stage too). On the shared runs it lowers the ATE of
    # all three sequences and the summed ATE of the twelve reversed/thinned LiDAR variants
    # (45 → 17 m), doubling only quick-shack reversed (docs/sequences.md, "The wide stage
    # turns only"); False: the wide stages solve all six
    coarse_rotation_only: bool = True
    # the screening: ICP of every start on screen_points of the frame, screen_iterations each
    screen_points: int = 500
    screen_iterations: int = 6
    # a start replaces the main alignment when its tight overlap (the fraction of points with
    # a map point within screen_voxels · voxel) is higher by more than screen_margin
    screen_voxels: float = 0.8
    screen_margin: float = 0.02
    # frames with more points than this after downsampling are registered on a random subset
    # of this size (the keyframes keep all): bounds the time per frame of dense scans (the
    # LiDAR default is lower, see _DEFAULTS)
    max_source_points: int = 8000
    # keyframes (the local map, loop closures, the map output) keep their points on a grid of
    # this fraction of the voxel; frames are registered on the voxel grid. The depth defaults
    # use 0.5; LiDAR keyframes keep 1 (on quick-shack a map at 0.5 lost track: 0.17 → 1.5 m
    # odometry ATE; on hku2-loop 0.071 → 0.081 m)
    map_voxel_fraction: float = 1.0
    # the local map: the newest map_keyframes keyframes within map_radius of the sensor
    map_keyframes: int = 20
    map_radius: float = 60.0
    # normals of a keyframe cloud: PCA over this many neighbours
    normal_neighbors: int = 10
    # an alignment is trusted when its overlap, RMS and conditioning pass these
    min_fitness: float = 0.3
    max_rms_voxels: float = 1.0
    min_condition: float = 1e-3
    # ICP leaves a frame at its prediction along the directions its points barely constrain:
    # eigenvalues of the step's normal equations (rotation scaled by the lever arm, as the
    # conditioning above) below this fraction of the largest (ICPConfig.degenerate_condition;
    # 0: off). A camera facing a bare wall and floor otherwise slides along them, faster each
    # frame through the constant-velocity prediction. On data.make_depth_sequence's rooms (300
    # frames, seeds 0-2, 10 or 20 boxes) it lowers the SLAM ATE in 5 of 6 runs (seed 0, 10
    # boxes: 40 → 7 cm; seed 2, 20 boxes: 0.71 → 0.84 cm, worse); those rooms still drift by
    # decimetres in their barest views. The shared sequences' frames are all conditioned 0.037
    # or better: their trajectories are bit for bit those without it
    degenerate_condition: float = 0.01
    # --- keyframes: a new one when the motion since the last exceeds either
    keyframe_translation: float = 0.2
    keyframe_rotation_deg: float = 5.0
    # --- loop closure
    loops: bool = True
    # candidates: an earlier keyframe within loop_radius (positions) ...
    loop_radius: float = 5.0
    # ... at least loop_min_gap keyframes and loop_min_path metres of travel before
    loop_min_gap: int = 30
    loop_min_path: float = 10.0
    # the candidate's submap: its keyframes ± loop_window
    loop_window: int = 3
    # verification ICP: initial gate (then shrinks), acceptance thresholds
    loop_gate: float = 2.0
    loop_min_fitness: float = 0.3
    loop_max_rms_voxels: float = 0.6
    # at most this many verifications per new keyframe
    loop_candidates: int = 1
    # a keyframe does not look for a loop within loop_cooldown keyframes of an accepted one
    loop_cooldown: int = 5
    # --- back end
    # ICP information is scaled by effective_points / inliers (neighbouring points' errors
    # are correlated; the raw JᵀJ/σ² would claim thousands of independent measurements)
    effective_points: float = 100.0
    # loop edges carry a Cauchy kernel of this scale (in whitened units, √χ²)
    loop_kernel_scale: float = 3.0
    # a loop is dropped when its χ² against the odometry chain alone (the Mahalanobis
    # distance of its innovation), or its edge's χ² in the least-squares graph with the other
    # loops, exceeds this (torchslam.slam.backend). The information's effective_points
    # scaling keeps correct loops far below it: on the shared LiDAR runs their χ² against the
    # odometry is 0.01–1.4 (defaults), a forced identity between distant keyframes 10³–10⁴
    loop_max_chi2: float = 200.0
    # rounds of the joint multiview ICP-SLAM refinement of the keyframes (poses and points, the
    # seed's problem) after the pose graph. The LiDAR defaults run one: on hku2-loop's 253
    # keyframes it takes ~5 s (1 thread), 20 ms per frame on top of the odometry's ~80; it
    # lowers quick-shack's ATE from 0.158 to 0.107 m (~2 s) and leaves hku2-loop's at 0.073 m
    # (a loop-closed graph already); the depth defaults none (7-Scenes: 0.63 → 0.65 cm, a
    # third more time per frame, measured with the six-DoF wide stage).
    refine_rounds: int = 0
    # keyframe pairs matched by the refinement: neighbours up to this index gap, plus loops
    refine_neighbors: int = 2
    # Levenberg-Marquardt iterations per refinement round at most (the rounds re-associate;
    # on hku2-loop 3 iterations reach the round's cost to 3e-4 relative and the ATE of 50)
    refine_iterations: int = 3

    def __post_init__(self) -> None:
        fn = "SLAMConfig"
        if not isinstance(self.sensor, str) or self.sensor not in SENSORS:
            raise ValueError(
                f"{fn}: argument 'sensor' must be 'depth' or 'lidar', got "
                f"{_checks.describe(self.sensor)}"
            )
        if self.prediction not in ("constant_velocity", "previous"):
            raise ValueError(
                f"{fn}: argument 'prediction' must be 'constant_velocity' or 'previous', got "
                f"{_checks.describe(self.prediction)}"
            )
        positive = (
            "voxel",
            "max_range",
            "initial_gate",
            "max_gate",
            "kernel_fraction",
            "map_voxel_fraction",
            "map_radius",
            "loop_radius",
            "loop_gate",
            "effective_points",
            "loop_kernel_scale",
            "loop_max_chi2",
            "max_rms_voxels",
            "loop_max_rms_voxels",
            "screen_voxels",
            "icp_step_voxels",
            "icp_step_deg",
        )
        for name in positive:
            _checks.check_real(fn, name, getattr(self, name), low=0.0, low_open=True)
        for name in (
            "min_range",
            "min_gate_voxels",
            "min_motion",
            "keyframe_translation",
            "keyframe_rotation_deg",
            "loop_min_path",
        ):
            _checks.check_real(fn, name, getattr(self, name), low=0.0)
        _checks.check_real(fn, "start_rotation_deg", self.start_rotation_deg, low=0.0, high=90.0)
        axes = self.start_axes
        if (
            not isinstance(axes, str)
            or not axes
            or set(axes) - set("xyz")
            or len(set(axes)) != len(axes)
        ):
            raise ValueError(
                f"{fn}: argument 'start_axes' must be a non-empty string of distinct axes "
                f"among 'x', 'y', 'z' (e.g. 'z' or 'xyz'), got {axes!r}"
            )
        for name in (
            "min_fitness",
            "min_condition",
            "degenerate_condition",
            "loop_min_fitness",
            "screen_margin",
        ):
            _checks.check_real(fn, name, getattr(self, name), low=0.0, high=1.0)
        if self.min_range >= self.max_range:
            raise ValueError(
                f"{fn}: 'min_range' ({self.min_range:g}) must be below 'max_range' "
                f"({self.max_range:g})"
            )
        for name, low in (
            ("pixel_stride", 1),
            ("icp_iterations", 1),
            ("screen_points", MIN_POINTS_SCREEN),
            ("screen_iterations", 1),
            ("max_source_points", MIN_SOURCE_POINTS),
            ("map_keyframes", 1),
            ("normal_neighbors", 3),
            ("loop_min_gap", 1),
            ("loop_window", 0),
            ("loop_candidates", 0),
            ("loop_cooldown", 0),
            ("refine_rounds", 0),
            ("refine_neighbors", 1),
            ("refine_iterations", 1),
        ):
            _checks.check_int(fn, name, getattr(self, name), minimum=low)
        for name in ("loops", "coarse_rotation_only"):
            _checks.check_bool(fn, name, getattr(self, name))

    @classmethod
    def for_sensor(cls, sensor: str, **overrides: object) -> SLAMConfig:
        """The defaults of ``sensor`` ("depth" or "lidar"), with ``overrides`` applied."""
        if not isinstance(sensor, str) or sensor not in _DEFAULTS:
            raise ValueError(
                f"SLAMConfig.for_sensor: argument 'sensor' must be 'depth' or 'lidar', got "
                f"{_checks.describe(sensor)}"
            )
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(overrides) - names)
        if unknown:
            raise TypeError(f"SLAMConfig.for_sensor: unknown option(s) {', '.join(unknown)}")
        return cls(sensor=sensor, **{**_DEFAULTS[sensor], **overrides})  # type: ignore[arg-type]


_DEFAULTS: dict[str, dict[str, object]] = {
    "depth": {
        "voxel": 0.04,
        "pixel_stride": 4,
        "min_range": 0.2,
        "max_range": 4.0,
        "initial_gate": 0.3,
        "max_gate": 0.3,
        "min_motion": 0.005,
        "map_radius": 6.0,
        "keyframe_translation": 0.08,
        "keyframe_rotation_deg": 5.0,
        "loop_radius": 0.6,
        "loop_min_gap": 20,
        "loop_min_path": 1.0,
        "loop_gate": 0.3,
        # a 30 Hz depth camera turns little between frames (7-Scenes: 0.2° median prediction
        # error) and has no time for the screening
        "start_rotation_deg": 0.0,
        # the local map on a grid of half the frame's voxel (2 cm): the frame's points find
        # their nearest map point on the surface twice as close, where a 4 cm grid's
        # chords cut curved surfaces (7-Scenes: 0.78 → 0.63 cm ATE; a LiDAR's sparse rings
        # do not gain from it, see map_voxel_fraction)
        "map_voxel_fraction": 0.5,
        # steps of 0.8 mm and 0.02° (≈ 0.9 mm at 2.5 m): below the Kinect's depth noise
        # (≈ 2–5 mm at 1–3 m), and a third fewer ICP passes on the finer map than 0.01
        "icp_step_voxels": 0.02,
        "icp_step_deg": 0.02,
    },
    "lidar": {
        "refine_rounds": 1,
        # 4000 points of the 0.25 m grid over-determine a 6-DoF step a thousandfold and hold
        # the shared keyframes whole (at most 3813); a 64-beam scan (tens of thousands of
        # voxels) is registered on a subset: on small_gicp's 70k-point pair (6166 voxels) as
        # accurate as on all of them, 60 vs 79 ms
        "max_source_points": 4000,
    },
}
