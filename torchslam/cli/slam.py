"""``torchslam slam``: ICP-SLAM on a folder of range-sensor frames (depth images or LiDAR scans).

Reads the frames of PATH (:func:`torchslam.io.frames.list_frames`: every ``.png`` for depth,
every ``.pcd``/``.bin``/``.ply``/``.npy`` for LiDAR, sorted by name, other files ignored),
runs :func:`torchslam.slam.run_sequence` with a progress bar (frames/s; on a terminal only, off
under ``--quiet``), prints a summary and writes to ``--out``:

- ``trajectory_tum.txt``: one line per frame used, in input order, frame → world (the first
  frame is the world); timestamps from the folder's ``times.txt`` (or ``--times``), else the
  frame index;
- ``trajectory_kitti.txt``: the same poses, KITTI format (evo reads both);
- ``map.ply``: the keyframes' clouds at their optimized poses, merged on the voxel grid;
- ``slam.png``: top view of the trajectory, the keyframes and the loop closures over the map
  (needs matplotlib; skipped with a message without it).

With ``--reference`` (a TUM or KITTI file, or a folder of per-frame ``*.pose.txt``, frame →
world) it prints the ATE (RMSE of positions after an SE(3) alignment, as ``evo_ape --align``)
and the RPE between successive frames (as ``evo_rpe --delta 1``), for odometry alone and after
the back end. A reference holds one pose per frame of PATH, or timestamps (TUM) at another
rate: then each frame used takes the reference pose nearest in time, within 0.01 s (evo's
``--t_max_diff``), and the errors are over the matched frames (TUM RGB-D's
``groundtruth.txt`` beside its ``depth.txt``). Exit status as :mod:`torchslam.cli`; 1 when
the pose graph solve failed.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from torchslam.cli import (
    EXIT_FAILED,
    EXIT_OK,
    _stderr,
    add_threads_argument,
    float_range,
    int_range,
    plots,
    using_threads,
)

__all__ = ["add_arguments", "main", "run", "trajectory_errors"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``torchslam slam``."""
    parser.add_argument("path", type=Path, help="folder of frames (depth .png or LiDAR scans)")
    parser.add_argument(
        "--sensor", choices=("depth", "lidar"), default=None, help="(inferred from the files)"
    )
    parser.add_argument(
        "--intrinsics",
        type=Path,
        default=None,
        help="depth: a 3×3 K as text (default: camera-intrinsics.txt beside the frames)",
    )
    parser.add_argument(
        "--depth-scale",
        type=float_range(0.0, 1e9, low_open=True),
        default=1000.0,
        help="depth units per metre (1000, as Open3D; TUM files use 5000)",
    )
    parser.add_argument(
        "--voxel",
        type=float_range(0.0, 1e6, low_open=True),
        default=None,
        help="voxel pitch in metres (depth 0.04, lidar 0.25)",
    )
    parser.add_argument(
        "--max-range",
        type=float_range(0.0, 1e6, low_open=True),
        default=None,
        help="drop points farther than this, metres (depth 4, lidar 60)",
    )
    parser.add_argument(
        "--every", type=int_range(1, 1_000_000), default=1, help="use every N-th frame (1)"
    )
    parser.add_argument("--no-loops", action="store_true", help="odometry only: no loop closure")
    parser.add_argument(
        "--refine",
        type=int_range(0, 100),
        default=None,
        help="rounds of the joint multiview ICP-SLAM refinement of the keyframes (LiDAR 1, "
        "depth 0)",
    )
    parser.add_argument(
        "--times", type=Path, default=None, help="timestamps file (default: the folder's times.txt)"
    )
    parser.add_argument(
        "--reference",
        type=Path,
        default=None,
        help="reference poses (TUM, KITTI, or a folder of *.pose.txt; one per frame, or TUM "
        "timestamps matched to the frames'): prints ATE and RPE",
    )
    parser.add_argument("--out", type=Path, default=Path("out"), help="output folder (out)")
    add_threads_argument(parser)


# A frame and a reference pose match when their timestamps differ by at most this (seconds):
# evo's default --t_max_diff.
MAX_TIME_DIFFERENCE = 0.01
# An SE(3) alignment and an RPE need a few matched frames.
MIN_MATCHED_FRAMES = 3


def _match_by_time(times, reference_times, args) -> tuple[np.ndarray, np.ndarray]:
    """(frames used, reference rows) matched by timestamp; ValueError when too few match."""
    from torchslam.io import frames as frame_io

    if times is None:  # pragma: no cover - checked before the run
        raise ValueError(f"--reference {args.reference}: the frames have no timestamps")
    frames, matched = frame_io.associate_timestamps(times, reference_times, MAX_TIME_DIFFERENCE)
    if len(frames) < MIN_MATCHED_FRAMES:
        raise ValueError(
            f"--reference {args.reference}: {len(frames)} of {len(times)} frames have a "
            f"reference pose within {MAX_TIME_DIFFERENCE:g} s (frame times "
            f"{float(times.min()):.3f}…{float(times.max()):.3f} s, reference "
            f"{float(reference_times.min()):.3f}…{float(reference_times.max()):.3f} s); at "
            f"least {MIN_MATCHED_FRAMES} are needed"
        )
    return frames, matched


def trajectory_errors(poses, reference) -> dict[str, float]:
    """ATE (RMSE of positions after the SE(3) alignment of ``poses`` onto ``reference``) and
    the RMSE of the RPE of successive frames (translation, rotation in degrees); both (F, 4, 4)
    frame → world."""
    from torchslam import metrics
    from torchslam.lie import se3

    errors = metrics.evaluate(se3.inverse(poses), se3.inverse(reference), align="se3")
    return {
        "ate": float(errors.ate),
        "rpe": float(errors.rpe_translation.square().mean().sqrt()),
        "rpe_deg": float(errors.rpe_rotation_deg.square().mean().sqrt()),
    }


