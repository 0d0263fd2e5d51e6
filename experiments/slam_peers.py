"""Odometry of the tools users would pick instead of torchslam, on range-sensor sequences.

Runs under the peers venv (``/work/peers-venv/bin/python``), never torchslam's: it imports
neither torchslam nor torch. torchslam's own SLAM experiment calls it as a subprocess, with the
frames written to an ``.npz``, and reads the JSON it writes back.

Methods (``--methods``, comma separated; default: all):

* ``open3d`` — Open3D point-to-plane ICP, frame to frame: voxel downsample, normals (hybrid
  radius/kNN search), ``registration_icp`` with ``TransformationEstimationPointToPlane``.
* ``small_gicp_f2f`` — small_gicp GICP, frame to frame: ``preprocess_points`` (downsample,
  covariances, KdTree) once per frame, then ``align`` against the previous frame and its tree.
* ``small_gicp_f2m`` — small_gicp frame to model, as small_gicp's Python odometry example:
  each downsampled frame is aligned (VGICP) to a ``GaussianVoxelMap`` (LRU-pruned) of the
  frames before it, then inserted at its estimated pose.
* ``kiss_icp`` — KISS-ICP 1.x (``KissICP`` with a ``KISSConfig``): its adaptive threshold and
  local voxel-hash map; no deskewing (the frames have no per-point timestamps).

Every method starts from the constant-velocity guess (the previous relative motion), and
``poses[0]`` is the identity: the world is the first frame.

Input (``--frames FILE.npz``): arrays ``frame_000000``, ``frame_000001``, … each (N_i, 3)
points in the sensor frame (float32 or float64), and a 0-d string array ``sensor``, "depth"
or "lidar", which picks the defaults in ``DEFAULTS`` (``--sensor`` overrides it). The file is
read, and the points converted to float64, before any timing.

Output (``--out FILE.json``)::

    {"frames": str, "sensor": str, "n_frames": int, "threads": int,
     "methods": {NAME: {"poses": [[[4 floats] × 4] × n_frames],   # frame → world
                        "ms_per_frame": float,          # mean over all frames, processing only
                        "ms_per_frame_median": float,
                        "total_s": float,
                        "version": str, "params": {...}}}}

A method that is not installed, or that raises, is given ``{"error": str, "version": ...,
"params": ...}`` instead (no poses) and the others still run; the exit status is 0 unless the
input cannot be read.

Threads (``--threads N``, default 1) are set before any library is imported: OMP/OpenBLAS/MKL
and TBB environment variables (Open3D reads ``OMP_NUM_THREADS``), small_gicp's
``num_threads`` and KISS-ICP's ``registration.max_num_threads``.

Usage::

    /work/peers-venv/bin/python experiments/slam_peers.py --frames seq.npz --out peers.json \\
        [--methods open3d,small_gicp_f2f,small_gicp_f2m,kiss_icp] [--threads 2] [--voxel 0.3] \\
        [--sensor lidar] [--set KEY=VALUE ...]

``--set`` overrides any ``DEFAULTS`` key (e.g. ``--set f2m_voxel=2.0``; ``none`` for None).
"""

from __future__ import annotations

import os
import sys


def _threads_from_argv(argv: list[str]) -> int:
    """``--threads N`` / ``--threads=N`` from the command line, before argparse runs (the
    thread-count environment must be set before numpy and the libraries are imported)."""
    for i, arg in enumerate(argv):
        if arg == "--threads" and i + 1 < len(argv):
            return max(1, int(argv[i + 1]))
        if arg.startswith("--threads="):
            return max(1, int(arg.split("=", 1)[1]))
    return 1


THREADS = _threads_from_argv(sys.argv[1:])
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "TBB_NUM_THREADS"):
    os.environ[_var] = str(THREADS)

import argparse  # noqa: E402
import importlib.metadata  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from collections.abc import Callable  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

METHODS = ("open3d", "small_gicp_f2f", "small_gicp_f2m", "kiss_icp")

