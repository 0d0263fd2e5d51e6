"""ICP-SLAM on real sequences, side by side with the odometry users would pick instead.

For each sequence (default: the library's three data sets of sequences, fetched by
``torchslam.data.fetch``: 7-Scenes depth frames, the hku2-loop and quick-shack LiDAR
keyframes) and each thread count (default 1 and 2):

- torchslam: the whole run as a user runs it, **reading included**: the frames are read with
  ``torchslam.io.frames`` and fed to the streaming :class:`torchslam.slam.SLAM` (the defaults
  of ``SLAMConfig.for_sensor``), then ``finish()`` (loop closures, pose graph). Time and RSS
  are recorded after every frame;
- the peers (``experiments/slam_peers.py`` in the peers venv, when there is one): Open3D
  point-to-plane, small_gicp frame-to-frame and frame-to-model, KISS-ICP, on the same points
  (for depth: the same back-projected pixels, stride and range as torchslam's); their times
  are processing only (reading excluded), as they report them.

ATE: RMSE of the positions after an SE(3) alignment onto the reference (evo_ape --align);
RPE: RMSE of the translation of successive-frame motions (evo_rpe --delta 1). Reference poses
are the dataset's (7-Scenes: KinectFusion; LiDAR: a LiDAR-inertial system with loop closure,
a pseudo ground truth).

Variants (``--variants``): each sequence can also be run reversed and thinned, a new sequence
of the same kind each (``full``: as recorded; ``rev``: last frame first; ``every2``: every
second frame; ``every2+1``: every second frame from the second; ``rev-every2+1``: both), every
method on the same frames and the reference indexed alike: a stand-in for sequences the
defaults were not tuned on. ``--variants robustness`` runs the six variants
``full,every2,every2+1`` forward and reversed.

Usage::

    .venv/bin/python experiments/slam_sequences.py [--sequences rgbd-7scenes,...|FOLDER]
        [--threads 1,2] [--variants full,rev,every2,...|robustness]
        [--peers-python ../peers-venv/bin/python]
        [--no-peers] [--refine N] [--option NAME=VALUE ...] [--out out/slam_sequences]
        [--depth-scale 5000 --intrinsics K.txt --reference groundtruth.txt]

A sequence of one's own (a folder) is read as ``torchslam slam`` reads it; its reference
poses are matched to the frames by index, or by timestamp for a TUM file at another rate.

Writes ``OUT/results.json`` and ``OUT/time_rss.png`` (time per frame and RSS against the frame
index, torchslam, per sequence).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from torchslam.data import fetch
from torchslam.lie import se3

ROOT = Path(__file__).resolve().parents[1]
# the library's data sets (torchslam.data.files: mirrored, cached or downloaded)
SEQUENCES = ("rgbd-7scenes", "lidar-hku2-loop", "lidar-quick-shack")


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _reference(folder: Path, count: int, times: np.ndarray | None, path: Path | None = None):
    """The reference pose of every frame, (count, 4, 4) frame → world, NaN where a frame has
    none: one pose per frame (by index), or a TUM file at another rate matched by timestamp
    (``torchslam.io.frames.associate_timestamps``, 0.01 s as evo: TUM RGB-D's
    groundtruth.txt). ``path``: the file or folder, else the folder's optimized_poses.txt,
    groundtruth.txt or per-frame *.pose.txt."""
    from torchslam.cli.slam import MAX_TIME_DIFFERENCE
    from torchslam.io import frames as fio

    candidates = [path] if path is not None else []
    candidates += [folder / "optimized_poses.txt", folder / "groundtruth.txt", folder]
    for candidate in candidates:
        if not candidate.exists():
            continue
        try:
            poses, stamps = fio.read_reference_poses(candidate)
        except ValueError:
            continue
        if poses.shape[0] == count:
            return poses
        if stamps is not None and times is not None:
            frames, matched = fio.associate_timestamps(times, stamps, MAX_TIME_DIFFERENCE)
            if len(frames) >= 3:
                full = torch.full((count, 4, 4), torch.nan, dtype=torch.float64)
                full[torch.from_numpy(frames)] = poses[torch.from_numpy(matched)]
                return full
    raise ValueError(f"no reference poses for {folder} (one per frame, or TUM timestamps)")


def _errors(poses: torch.Tensor, reference: torch.Tensor) -> dict[str, float]:
    """ATE and RPE over the frames with a reference pose (rows of ``reference`` not NaN)."""
    from torchslam.cli.slam import trajectory_errors

    known = ~reference.flatten(1).isnan().any(1)
    return trajectory_errors(poses[known], reference[known])


# frame_reader's options for depth images (--depth-scale, --intrinsics)
READ_OPTIONS: dict[str, object] = {}
ROBUSTNESS = ("full", "every2", "every2+1", "rev", "rev-every2", "rev-every2+1")


def variant_indices(spec: str, count: int) -> list[int]:
    """The frame indices of a variant of a sequence of ``count`` frames: ``full``, ``rev``,
    ``everyN``, ``everyN+K`` (every N-th frame from the K-th), ``rev-…`` (reversed first)."""
    order = list(range(count))
    rest = spec
    if rest == "full":
        return order
    if rest.startswith("rev"):
        order, rest = order[::-1], rest[3:].lstrip("-")
    if rest:
        if not rest.startswith("every"):
            raise ValueError(
                f"variant {spec!r}: expected full, rev, everyN, everyN+K, rev-everyN+K"
            )
        every, _, offset = rest[5:].partition("+")
        order = order[int(offset or 0) :: int(every)]
    return order


def _reader(folder: Path, variant: str):
    """frame_reader(folder) restricted to a variant: (read, count, times, sensor, indices of
    the frames used, number of frames in the sequence)."""
    from torchslam.slam import frame_reader

    read, count, times, sensor = frame_reader(folder, **READ_OPTIONS)
    indices = variant_indices(variant, count)
    if times is not None:
        times = np.asarray(times)[indices]
        if variant.startswith("rev"):
            times = None  # the streaming API wants time to run forward: frame indices instead
    return (lambda i: read(indices[i])), len(indices), times, sensor, indices, count


def run_torchslam(
    folder: Path, threads: int, overrides: dict | None = None, variant: str = "full"
) -> tuple[dict, int, str]:
    """One run with the sensor's defaults (``overrides``: SLAMConfig options instead) on a
    variant of the sequence (:func:`variant_indices`)."""
    from torchslam.slam import SLAM, SLAMConfig, frame_reader

    torch.set_num_threads(threads)
    read, count, times, sensor, indices, total = _reader(folder, variant)
    times_all = frame_reader(folder, **READ_OPTIONS)[2]
    slam = SLAM(SLAMConfig.for_sensor(sensor, **(overrides or {})))
    per_frame, rss = [], []
    start = time.perf_counter()
    for i in range(count):
        tic = time.perf_counter()
        slam.add(read(i), None if times is None else float(times[i]))
        per_frame.append(time.perf_counter() - tic)
        rss.append(_rss_mb())
    tic = time.perf_counter()
    result = slam.finish()
    finish = time.perf_counter() - tic
    wall = time.perf_counter() - start
    record = {
        "poses": result.poses,
        "odometry_poses": result.odometry_poses,
        "wall_s": wall,
        "finish_s": finish,
        "ms_per_frame": 1000 * wall / count,
        "frame_ms": [1000 * t for t in per_frame],
        "rss_mb": rss,
        "keyframes": len(result.keyframe_frames),
        "loops_accepted": len(result.accepted_loops),
        "loops_rejected": len(result.rejected_loops),
        "unreliable": sum(not f.trusted for f in result.frames),
        "slam": (slam, result),
        "indices": (indices, total, times_all),
    }
    return record, count, sensor


def loop_fits(slam, result, reference: torch.Tensor) -> list[tuple[int, int, float, float]]:
    """For each accepted loop closure (frames a, b): the residual RMS of keyframe b against
    the submap the closure was verified on, placed by the closure's measurement and by the
    reference's relative pose T_a⁻¹T_b (same gate, the judging one). Where the reference's
    placement fits worse, a closure that moves the trajectory away from the reference says
    more about the reference (a pseudo ground truth on LiDAR) than about the closure."""
    from scipy.spatial import cKDTree

    from torchslam.registration.quality import QualityThresholds, alignment_quality
    from torchslam.slam.loops import _submap
    from torchslam.slam.odometry import JUDGE_VOXELS

    cfg, keyframes, frames = result.config, slam.keyframes, result.keyframe_frames
    gate = JUDGE_VOXELS * cfg.voxel
    thresholds = QualityThresholds(cfg.loop_min_fitness, cfg.loop_max_rms_voxels * cfg.voxel, 0)
    out = []
    for c in result.accepted_loops:
        target, normals = _submap(keyframes, c.first, cfg.loop_window)
        tree = cKDTree(target.numpy())
        a, b = frames[c.first], frames[c.second]
        if bool(reference[[a, b]].isnan().any()):
            continue  # a frame with no reference pose (not matched by timestamp)
        truth = se3.compose(se3.inverse(reference[a]), reference[b])
        rms = []
        for Z in (c.measurement, truth):
            T = se3.compose(keyframes[c.first].pose, Z)
            q = alignment_quality(
                keyframes[c.second].points, target, normals, T, gate, thresholds,
                noise_floor=0.1 * cfg.voxel, tree=tree,
            )  # fmt: skip
            rms.append(q.rms)
        out.append((a, b, rms[0], rms[1]))
    return out


def run_planted(folder: Path) -> dict:
    """The sequence once more with a planted wrong loop candidate (the two keyframes farthest
    apart, verified by ICP as a detected candidate is) and a wrong closure forced into the
    graph (the identity between them, as confident as an odometry step)."""
    from torchslam.slam import SLAM, SLAMConfig

    torch.set_num_threads(1)
    read, count, _, sensor, _, _ = _reader(folder, "full")
    slam = SLAM(SLAMConfig.for_sensor(sensor))
    for i in range(count):
        slam.add(read(i))
    positions = torch.stack([kf.pose[:3, 3] for kf in slam.keyframes])
    distance = torch.cdist(positions, positions)
    a, b = sorted(int(i) for i in divmod(int(distance.argmax()), len(positions)))
    verified = slam.add_loop(a, b)
    forced = slam.add_loop(a, b, measurement=torch.eye(4, dtype=torch.float64))
    result = slam.finish()
    return {
        "pair": (a, b),
        "distance_m": float(distance[a, b]),
        "candidate_accepted": bool(verified.accepted),
        "candidate_reason": verified.reason,
        "forced_kept": bool(forced.kept),
        "poses": result.poses,
        "frames": (result.keyframe_frames[a], result.keyframe_frames[b]),
        "measurement": verified.measurement,
    }


def _clouds(folder: Path, variant: str) -> list[np.ndarray]:
    """The frames as torchslam reads them (depth: its stride and range), float32, for the
    peers (read again here so that torchslam's RSS curve holds only what it keeps)."""
    read, count, _, _, _, _ = _reader(folder, variant)
    return [read(i).numpy().astype(np.float32) for i in range(count)]


def run_peers(python: str, folder: Path, sensor: str, threads: int, work: Path, variant: str):
    frames = work / "frames.npz"
    if not frames.exists():
        arrays = {f"frame_{k:06d}": c for k, c in enumerate(_clouds(folder, variant))}
        np.savez(frames, sensor=np.array(sensor), **arrays)
    out = work / f"peers_{threads}.json"
    env = dict(os.environ)
    venv_lib = str(Path(python).resolve().parents[1] / "lib")
    env["LD_LIBRARY_PATH"] = venv_lib + os.pathsep + env.get("LD_LIBRARY_PATH", "")
    command = [python, str(ROOT / "experiments" / "slam_peers.py"), "--frames", str(frames)]
    command += ["--out", str(out), "--threads", str(threads)]
    subprocess.run(command, check=True, env=env, stdout=subprocess.DEVNULL)
    return json.loads(out.read_text())["methods"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--sequences",
        default=",".join(SEQUENCES),
        help="data set names (torchslam data list) or folders of frames, comma-separated",
    )
    parser.add_argument("--threads", default="1,2")
    parser.add_argument(
        "--peers-python", default=str(ROOT.parent / "peers-venv" / "bin" / "python")
    )
    parser.add_argument("--no-peers", action="store_true")
    parser.add_argument(
        "--refine",
        type=int,
        default=None,
        help="also run torchslam with this many rounds of the joint refinement (the defaults: "
        "LiDAR 1, depth 0)",
    )
    parser.add_argument(
        "--option",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="also run torchslam with this SLAMConfig option (repeatable, all in one extra run; "
        "e.g. coarse_rotation_only=False)",
    )
    parser.add_argument(
        "--variants",
        default="full",
        help="comma-separated: full, rev, everyN, everyN+K, rev-everyN+K (frames of each "
        "sequence, reversed and/or thinned), or 'robustness' for " + ",".join(ROBUSTNESS),
    )
    parser.add_argument(
        "--no-plant", action="store_true", help="skip the planted wrong loop closure runs"
    )
    parser.add_argument(
        "--depth-scale", type=float, default=1000.0, help="depth units per metre (TUM: 5000)"
    )
    parser.add_argument("--intrinsics", type=Path, default=None, help="a 3×3 K as text")
    parser.add_argument(
        "--reference",
        type=Path,
        default=None,
        help="reference poses of a FOLDER sequence (default: its optimized_poses.txt, "
        "groundtruth.txt or *.pose.txt); TUM timestamps at another rate are matched",
    )
    parser.add_argument("--out", type=Path, default=Path("out") / "slam_sequences")
    args = parser.parse_args(argv)
    READ_OPTIONS.update(depth_scale=args.depth_scale)
    if args.intrinsics is not None:
        READ_OPTIONS["intrinsics"] = args.intrinsics
    args.out.mkdir(parents=True, exist_ok=True)
    threads = [int(t) for t in args.threads.split(",")]
    options = dict(_option(text) for text in args.option)
    peers = not args.no_peers and Path(args.peers_python).exists()
    if not peers and not args.no_peers:
        print(f"peers skipped: no {args.peers_python} (bash ../shared/tools/install-peers.sh)")
    variants = ROBUSTNESS if args.variants == "robustness" else tuple(args.variants.split(","))
    rows, series = [], {}
    for sequence, variant in [(s, v) for s in args.sequences.split(",") for v in variants]:
        folder = Path(sequence) if Path(sequence).is_dir() else fetch(sequence)
        name = sequence if variant == "full" else f"{sequence}:{variant}"
        work = args.out / name.replace("/", "_").replace(":", "_")
        work.mkdir(parents=True, exist_ok=True)
        for t in threads:
            record, _, sensor = run_torchslam(folder, t, variant=variant)
            indices, total, times_all = record.pop("indices")
            reference = _reference(folder, total, times_all, args.reference)[indices]
            odo = _errors(record["odometry_poses"], reference)
            final = _errors(record["poses"], reference)
            series.setdefault(name, record)
            rows.append({
                "sequence": name, "method": "torchslam odometry", "threads": t,
                **odo, "ms_per_frame": None,
            })  # fmt: skip
            rows.append({
                "sequence": name, "method": "torchslam SLAM", "threads": t, **final,
                "ms_per_frame": record["ms_per_frame"], "reading": True,
                "loops": f"{record['loops_accepted']} of "
                f"{record['loops_accepted'] + record['loops_rejected']}",
                "max_rss_mb": max(record["rss_mb"]),
            })  # fmt: skip
            extra = dict(options)
            if args.refine is not None:
                extra["refine_rounds"] = args.refine
            if extra:
                refined, _, _ = run_torchslam(folder, t, extra, variant)
                refined.pop("slam")
                label = ", ".join(f"{k}={v}" for k, v in extra.items())
                rows.append({
                    "sequence": name, "method": f"torchslam SLAM, {label}",
                    "threads": t,
                    "odometry_ate": _errors(refined["odometry_poses"], reference)["ate"],
                    **_errors(refined["poses"], reference),
                    "ms_per_frame": refined["ms_per_frame"], "reading": True,
                    "loops": f"{refined['loops_accepted']} of "
                    f"{refined['loops_accepted'] + refined['loops_rejected']}",
                })  # fmt: skip
            if peers:
                for method, value in run_peers(
                    args.peers_python, folder, sensor, t, work, variant
                ).items():
                    if "poses" not in value:
                        rows.append({"sequence": name, "method": method, "threads": t,
                                     "error": value.get("error")})  # fmt: skip
                        continue
                    poses = torch.tensor(value["poses"], dtype=torch.float64)
                    rows.append({
                        "sequence": name, "method": method, "threads": t,
                        **_errors(poses, reference), "ms_per_frame": value["ms_per_frame"],
                        "reading": False,
                    })  # fmt: skip
            _print([r for r in rows if r["sequence"] == name and r.get("threads") == t])
            slam_and_result = record.pop("slam")
            fits = loop_fits(*slam_and_result, reference) if t == threads[0] else []
            if fits:
                worse = sum(ref > meas for _, _, meas, ref in fits)
                print(
                    f"{name:<22} loop closures: keyframe RMS against the verified submap at the "
                    f"closure's measurement / at the reference's relative pose (m): "
                    + ", ".join(f"{a}-{b} {m:.3f}/{r:.3f}" for a, b, m, r in fits)
                    + f"; the reference fits worse at {worse} of {len(fits)}"
                )
                rows.append({"sequence": name, "method": "loop fits", "fits": fits})
        if not args.no_plant and variant == "full":
            plant = run_planted(folder)
            errors = _errors(plant.pop("poses"), reference)
            fa, fb = plant.pop("frames")
            truth = se3.compose(se3.inverse(reference[fa]), reference[fb])
            off = se3.compose(se3.inverse(truth), plant.pop("measurement"))
            plant["measurement_error_m"] = float(off[:3, 3].norm())
            base = next(
                r for r in rows if r["sequence"] == name and r["method"] == "torchslam SLAM"
            )
            # The farthest pair of a small scene may still see the same surfaces: then its
            # closure is right (its ICP result near the reference's relative pose), and being
            # accepted is the correct verdict, not a failure of the test.
            from torchslam.slam import SLAMConfig

            voxel = SLAMConfig.for_sensor(sensor).voxel
            overlapping = plant["measurement_error_m"] <= 2 * voxel
            plant["overlapping_views"] = overlapping
            rows.append({"sequence": name, "method": "planted", **plant, **errors})
            verdict = "ACCEPTED" if plant["candidate_accepted"] else "rejected"
            if overlapping:
                verdict += " (a right pair: the views overlap)"
            print(
                f"{name:<22} planted candidate: the farthest keyframes {plant['pair']} "
                f"({plant['distance_m']:.1f} m apart): {verdict} "
                f"({plant['candidate_reason']}; its ICP result is "
                f"{plant['measurement_error_m']:.2f} m from the reference); forced wrong closure "
                f"{'kept' if plant['forced_kept'] else 'dropped'}: ATE {errors['ate']:.4f} m "
                f"vs {base['ate']:.4f} m ({100 * (errors['ate'] / base['ate'] - 1):+.1f} %)"
            )
    if len(variants) > 1:
        _print_ratios(rows, threads[0])
    (args.out / "results.json").write_text(json.dumps(rows, indent=1))
    _plot(series, args.out / "time_rss.png")
    print(f"wrote {args.out / 'results.json'}, {args.out / 'time_rss.png'}")
    return 0


def _option(text: str) -> tuple[str, object]:
    """NAME=VALUE of --option: the value as a Python literal (True, 0.5, 'z'), else a string."""
    import ast

    name, sep, value = text.partition("=")
    if not sep or not name:
        raise SystemExit(f"--option: expected NAME=VALUE, got {text!r}")
    try:
        return name, ast.literal_eval(value)
    except (ValueError, SyntaxError):
        return name, value


def _print(rows: list[dict]) -> None:
    for r in rows:
        if "error" in r:
            print(f"{r['sequence']:<22} {r['method']:<20} {r['threads']}  error: {r['error']}")
            continue
        ms = "" if r.get("ms_per_frame") is None else f"{r['ms_per_frame']:7.1f} ms/frame"
        extra = " (reading included)" if r.get("reading") else ""
        loops = f"  loops {r['loops']}" if "loops" in r else ""
        print(
            f"{r['sequence']:<22} {r['method']:<20} {r['threads']}  ATE {r['ate']:8.4f} m  "
            f"RPE {r['rpe']:.4f} m  {ms}{extra}{loops}"
        )
    sys.stdout.flush()


def _print_ratios(rows: list[dict], threads: int) -> None:
    """One line per sequence variant: torchslam's ATE (odometry, SLAM) against the best peer's."""
    print(f"\nATE (m), {threads} thread(s): torchslam odometry / SLAM, the best peer, SLAM ÷ best")
    for name in dict.fromkeys(r["sequence"] for r in rows):
        here = [r for r in rows if r["sequence"] == name and r.get("threads") == threads]
        mine = {r["method"]: r["ate"] for r in here if "ate" in r}
        peers = {m: a for m, a in mine.items() if not m.startswith("torchslam")}
        odo, final = mine.get("torchslam odometry"), mine.get("torchslam SLAM")
        if not peers:
            print(f"{name:<34} {odo:8.3f} / {final:8.3f}")
            continue
        best = min(peers, key=peers.get)
        print(
            f"{name:<34} {odo:8.3f} / {final:8.3f}   {peers[best]:8.3f} ({best})   "
            f"{final / peers[best]:.2f}"
        )
        for r in here:
            if r["method"].startswith("torchslam SLAM, ") and "ate" in r:
                print(
                    f"{'  ' + r['method'][len('torchslam SLAM, ') :]:<34} "
                    f"{r['odometry_ate']:8.3f} / {r['ate']:8.3f}   "
                    f"{'':>{len(best) + 12}}   {r['ate'] / peers[best]:.2f}"
                )


def _plot(series: dict, path: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("figure skipped: matplotlib is not installed")
        return
    figure, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    for name, record in series.items():
        axes[0].plot(record["frame_ms"], lw=0.8, label=name)
        axes[1].plot(record["rss_mb"], lw=1.2, label=name)
    axes[0].set_ylabel("time per frame (ms, reading included)")
    axes[1].set_ylabel("RSS (MB)")
    axes[1].set_xlabel("frame")
    axes[0].legend()
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


if __name__ == "__main__":
    raise SystemExit(main())
