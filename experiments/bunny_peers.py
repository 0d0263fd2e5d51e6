"""Issue 17 figures: pairwise ICP and whole-registration time vs Open3D and small_gicp, units
and order, and evo reading torchslam's TUM/KITTI trajectories.

1. **Pairwise ICP**, bun045 → bun000 at full resolution (40k points each), 1 and 2 threads,
   every library from the same start (bun.conf's relative pose perturbed by 2.2° and 4 mm)
   with the same 5 mm correspondence gate and at most 30 iterations. Times are split into
   *prep* (normals/covariances and the target's search tree) and *align* (the iterations).
   torchslam runs twice: its default (the gate shrinks with the inlier RMS, 10 % trimmed)
   and with the peers' fixed gate and no trimming. The peers run in a subprocess of
   ``/work/peers-venv`` (``--peers-python``); runs alternate torchslam / peers and 1 / 2
   threads, 1-thread runs of every library are pinned to the same core (``taskset -c``),
   and the table gives medians, the ratios to small_gicp and the load average (the machine
   may be shared).
2. **Whole registration** of the 10 scans, shuffled and in millimetres, no chain order
   (``torchslam.registration.register``), 1 and 2 threads, errors vs bun.conf (scaled):
   rotation and the scan centroid's displacement. For comparison small_gicp (GICP) and
   Open3D (point-to-plane ICP) refine the same spanning tree's pairs from torchslam's coarse
   alignment, and their relative poses are composed along the tree (neither library has a
   global, order-free multiview registration of its own in Python; Open3D's multiway pose
   graph needs the pairs given).
3. **evo**: the poses written as TUM and KITTI files (``torchslam.io.trajectories``) are
   read by ``evo_traj`` and compared with bun.conf by ``evo_ape`` (skipped without evo).

Usage: python experiments/bunny_peers.py [--data DIR] [--repeats N] [--whole-repeats N]
       [--skip-whole]
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import random
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from torchslam import registration
from torchslam.data import fetch
from torchslam.io import trajectories
from torchslam.io.stanford import read_conf, relative_to_first, stack
from torchslam.lie import se3
from torchslam.registration import icp

PEERS_PYTHON = Path("/work/peers-venv/bin/python")
SCANS = ["bun000", "bun045", "bun090", "bun180", "bun270", "bun315", "chin", "ear_back"]
SCANS += ["top2", "top3"]
GATE = 0.005  # metres
PERTURBATION = (0.03, 0.02, -0.02, 0.003, -0.002, 0.002)  # ω (rad), v (m): 2.2°, 4 mm
# The peers' gates on the tree pairs, in voxels (2 mm): torchslam's finest level starts at 5
# and shrinks to 1.
CHAIN_GATES = (5, 1)

# ----------------------------------------------------------------------------- peers (subprocess)

PEER_WORKER = r"""
import json, sys, time
import numpy as np
job = json.loads(sys.argv[1])
z = np.load(job["npz"])
out = {}
def t():
    return time.perf_counter()
threads = job["threads"]
gate, iters = job["gate"], job["iterations"]
try:
    import small_gicp
    A, B, init = z["target"], z["source"], z["init"]
    for kind in ("GICP", "PLANE_ICP"):
        s = t()
        tg = small_gicp.PointCloud(A); sr = small_gicp.PointCloud(B)
        tree = small_gicp.KdTree(tg, num_threads=threads)
        if kind == "GICP":
            small_gicp.estimate_covariances(tg, tree, 20, threads)
            stree = small_gicp.KdTree(sr, num_threads=threads)
            small_gicp.estimate_covariances(sr, stree, 20, threads)
        else:
            small_gicp.estimate_normals(tg, tree, 12, threads)
        p = t()
        r = small_gicp.align(tg, sr, tree, init, kind, max_correspondence_distance=gate,
                             num_threads=threads, max_iterations=iters,
                             rotation_epsilon=1e-4, translation_epsilon=1e-6)
        out["small_gicp " + kind] = dict(prep=p - s, align=t() - p, iterations=r.iterations,
                                         T=np.asarray(r.T_target_source).tolist())
    for factor in (job["chain_gates"] if "chain" in z.files else ()):
        s = t()
        Ts = []
        for (a, b), T0 in zip(z["chain"], z["chain_init"]):
            r = small_gicp.align(z[f"scan{a}"], z[f"scan{b}"], T0, "GICP",
                                 downsampling_resolution=job["voxel"],
                                 max_correspondence_distance=factor * job["voxel"],
                                 num_threads=threads, max_iterations=iters)
            Ts.append(np.asarray(r.T_target_source).tolist())
        out[f"small_gicp chain {factor}"] = dict(seconds=t() - s, T=Ts)