# Per-sensor defaults. ``voxel`` is the downsampling leaf of every method (``--voxel``
# overrides it; KISS-ICP's map voxel is ``kiss_voxel``, or ``voxel`` when --voxel is given).
# Distances in metres. The lidar values are the libraries' own defaults where they have one
# (small_gicp: 0.25 m downsampling, 1 m gate and VGICP voxel, 10 neighbours; KISS-ICP:
# voxel = max_range / 100, 2 m initial threshold). On the ~5k-point solid-state sequences the
# frame-to-frame and small_gicp results swing by metres with a ×2 change of voxel, gate or
# neighbours (hku2-loop small_gicp_f2m: 9.5 m ATE at f2m_voxel 1.0, 0.09 m at 2.0), so
# these were not tuned per sequence: a light sweep found no setting better on both lidar runs.
DEFAULTS: dict[str, dict[str, Any]] = {
    # Kinect-class depth camera, 0.3–5 m, ~300k points a frame, slow hand-held motion.
    "depth": {
        "voxel": 0.03,
        "normal_radius": 0.08,  # Open3D normals: hybrid search radius …
        "normal_max_nn": 30,  # … and at most this many neighbours
        "max_correspondence": 0.08,  # ICP/GICP gate (open3d, small_gicp_f2f)
        "max_iterations": 30,
        "gicp_neighbors": 20,  # small_gicp covariance neighbours
        "f2m_voxel": 0.08,  # small_gicp GaussianVoxelMap leaf (frame to model)
        "f2m_max_correspondence": 0.08,
        "f2m_lru_horizon": 100,
        "kiss_min_range": 0.2,
        "kiss_max_range": 5.0,
        "kiss_voxel": 0.05,  # = max_range / 100, KISS-ICP's own rule
        "kiss_initial_threshold": 0.1,  # KISS-ICP's default 2 m is a car's, not a hand's
        "kiss_min_motion": 0.01,
    },
    # Solid-state lidar (Livox-class), ~4–5k points a keyframe, indoor/outdoor, 1–40 m.
    "lidar": {
        "voxel": 0.25,
        "normal_radius": 1.0,
        "normal_max_nn": 20,
        "max_correspondence": 1.0,
        "max_iterations": 30,
        "gicp_neighbors": 10,
        "f2m_voxel": 1.0,
        "f2m_max_correspondence": 1.0,
        "f2m_lru_horizon": 100,
        "kiss_min_range": 0.5,
        "kiss_max_range": None,  # None: the 99th percentile range of the first frames
        "kiss_voxel": None,  # None: max_range / 100, KISS-ICP's own rule
        "kiss_initial_threshold": 2.0,
        "kiss_min_motion": 0.1,
    },
}


def _version(dist: str) -> str:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return "not installed"


def _run_loop(
    frames: list[np.ndarray], step: Callable[[np.ndarray], np.ndarray]
) -> tuple[list[np.ndarray], list[float]]:
    """Calls ``step(points) -> T_world_frame`` on every frame, timing each call."""
    poses, times = [], []
    for points in frames:
        t0 = time.perf_counter()
        pose = step(points)
        times.append(time.perf_counter() - t0)
        poses.append(np.array(pose, dtype=np.float64))
    return poses, times


def run_open3d(frames: list[np.ndarray], p: dict[str, Any], threads: int) -> dict[str, Any]:
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    reg = o3d.pipelines.registration
    estimation = reg.TransformationEstimationPointToPlane()
    criteria = reg.ICPConvergenceCriteria(max_iteration=p["max_iterations"])
    search = o3d.geometry.KDTreeSearchParamHybrid(
        radius=p["normal_radius"], max_nn=p["normal_max_nn"]
    )
    state = {"target": None, "pose": np.eye(4), "delta": np.eye(4)}

    def step(points: np.ndarray) -> np.ndarray:
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        cloud = cloud.voxel_down_sample(p["voxel"])
        cloud.estimate_normals(search)
        if state["target"] is not None:
            result = reg.registration_icp(
                cloud,
                state["target"],
                p["max_correspondence"],
                state["delta"],
                estimation,
                criteria,
            )
            state["delta"] = np.asarray(result.transformation)
            state["pose"] = state["pose"] @ state["delta"]
        state["target"] = cloud
        return state["pose"]

    poses, times = _run_loop(frames, step)
    return {"poses": poses, "times": times, "version": o3d.__version__}


