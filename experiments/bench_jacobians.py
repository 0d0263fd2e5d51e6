"""Time and peak memory of the analytic vs the jacrev Jacobian blocks of PointMapProblem.

For E = 10⁴, 10⁵, 10⁶ observations (float64, CPU, ``torch.set_num_threads(2)``) computes the
per-observation blocks ∂r/∂δ (E, 3, 6) and ∂r/∂X (E, 3, 3) with
``torchslam.problem.jacobian_blocks(..., mode)`` for mode = "analytic" (closed form
[R [X]× | −R], −R) and "jacrev" (``torch.func.jacrev`` vmapped over observations), exactly as
the solver calls it (on detached parameters, so no autograd graph is recorded).

Problem: B = 1, m = 100 poses with random twists (|ω| ≤ 3 rad), n = E / 10 points, each
observation a random (pose, point) pair; the blocks do not depend on the observed values.

Time: one fresh process per E alternates analytic and jacrev calls (after one untimed call of
each at full size), ``--runs`` pairs (five times as many at E = 10⁴); the table gives median
(min) per mode and the speed-up as the median of the per-pair ratios, so that both paths see
the same machine load. On a shared machine the small sizes are the most load-sensitive (with
2 threads an op waits for its descheduled sibling thread); the load average is printed.

Peak memory (honest, per configuration): every (E, mode) runs in its own fresh Python process
(``--worker``). The process builds its inputs, warms up on a 1,000-observation problem, then
measures the first full-size call with ``peak_memory.PeakMemory``: the extra resident memory
the call needed (peak RSS after a reset of the kernel's counter, minus the RSS before),
outputs included (27·8 bytes per observation). Measuring the first full-size call of a fresh
process matters: afterwards glibc keeps freed blocks and later calls would look cheaper.
Where the counter cannot be reset, the figure is a lower bound (the JSON says which method
was used).

Run: .venv/bin/python experiments/bench_jacobians.py [--quick]   (writes out/bench_jacobians.json)
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch
from peak_memory import PeakMemory

import torchslam
from torchslam.lie import se3
from torchslam.objective import data as data_module
from torchslam.problem import PointMapProblem

MODES = ("analytic", "jacrev")
NUM_POSES = 100
POINTS_PER_OBSERVATION = 0.1
BYTES_PER_OBSERVATION = (18 + 9) * 8  # the two float64 blocks


# --------------------------------------------------------------------------- worker


def _problem(num_observations: int, seed: int) -> PointMapProblem:
    """Random problem: m = 100 poses, n = E/10 points, E random (pose, point) observations."""
    g = torch.Generator().manual_seed(seed)
    E = num_observations
    m = NUM_POSES
    n = max(3, int(E * POINTS_PER_OBSERVATION))
    xi = torch.randn(1, m, 6, generator=g, dtype=torch.float64)
    xi[..., :3] *= 3.0 / xi[..., :3].norm(dim=-1, keepdim=True).clamp_min(1.0)  # |ω| ≤ 3 < π
    points = 5 * torch.randn(1, n, 3, generator=g, dtype=torch.float64)
    # Every pose and every point observed (a permutation first), the rest random.
    pose_index = torch.randint(0, m, (1, E), generator=g)
    point_index = torch.randint(0, n, (1, E), generator=g)
    pose_index[0, :m] = torch.arange(m)
    point_index[0, :n] = torch.randperm(n, generator=g)
    observations = torch.randn(1, E, 3, generator=g, dtype=torch.float64)
    with torchslam.validation(False):  # skip the value checks: this times the Jacobians only
        return PointMapProblem(se3.exp(xi), points, pose_index, point_index, observations)


def _inputs(num_observations: int, seed: int, threads: int):
    torch.set_num_threads(threads)
    problem = _problem(num_observations, seed)
    data = problem.data
    data.flat_pose_index, data.flat_point_index  # noqa: B018 (cached gathers, built once)
    # Warm-up on a small problem (kernels, vmap/jacrev tracing caches, lazy imports).
    small = _problem(1000, seed + 1)
    for mode in MODES:
        data_module.jacobian_blocks(
            small.pose_tangent.detach(), small.points.detach(), small.data, mode
        )
    gc.collect()
    return problem.pose_tangent.detach(), problem.points.detach(), data


def _memory_worker(num_observations: int, mode: str, threads: int, seed: int) -> dict:
    """Extra resident memory of the first full-size call of ``mode`` in this fresh process."""
    pose_tangent, points, data = _inputs(num_observations, seed, threads)
    with PeakMemory() as peak:
        start = time.perf_counter()
        J_xi, J_point = data_module.jacobian_blocks(pose_tangent, points, data, mode)
        first_seconds = time.perf_counter() - start
    assert J_xi.shape == (1, num_observations, 3, 6) and J_point.shape[-2:] == (3, 3)
    return {
        "observations": num_observations,
        "mode": mode,
        "peak_extra_mib": peak.extra_mib,
        "output_mib": num_observations * BYTES_PER_OBSERVATION / 2**20,
        "first_call_seconds": first_seconds,
        "memory_method": peak.method,
    }


def _timing_worker(num_observations: int, runs: int, threads: int, seed: int) -> dict:
    """Paired timing: analytic and jacrev alternate, so both see the same machine load."""
    pose_tangent, points, data = _inputs(num_observations, seed, threads)
    times: dict[str, list[float]] = {mode: [] for mode in MODES}
    for mode in MODES:  # one untimed call at full size each
        data_module.jacobian_blocks(pose_tangent, points, data, mode)
    for _ in range(runs):
        for mode in MODES:
            start = time.perf_counter()
            data_module.jacobian_blocks(pose_tangent, points, data, mode)
            times[mode].append(time.perf_counter() - start)
    ratios = [j / a for a, j in zip(times["analytic"], times["jacrev"], strict=True)]
    out: dict = {"observations": num_observations, "runs": runs}
    for mode in MODES:
        out[mode] = {
            "median_seconds": statistics.median(times[mode]),
            "min_seconds": min(times[mode]),
            "max_seconds": max(times[mode]),
        }
    out["speedup_median_of_paired_ratios"] = statistics.median(ratios)
    return out


# --------------------------------------------------------------------------- driver


def _run_worker(args: argparse.Namespace, *worker: str) -> dict:
    """Run ``--worker *worker`` in a fresh Python process and return its JSON line."""
    command = [sys.executable, str(Path(__file__).resolve()), "--worker", *worker]
    command += ["--threads", str(args.threads), "--seed", str(args.seed)]
    env = dict(os.environ, OMP_NUM_THREADS=str(args.threads))
    done = subprocess.run(command, capture_output=True, text=True, env=env, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"worker {worker} failed:\n{done.stderr}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _runs_for(E: int, runs: int) -> int:
    """Small sizes are cheap and the most load-sensitive: five times as many runs."""
    return 5 * runs if E <= 10_000 else runs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="E = 1e4, 1e5 only, 3 runs")
    parser.add_argument("--runs", type=int, default=None, help="paired timed runs (default 7)")
    parser.add_argument("--threads", type=int, default=2, help="torch.set_num_threads")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=Path("out/bench_jacobians.json"))
    parser.add_argument("--worker", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.runs is None:
        args.runs = 3 if args.quick else 7

    if args.worker is not None:  # ["memory", E, mode] or ["timing", E, runs]
        kind, E = args.worker[0], int(args.worker[1])
        if kind == "memory":
            row = _memory_worker(E, args.worker[2], args.threads, args.seed)
        else:
            row = _timing_worker(E, int(args.worker[2]), args.threads, args.seed)
        print(json.dumps(row))
        return

    sizes = (10_000, 100_000) if args.quick else (10_000, 100_000, 1_000_000)
    memory, timing = {}, {}
    for E in sizes:
        for mode in MODES:
            print(f"  E = {E:>9,}  memory of {mode:<8} …", end="", flush=True)
            memory[E, mode] = _run_worker(args, "memory", str(E), mode)
            print(f" +{memory[E, mode]['peak_extra_mib']:.1f} MiB")
        runs = _runs_for(E, args.runs)
        print(f"  E = {E:>9,}  {runs} paired timing runs …", end="", flush=True)
        timing[E] = _run_worker(args, "timing", str(E), str(runs))
        print(f" speed-up {timing[E]['speedup_median_of_paired_ratios']:.1f}x")
    load = os.getloadavg() if hasattr(os, "getloadavg") else None

    print()
    print(
        f"Jacobian blocks of PointMapProblem (m = {NUM_POSES}, n = E/10), float64, CPU, "
        f"{args.threads} threads. Times: median (min) of paired runs, analytic and jacrev "
        "alternating; speed-up: median of the per-pair ratios. Memory: extra resident memory "
        "of the first full-size call, one fresh process per entry."
    )
    header = (
        f"{'E':>10} {'runs':>5} {'analytic ms':>19} {'jacrev ms':>21} {'speed-up':>9} "
        f"{'analytic MiB':>13} {'jacrev MiB':>11} {'mem ratio':>10} {'output MiB':>11}"
    )
    print(header)
    print("-" * len(header))
    summary = []
    for E in sizes:
        t = timing[E]
        a, j = t["analytic"], t["jacrev"]
        speedup = t["speedup_median_of_paired_ratios"]
        mem_a = memory[E, "analytic"]["peak_extra_mib"]
        mem_j = memory[E, "jacrev"]["peak_extra_mib"]
        mem_ratio = mem_j / mem_a if mem_a > 0 else None
        output_mib = memory[E, "analytic"]["output_mib"]
        summary.append(
            {
                "observations": E,
                "runs": t["runs"],
                "analytic_median_ms": a["median_seconds"] * 1e3,
                "analytic_min_ms": a["min_seconds"] * 1e3,
                "jacrev_median_ms": j["median_seconds"] * 1e3,
                "jacrev_min_ms": j["min_seconds"] * 1e3,
                "speedup": speedup,
                "analytic_peak_extra_mib": mem_a,
                "jacrev_peak_extra_mib": mem_j,
                "memory_ratio": mem_ratio,
                "output_mib": output_mib,
            }
        )
        a_cell = f"{a['median_seconds'] * 1e3:.2f} ({a['min_seconds'] * 1e3:.2f})"
        j_cell = f"{j['median_seconds'] * 1e3:.1f} ({j['min_seconds'] * 1e3:.1f})"
        ratio_cell = f"{mem_ratio:.1f}x" if mem_ratio is not None else "-"
        print(
            f"{E:>10,} {t['runs']:>5} {a_cell:>19} {j_cell:>21} {speedup:>8.1f}x "
            f"{mem_a:>13.1f} {mem_j:>11.1f} {ratio_cell:>10} {output_mib:>11.1f}"
        )
    method = memory[sizes[0], "analytic"]["memory_method"]
    print(f"\nmemory measured by: {method}")
    if load is not None:
        print(f"load average at the end (1, 5, 15 min): {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")

    output = {
        "description": "analytic vs jacrev Jacobian blocks, torchslam.problem.jacobian_blocks",
        "dtype": "float64",
        "device": "cpu",
        "threads": args.threads,
        "runs": args.runs,
        "num_poses": NUM_POSES,
        "points_per_observation": POINTS_PER_OBSERVATION,
        "memory_method": method,
        "torch": torch.__version__,
        "torchslam": torchslam.__version__,
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "load_average": load,
        "summary": summary,
        "timing": [timing[E] for E in sizes],
        "memory": [memory[E, mode] for E in sizes for mode in MODES],
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(output, indent=2) + "\n")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