except ImportError as e:
    out["small_gicp"] = dict(skipped=str(e))
try:
    import open3d as o3d
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    for factor in (job["chain_gates"] if "chain" in z.files else ()):
        s = t()
        Ts = []
        voxel = job["voxel"]
        crit = o3d.pipelines.registration.ICPConvergenceCriteria(1e-6, 1e-6, iters)
        est = o3d.pipelines.registration.TransformationEstimationPointToPlane()
        for (a, b), T0 in zip(z["chain"], z["chain_init"]):
            clouds = []
            for k in (a, b):
                c = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(z[f"scan{k}"]))
                c = c.voxel_down_sample(voxel)
                c.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(12))
                clouds.append(c)
            r = o3d.pipelines.registration.registration_icp(
                clouds[1], clouds[0], factor * voxel, T0, est, crit)
            Ts.append(np.asarray(r.transformation).tolist())
        out[f"open3d chain {factor}"] = dict(seconds=t() - s, T=Ts)
    A, B, init = z["target"], z["source"], z["init"]
    s = t()
    tg = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(A))
    sr = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(B))
    tg.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(12))
    p = t()
    crit = o3d.pipelines.registration.ICPConvergenceCriteria(1e-6, 1e-6, iters)
    est = o3d.pipelines.registration.TransformationEstimationPointToPlane()
    r = o3d.pipelines.registration.registration_icp(sr, tg, gate, init, est, crit)
    out["open3d point_to_plane"] = dict(prep=p - s, align=t() - p, iterations=None,
                                        T=np.asarray(r.transformation).tolist())
except ImportError as e:
    out["open3d"] = dict(skipped=str(e))
print(json.dumps(out))
"""


def cpus(threads: int) -> set[int] | None:
    """The CPUs a run on ``threads`` threads is confined to: one fixed core for 1 thread (as
    ``taskset -c``), all of this process's otherwise; None where affinity is unsupported."""
    if not hasattr(os, "sched_getaffinity"):
        return None
    allowed = sorted(os.sched_getaffinity(0))
    return {allowed[0]} if threads == 1 else set(allowed)


@contextlib.contextmanager
def pinned(threads: int) -> Iterator[None]:
    """This process on :func:`cpus` (threads) for the duration (restored after)."""
    target = cpus(threads)
    if target is None:
        yield
        return
    before = os.sched_getaffinity(0)
    os.sched_setaffinity(0, target)
    try:
        yield
    finally:
        os.sched_setaffinity(0, before)