def run_small_gicp_f2f(frames: list[np.ndarray], p: dict[str, Any], threads: int) -> dict[str, Any]:
    import small_gicp

    state = {"target": None, "tree": None, "pose": np.eye(4), "delta": np.eye(4)}

    def step(points: np.ndarray) -> np.ndarray:
        cloud, tree = small_gicp.preprocess_points(
            points, p["voxel"], num_neighbors=p["gicp_neighbors"], num_threads=threads
        )
        if state["target"] is not None:
            result = small_gicp.align(
                state["target"],
                cloud,
                state["tree"],
                init_T_target_source=state["delta"],
                registration_type="GICP",
                max_correspondence_distance=p["max_correspondence"],
                num_threads=threads,
                max_iterations=p["max_iterations"],
            )
            state["delta"] = np.asarray(result.T_target_source)
            state["pose"] = state["pose"] @ state["delta"]
        state["target"], state["tree"] = cloud, tree
        return state["pose"]

    poses, times = _run_loop(frames, step)
    return {"poses": poses, "times": times, "version": _version("small_gicp")}


def run_small_gicp_f2m(frames: list[np.ndarray], p: dict[str, Any], threads: int) -> dict[str, Any]:
    import small_gicp

    voxelmap = small_gicp.GaussianVoxelMap(p["f2m_voxel"])
    voxelmap.set_lru(horizon=p["f2m_lru_horizon"], clear_cycle=10)
    state = {"pose": np.eye(4), "delta": np.eye(4)}

    def step(points: np.ndarray) -> np.ndarray:
        cloud, _ = small_gicp.preprocess_points(
            points, p["voxel"], num_neighbors=p["gicp_neighbors"], num_threads=threads
        )
        if voxelmap.size() > 0:
            result = small_gicp.align(
                voxelmap,
                cloud,
                state["pose"] @ state["delta"],
                max_correspondence_distance=p["f2m_max_correspondence"],
                num_threads=threads,
                max_iterations=p["max_iterations"],
            )
            pose = np.asarray(result.T_target_source)
            state["delta"] = np.linalg.inv(state["pose"]) @ pose
            state["pose"] = pose
        voxelmap.insert(cloud, state["pose"])
        return state["pose"]

    poses, times = _run_loop(frames, step)
    return {"poses": poses, "times": times, "version": _version("small_gicp")}


def run_kiss_icp(frames: list[np.ndarray], p: dict[str, Any], threads: int) -> dict[str, Any]:
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    config = KISSConfig()
    config.out_dir = os.devnull
    config.data.deskew = False
    config.data.min_range = p["kiss_min_range"]
    config.data.max_range = p["kiss_max_range"]
    config.mapping.voxel_size = p["kiss_voxel"]
    config.registration.max_num_threads = threads
    config.adaptive_threshold.initial_threshold = p["kiss_initial_threshold"]
    config.adaptive_threshold.min_motion_th = p["kiss_min_motion"]
    odometry = KissICP(config=config)
    no_timestamps = np.zeros(0)

    def step(points: np.ndarray) -> np.ndarray:
        odometry.register_frame(points, no_timestamps)
        return odometry.last_pose

    poses, times = _run_loop(frames, step)
    return {"poses": poses, "times": times, "version": _version("kiss-icp")}


RUNNERS = {
    "open3d": (run_open3d, "open3d"),
    "small_gicp_f2f": (run_small_gicp_f2f, "small_gicp"),
    "small_gicp_f2m": (run_small_gicp_f2m, "small_gicp"),
    "kiss_icp": (run_kiss_icp, "kiss-icp"),
}