def run(
    args: argparse.Namespace,
    echo: Callable[[str], None] = print,
    warn: Callable[[str], None] = _stderr,
    *,
    progress: bool | None = None,
) -> int:
    """Run ``torchslam slam`` (module docstring); returns the exit status.

    ``progress``: show the bar (default: when stderr is a terminal and output is not quiet).

    Raises:
        ValueError: bad options or input files. OSError: unreadable or unwritable files.
    """
    from torchslam.io import frames as frame_io
    from torchslam.slam import SLAMConfig

    if args.out.exists() and not args.out.is_dir():
        raise ValueError(f"--out {args.out} exists and is not a directory")
    paths, sensor = frame_io.list_frames(args.path, args.sensor)
    overrides: dict[str, object] = {"loops": not args.no_loops}
    if args.refine is not None:
        overrides["refine_rounds"] = args.refine
    if args.voxel is not None:
        overrides["voxel"] = args.voxel
    if args.max_range is not None:
        overrides["max_range"] = args.max_range
    config = SLAMConfig.for_sensor(sensor, **overrides)
    times = None
    if args.times is not None:
        times = frame_io.read_timestamps(args.times, len(paths), [p.name for p in paths])
    used = list(range(0, len(paths), args.every))
    reference = reference_times = None
    if args.reference is not None:
        reference, reference_times = frame_io.read_reference_poses(args.reference)
        if reference.shape[0] == len(paths):
            reference, reference_times = reference[used], None  # one pose per frame
        elif reference_times is None or (
            args.times is None and frame_io.find_timestamps(paths[0].parent) is None
        ):
            raise ValueError(
                f"--reference {args.reference}: {reference.shape[0]} poses for "
                f"{len(paths)} frames: one per frame of {args.path} is needed, or timestamps "
                "on both sides to match them by time (a TUM reference file, and the frames' "
                "times.txt, depth.txt or --times)"
            )
    if progress is None:
        progress = sys.stderr.isatty() and echo is print
    wrap = None
    if progress:
        from tqdm import tqdm

        def wrap(indices):
            return tqdm(indices, total=len(used), unit="frame", file=sys.stderr, leave=False)

    echo(f"{args.path}: {len(paths)} {sensor} frames, using {len(used)} (every {args.every})")
    start = time.perf_counter()
    with using_threads(args.threads):
        from torchslam.slam import run_sequence

        result = run_sequence(
            args.path, config, intrinsics=args.intrinsics, depth_scale=args.depth_scale,
            timestamps=times, every=args.every, progress=wrap,
        )  # fmt: skip
        wall = time.perf_counter() - start
        echo(result.summary())
        echo(
            f"total {wall:.2f} s, {1000 * wall / len(used):.1f} ms/frame "
            f"({len(used) / wall:.1f} frames/s, reading included)"
        )
        _write(args.out, result, used, echo, warn)
        if reference is not None:
            frames = slice(None)
            if reference_times is not None:
                frames, matched = _match_by_time(result.timestamps, reference_times, args)
                reference = reference[matched]
                echo(
                    f"{len(frames)} of {len(used)} frames matched to {args.reference} by "
                    f"timestamp (nearest within {MAX_TIME_DIFFERENCE:g} s, as evo)"
                )
            odometry = trajectory_errors(result.odometry_poses[frames], reference)
            final = trajectory_errors(result.poses[frames], reference)
            for name, e in (("odometry", odometry), ("after back end", final)):
                echo(
                    f"{name:>15}: ATE {e['ate']:.4f} m, RPE {e['rpe']:.4f} m / "
                    f"{e['rpe_deg']:.3f}° (RMSE, successive frames; SE(3)-aligned to "
                    f"{args.reference})"
                )
    unreliable = sum(not f.trusted for f in result.frames)
    if unreliable:
        warn(
            f"warning: {unreliable} frame(s) could not be aligned reliably (kept at their best "
            "attempt; see FrameInfo.status)"
        )
    status = result.backend.graph_status if result.backend is not None else None
    if status in ("NON_FINITE", "LINEAR_SOLVE_FAILED"):
        warn(f"error: the pose graph solve failed: status {status}")
        return EXIT_FAILED
    return EXIT_OK


def _write(
    out: Path, result, used: list[int], echo: Callable[[str], None], warn: Callable[[str], None]
) -> None:
    from torchslam.io.ply import write_ply
    from torchslam.io.trajectories import write_trajectory

    out.mkdir(parents=True, exist_ok=True)
    times = None
    if result.timestamps is not None:
        stamps = result.timestamps.numpy()
        if np.isfinite(stamps).all() and (np.diff(stamps) > 0).all():
            times = stamps
    else:
        times = np.array(used, dtype=np.float64)  # the input frame index
    frame = "the first frame's sensor frame"
    write_trajectory(out / "trajectory_tum.txt", result.poses, "tum", timestamps=times, frame=frame)
    write_trajectory(out / "trajectory_kitti.txt", result.poses, "kitti", frame=frame)
    write_ply(out / "map.ply", result.map_points(), coordinate_type="float")
    written = ["trajectory_tum.txt", "trajectory_kitti.txt", "map.ply"]
    try:
        plots.plot_slam(result, out / "slam.png")
        written.append("slam.png")
    except plots.MatplotlibMissingError as error:
        warn(f"figure skipped: {error}")
    echo(f"wrote {', '.join(str(out / name) for name in written)}")


def main(argv: list[str] | None = None) -> int:
    """``python -m torchslam.cli.slam``: the same as ``torchslam slam``."""
    from torchslam import cli

    return cli.main(["slam", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    raise SystemExit(main())