def run_peers(python: Path, npz: Path, threads: int) -> dict:
    """Time the peers once in a fresh subprocess (thread count fixed before their import,
    on :func:`cpus` (threads))."""
    env = dict(os.environ, OMP_NUM_THREADS=str(threads))
    job = json.dumps(
        {
            "npz": str(npz),
            "threads": threads,
            "gate": GATE,
            "iterations": 30,
            "voxel": 0.002,
            "chain_gates": CHAIN_GATES,
        }
    )
    target = cpus(threads)
    done = subprocess.run(
        [str(python), "-c", PEER_WORKER, job],
        capture_output=True,
        text=True,
        env=env,
        check=False,
        preexec_fn=None if target is None else lambda: os.sched_setaffinity(0, target),
    )
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1] if done.stderr else "failed"}
    return json.loads(done.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------- torchslam


def errors(T: np.ndarray, T_true: torch.Tensor, centroid: torch.Tensor) -> tuple[float, float]:
    """Rotation error (degrees) and error of the source centroid's image (mm)."""
    E = se3.inverse(T_true) @ torch.as_tensor(T, dtype=torch.float64)
    angle = float(torch.rad2deg(torch.linalg.vector_norm(se3.log(E)[:3])))
    moved = torch.as_tensor(T, dtype=torch.float64)[:3, :3] @ centroid
    moved = moved + torch.as_tensor(T, dtype=torch.float64)[:3, 3]
    truth = T_true[:3, :3] @ centroid + T_true[:3, 3]
    return angle, float(torch.linalg.vector_norm(moved - truth)) * 1000


def torchslam_pair(target, source, init, threads: int, fixed_gate: bool) -> dict:
    torch.set_num_threads(threads)
    tic = time.perf_counter()
    normals = icp.estimate_normals(target, 12)
    prep = time.perf_counter() - tic
    config = icp.ICPConfig(
        method="point_to_plane",
        max_iterations=30,
        max_distance=GATE,
        min_distance=GATE if fixed_gate else 0.001,
        gate_scale=None if fixed_gate else 3.0,
        trim_fraction=1.0 if fixed_gate else 0.9,
        relative_tolerance=1e-4,
        rotation_tolerance_deg=1e-4 * 180 / np.pi,  # small_gicp's epsilons
        translation_tolerance=1e-6,
    )
    tic = time.perf_counter()
    result = icp.icp(source, target, init, config, normals)
    align = time.perf_counter() - tic
    return dict(
        prep=prep,
        align=align,
        iterations=int(result.iterations),
        T=result.transform.numpy().tolist(),
    )


def pairwise_table(data: Path, repeats: int, peers: Path | None) -> None:
    _, (target, source) = registration.load_scans([data / "bun000.ply", data / "bun045.ply"])
    conf = read_conf(data / "bun.conf")
    truth = se3.inverse(conf["bun000"]) @ conf["bun045"]
    init = se3.exp(torch.tensor(PERTURBATION, dtype=torch.float64)) @ truth
    centroid = source.mean(0)
    rows: dict[tuple[str, int], list[dict]] = {}
    before = load()
    with tempfile.TemporaryDirectory() as tmp:
        npz = Path(tmp) / "pair.npz"
        np.savez(npz, target=target.numpy(), source=source.numpy(), init=init.numpy())
        for _ in range(repeats):
            for threads in (1, 2):  # alternate: torchslam, peers, 1 and 2 threads
                for fixed in (False, True):
                    label = "torchslam point_to_plane" + (" (fixed gate)" if fixed else "")
                    with pinned(threads):
                        run = torchslam_pair(target, source, init, threads, fixed)
                    rows.setdefault((label, threads), []).append(run)
                if peers is not None:
                    for label, run in run_peers(peers, npz, threads).items():
                        rows.setdefault((label, threads), []).append(run)
    print(f"pairwise ICP bun045 → bun000, full resolution ({len(source)} → {len(target)} points),")
    print(
        f"start 2.2° / 4 mm off bun.conf, gate {GATE * 1000:g} mm, ≤ 30 iterations; medians of "
        f"{repeats} alternating runs (1 thread: all pinned to one core); load average "
        f"{before} before, {load()} after"
    )
    print(
        f"  {'method':<38} {'thr':>3} {'prep s':>7} {'align s':>8} {'total s':>8} {'iters':>5} "
        f"{'rot°':>6} {'mm':>6}"
    )
    for (label, threads), runs in sorted(rows.items(), key=lambda kv: (kv[0][0], kv[0][1])):
        if "skipped" in runs[0] or "error" in runs[0]:
            print(
                f"  {label:<38} {threads:>3} skipped: {runs[0].get('skipped') or runs[0]['error']}"
            )
            continue
        prep = statistics.median(r["prep"] for r in runs)
        align = statistics.median(r["align"] for r in runs)
        rot, mm = errors(np.array(runs[-1]["T"]), truth, centroid)
        iters = runs[-1]["iterations"]
        print(
            f"  {label:<38} {threads:>3} {prep:7.3f} {align:8.3f} {prep + align:8.3f} "
            f"{'-' if iters is None else iters:>5} {rot:6.3f} {mm:6.3f}"
        )
    print(
        "  (rot°, mm: error of the result vs bun.conf — itself good to ~0.2° — at the source "
        "centroid)"
    )

    def total(label: str, threads: int) -> float | None:
        runs = rows.get((label, threads), [])
        if not runs or "prep" not in runs[0]:
            return None
        return statistics.median(r["prep"] + r["align"] for r in runs)

    for label in ("torchslam point_to_plane", "torchslam point_to_plane (fixed gate)"):
        ours = {t: total(label, t) for t in (1, 2)}
        peer = {t: total("small_gicp GICP", t) for t in (1, 2)}
        parts = [
            f"{t} thread(s) {ours[t] / peer[t]:.2f}× small_gicp GICP"
            for t in (1, 2)
            if ours[t] and peer[t]
        ]
        if ours[1] and ours[2]:
            parts.append(f"2 threads vs 1: {ours[1] / ours[2]:.2f}× faster")
        print(f"  {label}: " + "; ".join(parts))


# ----------------------------------------------------------------------------- whole registration


def whole_registration(data: Path, peers: Path | None, repeats: int = 1) -> None:
    names = list(SCANS)
    random.Random(17).shuffle(names)
    _, clouds = registration.load_scans([data / f"{n}.ply" for n in names])
    clouds_mm = [c * 1000 for c in clouds]
    reference = relative_to_first(stack(read_conf(data / "bun.conf"), names), names.index("bun000"))
    reference[:, :3, 3] *= 1000
    frame = names.index("bun000")
    centroids = torch.stack([c.mean(0) for c in clouds_mm])
    print()
    print(f"whole registration: 10 scans in millimetres, shuffled ({', '.join(names)}), no chain")
    print(f"order; wall seconds (median of {repeats}), errors vs bun.conf over the 9 scans")
    print(f"other than bun000 (load average before: {load()})")
    header = (
        f"  {'method':<46} {'thr':>3} {'s':>6} {'rot° mean':>9} {'max':>6} {'cen mm':>7} {'max':>6}"
    )
    print(header)
    result = None
    for threads in (1, 2):
        torch.set_num_threads(threads)
        times = []
        for _ in range(repeats):
            with pinned(threads):
                tic = time.perf_counter()
                result = registration.register(
                    names, clouds_mm, registration.RegisterConfig(), frame=frame
                )
                times.append(time.perf_counter() - tic)
        assert result is not None
        seconds = statistics.median(times)
        print(
            table_row(
                "torchslam register (search + tree + joint)",
                threads,
                seconds,
                result.poses,
                reference,
                centroids,
                frame,
            )
        )
        print(
            table_row(
                "  its spanning-tree poses (before the joint)",
                threads,
                None,
                result.chained,
                reference,
                centroids,
                frame,
            )
        )
    assert result is not None
    stages = ", ".join(f"{k} {v:.1f}" for k, v in result.seconds.items())
    tree = ", ".join(f"{names[a]}←{names[b]}" for a, b in result.chain.tree_edges)
    print(
        f"  (torchslam stages, last run: {stages} s; voxel size {result.voxel_size:g} mm "
        f"(derived), ok={result.ok}, joint pairs {len(result.refinement.pairs)}, tree: {tree})"
    )
    if peers is None:
        return
    edges = result.chain.tree_edges
    with tempfile.TemporaryDirectory() as tmp:
        npz = Path(tmp) / "chain.npz"
        coarse = {f"scan{k}": clouds[k].numpy() for k in range(len(names))}
        init = [relative_pose(result.chained, a, b, metres=True) for a, b in edges]
        np.savez(
            npz,
            target=clouds[0].numpy(),
            source=clouds[1].numpy(),
            init=np.eye(4),
            chain=np.array(edges),
            chain_init=np.array(init),
            **coarse,
        )
        for threads in (1, 2):
            runs = [run_peers(peers, npz, threads) for _ in range(repeats)]
            for (key, peer), factor in itertools.product(
                (("small_gicp", "small_gicp GICP"), ("open3d", "Open3D point-to-plane")),
                CHAIN_GATES,
            ):
                key, label = f"{key} chain {factor}", f"{peer}, tree pairs, gate {2 * factor} mm"
                if key not in runs[-1]:
                    continue
                seconds = statistics.median(r[key]["seconds"] for r in runs)
                poses = chain_tree(runs[-1][key]["T"], edges, len(names), frame)
                print(table_row(label, threads, seconds, poses, reference, centroids, frame))
    print(
        "  (the peers refine only the spanning tree's pairs, from torchslam's spanning-tree "
        "poses, each pair downsampled to 2 mm, their results composed along the tree: no "
        "global search, no joint solve)"
    )


def chain_tree(relative: list, edges: list[tuple[int, int]], m: int, frame: int) -> torch.Tensor:
    """Poses in mm, in the frame of scan ``frame``, composed along the tree's edges (parent,
    child) from relative transforms in metres (child → parent)."""
    poses: dict[int, torch.Tensor] = {edges[0][0]: torch.eye(4, dtype=torch.float64)}
    pending = list(zip(edges, relative, strict=True))
    while pending:
        rest = []
        for (a, b), T in pending:
            if a in poses:
                step = torch.tensor(T, dtype=torch.float64)
                step[:3, 3] *= 1000
                poses[b] = poses[a] @ step
            else:
                rest.append(((a, b), T))
        pending = rest
    stacked = torch.stack([poses[i] for i in range(m)])
    return se3.inverse(stacked[frame]) @ stacked


def table_row(label, threads, seconds, poses, reference, centroids, frame) -> str:
    rot, cen = pose_errors_mm(poses, reference, centroids, frame)
    time_s = "" if seconds is None else f"{seconds:6.1f}"
    return (
        f"  {label:<46} {threads:>3} {time_s:>6} {float(rot.mean()):9.3f} "
        f"{float(rot.max()):6.3f} {float(cen.mean()):7.3f} {float(cen.max()):6.3f}"
    )


def pose_errors_mm(poses, reference, centroids, frame) -> tuple[torch.Tensor, torch.Tensor]:
    """Rotation error (degrees) and centroid error (mm) of every scan but ``frame``."""
    others = [i for i in range(len(poses)) if i != frame]
    E = se3.inverse(reference) @ poses
    rot = torch.rad2deg(torch.linalg.vector_norm(se3.log(E)[:, :3], dim=-1))[others]
    moved = se3.act(poses, centroids)  # centroid i by pose i, (m, 3)
    truth = se3.act(reference, centroids)
    return rot, torch.linalg.vector_norm(moved - truth, dim=-1)[others]


def load() -> str:
    """The 1-minute load average and the CPU count (how busy the machine was)."""
    if not hasattr(os, "getloadavg"):
        return "unknown"
    return f"{os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs"


def relative_pose(poses: torch.Tensor, a: int, b: int, metres: bool) -> np.ndarray:
    T = (se3.inverse(poses[a]) @ poses[b]).clone()
    if metres:
        T[:3, 3] /= 1000
    return T.numpy()


# ----------------------------------------------------------------------------- evo


def evo_check(data: Path, result_poses: torch.Tensor | None = None) -> None:
    print()
    evo_traj = shutil.which("evo_traj") or "/work/peers-venv/bin/evo_traj"
    evo_ape = shutil.which("evo_ape") or "/work/peers-venv/bin/evo_ape"
    if not (os.access(evo_traj, os.X_OK) and os.access(evo_ape, os.X_OK)):
        print("evo: skipped (evo_traj/evo_ape not installed; pip install evo)")
        return
    names = list(SCANS)
    reference = relative_to_first(stack(read_conf(data / "bun.conf"), names), 0)
    estimate = reference @ se3.exp(torch.tensor([0.002, 0, 0, 0.0005, 0, 0], dtype=torch.float64))
    env = dict(os.environ, MPLBACKEND="Agg")
    with tempfile.TemporaryDirectory() as tmp:
        for fmt in ("tum", "kitti"):
            ref, est = Path(tmp) / f"ref_{fmt}.txt", Path(tmp) / f"est_{fmt}.txt"
            trajectories.write_trajectory(ref, reference, fmt, names=names, frame="bun000")
            trajectories.write_trajectory(est, estimate, fmt, names=names, frame="bun000")
            traj = subprocess.run(
                [evo_traj, fmt, str(est)], capture_output=True, text=True, env=env, check=False
            )
            ape = subprocess.run(
                [evo_ape, fmt, str(ref), str(est)],
                capture_output=True,
                text=True,
                env=env,
                check=False,
            )
            info = next((ln.strip() for ln in traj.stdout.splitlines() if "poses" in ln), "?")
            rmse = next((ln.split()[-1] for ln in ape.stdout.splitlines() if "rmse" in ln), "?")
            print(
                f"evo {fmt}: evo_traj exit {traj.returncode} ({info}); evo_ape exit "
                f"{ape.returncode}, APE rmse {rmse} (expected 0.0005: every pose offset by "
                "0.5 mm along its own x axis)"
            )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--data", type=Path, default=None, help="bunny data folder (default: the data set 'bunny')"
    )
    parser.add_argument("--repeats", type=int, default=7, help="alternating runs per method")
    parser.add_argument(
        "--whole-repeats", type=int, default=1, help="runs of the whole registration"
    )
    parser.add_argument("--peers-python", type=Path, default=PEERS_PYTHON)
    parser.add_argument("--skip-whole", action="store_true", help="pairwise table and evo only")
    args = parser.parse_args(argv)
    args.data = args.data or fetch("bunny")
    if not (args.data / "bun.conf").is_file():
        print(f"no bun.conf in {os.path.normpath(args.data)}; pass --data", file=sys.stderr)
        return 2
    peers = args.peers_python if args.peers_python.is_file() else None
    if peers is None:
        print(f"peers: skipped ({args.peers_python} not found)")
    pairwise_table(args.data, args.repeats, peers)
    if not args.skip_whole:
        whole_registration(args.data, peers, args.whole_repeats)
    evo_check(args.data)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