def resolve_params(
    sensor: str,
    frames: list[np.ndarray],
    voxel: float | None,
    overrides: dict[str, float | None] | None = None,
) -> dict[str, Any]:
    """The sensor's defaults with ``--set`` overrides, ``--voxel`` and the data-driven KISS-ICP
    ranges filled in."""
    p = dict(DEFAULTS[sensor])
    for key, value in (overrides or {}).items():
        is_int = isinstance(DEFAULTS[sensor][key], int)
        p[key] = int(value) if is_int and value is not None else value
    if voxel is not None:
        p["voxel"] = voxel
        p["kiss_voxel"] = voxel
    if p["kiss_max_range"] is None:
        sample = np.concatenate(frames[: min(len(frames), 10)])
        p["kiss_max_range"] = round(float(np.percentile(np.linalg.norm(sample, axis=1), 99)), 2)
    if p["kiss_voxel"] is None:
        p["kiss_voxel"] = p["kiss_max_range"] / 100.0
    return p


def load_frames(path: str) -> tuple[list[np.ndarray], str]:
    with np.load(path, allow_pickle=False) as data:
        keys = sorted((k for k in data.files if k.startswith("frame_")), key=lambda k: int(k[6:]))
        frames = [np.ascontiguousarray(data[k], dtype=np.float64)[:, :3] for k in keys]
        sensor = str(data["sensor"]) if "sensor" in data.files else ""
    frames = [np.ascontiguousarray(f[np.isfinite(f).all(axis=1)]) for f in frames]
    return frames, sensor


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", required=True, help="npz with frame_XXXXXX and sensor")
    parser.add_argument("--out", required=True, help="JSON written here")
    parser.add_argument(
        "--methods", default=",".join(METHODS), help="comma list of " + str(METHODS)
    )
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--voxel", type=float, default=None, help="downsampling leaf (m)")
    parser.add_argument("--sensor", choices=sorted(DEFAULTS), default=None, help="overrides npz")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override one DEFAULTS entry (repeatable), e.g. --set max_correspondence=0.5",
    )
    args = parser.parse_args(argv)

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in methods if m not in RUNNERS]
    if unknown:
        parser.error(f"unknown methods {unknown}; choose among {list(METHODS)}")
    frames, sensor = load_frames(args.frames)
    sensor = args.sensor or sensor
    if sensor not in DEFAULTS:
        parser.error(f"sensor {sensor!r} not in {sorted(DEFAULTS)}: give --sensor")
    if not frames:
        parser.error(f"no frame_XXXXXX arrays in {args.frames}")
    overrides = {}
    for item in args.set:
        key, _, value = item.partition("=")
        if key not in DEFAULTS[sensor]:
            parser.error(f"--set {key}: not one of {sorted(DEFAULTS[sensor])}")
        overrides[key] = None if value.lower() == "none" else float(value)
    params = resolve_params(sensor, frames, args.voxel, overrides)

    report: dict[str, Any] = {
        "frames": os.path.abspath(args.frames),
        "sensor": sensor,
        "n_frames": len(frames),
        "threads": THREADS,
        "methods": {},
    }
    for name in methods:
        runner, dist = RUNNERS[name]
        entry: dict[str, Any] = {
            "version": _version(dist),
            "params": {**params, "threads": THREADS},
        }
        try:
            result = runner(frames, params, THREADS)
        except ImportError as exc:
            entry["error"] = f"not installed: {exc}"
        except Exception as exc:
            entry["error"] = f"{type(exc).__name__}: {exc}"
            entry["traceback"] = traceback.format_exc(limit=4)
        else:
            times = result["times"]
            entry.update(
                poses=[pose.tolist() for pose in result["poses"]],
                ms_per_frame=1e3 * float(np.mean(times)),
                ms_per_frame_median=1e3 * float(np.median(times)),
                total_s=float(np.sum(times)),
                version=result["version"],
            )
        report["methods"][name] = entry
        status = entry.get("error") or f"{entry['ms_per_frame']:.1f} ms/frame"
        print(f"{name}: {status}", file=sys.stderr)

    with open(args.out, "w") as f:
        json.dump(report, f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
