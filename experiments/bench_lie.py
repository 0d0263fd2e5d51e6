"""Throughput of torchslam.lie on 1,000,000 poses, next to pytorch-kinematics' SO(3) maps.

Times batched so3.exp, so3.log, se3.exp, se3.log and se3.act (one point per pose) in float64,
median over several runs after a warm-up, and pytorch-kinematics' so3_exp_map / so3_log_map
(and Transform3d.transform_points for act) on the same inputs. Also reports the max round-trip
error |log(exp(ω)) − ω| of both libraries, over the benchmark inputs and over a band of angles
just below π (where pytorch-kinematics' so3_log_map fails, issue 2).

Run: .venv/bin/python experiments/bench_lie.py   (writes out/bench_lie.json)
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import math
import os
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch
from pytorch_kinematics import transforms as pk

import torchslam
from torchslam.lie import se3, so3


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _median_seconds(fn: Callable[[], object], runs: int, device: torch.device) -> float:
    fn()  # warm-up (allocator, kernels)
    _sync(device)
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _inputs(n: int, device: torch.device, seed: int) -> dict[str, torch.Tensor]:
    """Random rotation vectors (angles uniform in [0, π)), twists, poses and points."""
    g = torch.Generator().manual_seed(seed)
    axes = torch.randn(n, 3, generator=g, dtype=torch.float64)
    axes = axes / axes.norm(dim=-1, keepdim=True)
    angles = torch.rand(n, 1, generator=g, dtype=torch.float64) * math.pi
    omega = axes * angles
    xi = torch.cat((omega, torch.randn(n, 3, generator=g, dtype=torch.float64)), dim=-1)
    points = torch.randn(n, 3, generator=g, dtype=torch.float64)
    out = {"omega": omega, "xi": xi, "points": points}
    out = {k: v.to(device) for k, v in out.items()}
    out["R"] = so3.exp(out["omega"])
    out["T"] = se3.exp(out["xi"])
    return out


def _near_pi_errors(device: torch.device, seed: int) -> dict[str, float]:
    """Max |log(exp(ω)) − ω| for θ ∈ π − [1e-9, 1e-2] (log-spaced), ours and pk's."""
    g = torch.Generator().manual_seed(seed + 1)
    count = 10_000
    axes = torch.randn(count, 3, generator=g, dtype=torch.float64)
    axes = axes / axes.norm(dim=-1, keepdim=True)
    angles = math.pi - torch.logspace(-9, -2, count, dtype=torch.float64)
    omega = (axes * angles[:, None]).to(device)
    R = so3.exp(omega)
    return {
        "torchslam": float((so3.log(R) - omega).abs().max()),
        "pytorch_kinematics": float((pk.so3_log_map(pk.so3_exp_map(omega)) - omega).abs().max()),
        "pytorch_kinematics_log_of_our_exp": float((pk.so3_log_map(R) - omega).abs().max()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=1_000_000, help="poses per batch")
    parser.add_argument("--runs", type=int, default=5, help="timed runs per operation")
    parser.add_argument("--threads", type=int, default=2, help="torch.set_num_threads")
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=Path("out/bench_lie.json"))
    args = parser.parse_args()

    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    n, runs = args.count, args.runs
    x = _inputs(n, device, args.seed)
    omega, xi, R, T, points = x["omega"], x["xi"], x["R"], x["T"], x["points"]
    t3d = pk.Transform3d(matrix=T)

    # (name, torchslam callable, pytorch-kinematics callable or None)
    cases: list[tuple[str, Callable[[], object], Callable[[], object] | None]] = [
        ("so3.exp", lambda: so3.exp(omega), lambda: pk.so3_exp_map(omega)),
        ("so3.log", lambda: so3.log(R), lambda: pk.so3_log_map(R)),
        ("se3.exp", lambda: se3.exp(xi), None),
        ("se3.log", lambda: se3.log(T), None),
        (
            "se3.act",
            lambda: se3.act(T, points),
            lambda: t3d.transform_points(points[:, None, :]),
        ),
    ]
    rows = []
    for name, ours, theirs in cases:
        seconds = _median_seconds(ours, runs, device)
        with torchslam.validation(False):
            seconds_unchecked = _median_seconds(ours, runs, device)
        seconds_pk = _median_seconds(theirs, runs, device) if theirs is not None else None
        rows.append(
            {
                "op": name,
                "seconds": seconds,
                "mops": n / seconds / 1e6,
                "seconds_validation_off": seconds_unchecked,
                "mops_validation_off": n / seconds_unchecked / 1e6,
                "pk_seconds": seconds_pk,
                "pk_mops": None if seconds_pk is None else n / seconds_pk / 1e6,
            }
        )

    # Round trip over the benchmark inputs, split at θ = π − 0.1 (pk is accurate below it).
    err_ours = (so3.log(R) - omega).abs().amax(-1)
    err_pk = (pk.so3_log_map(pk.so3_exp_map(omega)) - omega).abs().amax(-1)
    away = omega.norm(dim=-1) < math.pi - 0.1
    errors_all = {
        "torchslam": float(err_ours.max()),
        "pytorch_kinematics": float(err_pk.max()),
        "torchslam_below_pi_minus_0.1": float(err_ours[away].max()),
        "pytorch_kinematics_below_pi_minus_0.1": float(err_pk[away].max()),
    }
    errors_near_pi = _near_pi_errors(device, args.seed)
    load = os.getloadavg() if hasattr(os, "getloadavg") else None

    pk_names = {"so3.exp": "so3_exp_map", "so3.log": "so3_log_map", "se3.act": "transform_points"}
    print(
        f"torchslam.lie throughput, {n:,} poses, float64, {device}, {args.threads} threads, "
        f"median of {runs} runs (million ops/s)"
    )
    header = f"{'op':<9} {'torchslam':>10} {'valid. off':>10} {'pytorch-kinematics':>28}"
    print(header)
    print("-" * len(header))
    for r in rows:
        pk_cell = f"{r['pk_mops']:.2f} ({pk_names[r['op']]})" if r["pk_mops"] else "-"
        print(f"{r['op']:<9} {r['mops']:>10.2f} {r['mops_validation_off']:>10.2f} {pk_cell:>28}")
    print()
    print("max |log(exp(ω)) − ω|       torchslam   pytorch-kinematics")
    print(
        f"  θ uniform in [0, π − 0.1) {errors_all['torchslam_below_pi_minus_0.1']:>9.2e}   "
        f"{errors_all['pytorch_kinematics_below_pi_minus_0.1']:>10.2e}"
    )
    print(
        f"  θ uniform in [0, π)      {errors_all['torchslam']:>10.2e}   "
        f"{errors_all['pytorch_kinematics']:>10.2e}"
    )
    print(
        f"  θ ∈ π − [1e-9, 1e-2]     {errors_near_pi['torchslam']:>10.2e}   "
        f"{errors_near_pi['pytorch_kinematics']:>10.2e}"
    )
    if load is not None:
        print(
            f"\nload average at the end (1, 5, 15 min): {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}"
        )

    result = {
        "count": n,
        "runs": runs,
        "dtype": "float64",
        "device": str(device),
        "threads": args.threads,
        "torch": torch.__version__,
        "pytorch_kinematics": importlib.metadata.version("pytorch_kinematics"),
        "torchslam": torchslam.__version__,
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "load_average": load,
        "results": rows,
        "round_trip_max_error": {"uniform_angles": errors_all, "near_pi": errors_near_pi},
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
