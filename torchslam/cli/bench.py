"""``torchslam bench``: the solver benchmark (cases S, M, L, O, BATCH) with a table and a figure.

    torchslam bench [--cases S M L O BATCH TRAIN] [--repeats N] [--quick] [--out DIR]
                    [--threads N | --thread-counts N [N ...]]
    (or .venv/bin/python experiments/bench_solver.py with the same options)

The measurements are those of :mod:`torchslam.benchmark` (float64, torch threads as
``--threads`` says, 1 by default: :mod:`torchslam.cli`'s policy). ``--thread-counts 1 2``
measures every case under each count, interleaved within each repeat
(:func:`torchslam.benchmark.run_case_threads`), and prints each count's time with the median
of its paired ratios to the first count's ("vs first": below 1 is faster). Printed: one line
per case (and count) and a summary table; written:
out/bench_solver.json and out/bench_solver.png (the figure needs matplotlib).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path

import torch

from torchslam.benchmark import (
    REPEATS,
    TARGETS_S,
    matmul_rate,
    peak_memory_subprocess,
    run_case_threads,
)
from torchslam.cli import _stderr, add_threads_argument, int_range, plots, using_threads

__all__ = ["add_arguments", "main", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``torchslam bench``."""
    parser.add_argument(
        "--cases",
        nargs="+",
        default=["S", "M", "L", "O", "BATCH", "TRAIN"],
        choices=list(REPEATS),
        metavar="CASE",
        help="which cases (all): S, M, L (one problem of 10, 50, 200 poses), O (M with 10%% "
        "outliers, Huber), BATCH (64 S problems at once), TRAIN (BATCH's forward solve plus the "
        "implicit backward to the observations)",
    )
    parser.add_argument(
        "--repeats",
        type=int_range(1, 1000),
        default=None,
        help="runs per case, median [1, 1000] (default per case: "
        + ", ".join(f"{k} {v}" for k, v in REPEATS.items())
        + ")",
    )
    parser.add_argument("--quick", action="store_true", help="2 repeats, no scipy, no memory")
    parser.add_argument(
        "--no-scipy",
        action="store_true",
        help="do not run scipy.optimize.least_squares beside each case (it is the slow part)",
    )
    add_threads_argument(parser)
    parser.add_argument(
        "--thread-counts",
        type=int_range(1, 1024),
        nargs="+",
        default=None,
        metavar="N",
        help="measure under each of these torch thread counts, interleaved (overrides --threads)",
    )
    parser.add_argument("--out", type=Path, default=Path("out"), help="output folder")


def run(
    args: argparse.Namespace,
    echo: Callable[[str], None] = print,
    warn: Callable[[str], None] = _stderr,
) -> list[dict]:
    """Run the benchmark; print progress and a table; write JSON (and PNG) to ``args.out``.

    The figure needs matplotlib; without it one line ``figure skipped: …`` goes to ``warn``.
    """
    if args.repeats is not None and args.repeats < 1:
        raise ValueError(f"--repeats must be ≥ 1, got {args.repeats}")
    with using_threads(args.threads):
        return _run(args, echo, warn)


def _run(
    args: argparse.Namespace, echo: Callable[[str], None], warn: Callable[[str], None]
) -> list[dict]:
    out_dir = args.out
    out_dir.mkdir(parents=True, exist_ok=True)
    counts = list(dict.fromkeys(getattr(args, "thread_counts", None) or [args.threads]))
    rates = {}
    for threads in counts:
        torch.set_num_threads(threads)
        rates[threads] = matmul_rate()
    torch.set_num_threads(counts[0])
    echo(
        f"torch {torch.__version__}, threads {', '.join(map(str, counts))}, float64 matmul rate "
        + ", ".join(f"{rates[t] / 1e9:.1f}" for t in counts)
        + " GFLOP/s"
    )
    rows = []
    for index, case in enumerate(args.cases):
        echo(f"[{index + 1}/{len(args.cases)}] case {case} …")
        repeats = 2 if args.quick else (args.repeats or REPEATS[case])
        with_scipy = not (args.quick or args.no_scipy)
        case_rows = run_case_threads(case, repeats, rates, with_scipy)
        if case == "L" and not args.quick:
            memory = peak_memory_subprocess("L")
            for row in case_rows:
                row["peak_memory_gib"] = memory
        for row in case_rows:
            rows.append(row)
            echo(_format_row(row, len(counts) > 1))

    echo("")
    several = len(counts) > 1
    echo(
        f"{'case':6} {'threads':>7} {'time':>9} {'target':>8} {'iters':>5} {'ms/iter':>8} "
        f"{'FLOP ratio':>10} {'rot err °':>10} {'scipy':>8} {'speed-up':>8}"
        + (f" {'vs first':>8}" if several else "")
    )
    for r in rows:
        target = TARGETS_S.get(r["case"])
        target_text = f"{target * 1e3:.0f}ms" if target else "-"
        scipy_text = f"{r['scipy_s']:.3f}s" if "scipy_s" in r else "-"
        speedup_text = f"{r['speedup_vs_scipy']:.1f}×" if "speedup_vs_scipy" in r else "-"
        echo(
            f"{r['case']:6} {r['threads']:7d} {r['median_s'] * 1e3:7.1f}ms {target_text:>8} "
            f"{r['iterations']:5d} {r['per_iteration_s'] * 1e3:8.2f} {r['flop_ratio']:10.1f} "
            f"{r['rotation_error_deg']:10.5f} {scipy_text:>8} {speedup_text:>8}"
            + (f" {r['paired_ratio']:8.3f}" if several else "")
        )
    json_path, png_path = out_dir / "bench_solver.json", out_dir / "bench_solver.png"
    json_path.write_text(
        json.dumps({"matmul_rate": rates, "threads": counts, "cases": rows}, indent=2)
    )
    written = [json_path]
    try:
        plots.plot_bench([r for r in rows if r["threads"] == counts[0]], png_path)
    except plots.MatplotlibMissingError as error:
        warn(f"figure skipped: {error}")
    else:
        written.append(png_path)
    echo(f"\nwrote {' and '.join(map(str, written))}")
    return rows


def main(argv: list[str] | None = None) -> int:
    """``python experiments/bench_solver.py``: the same as ``torchslam bench``."""
    from torchslam import cli

    return cli.main(["bench", *(sys.argv[1:] if argv is None else argv)])


def _format_row(r: dict, with_threads: bool = False) -> str:
    extra = ""
    if "scipy_s" in r:
        extra = (
            f"; scipy {r['scipy_s']:.3f} s (cost {r['scipy_final_cost']:.6g}, "
            f"{r['scipy_runs']} runs), speed-up {r['speedup_vs_scipy']:.1f}× (median of the "
            f"paired ratios; {r['speedup_vs_scipy_of_medians']:.1f}× the ratio of the medians)"
        )
    if "peak_memory_gib" in r:
        extra += f"; peak memory {r['peak_memory_gib']:.2f} GiB"
    if with_threads:
        extra += f"; {r['paired_ratio']:.3f}× the first thread count's time (paired median)"
    threads = f" [{r['threads']} threads]" if with_threads else ""
    return (
        f"{r['case']}{threads}: B={r['B']} m={r['m']} n={r['n']} E={r['observations']}: "
        f"{r['median_s'] * 1e3:.1f} ms median, {r['iterations']} iterations, "
        f"{r['per_iteration_s'] * 1e3:.2f} ms/iteration (FLOP model {r['flop_time_s'] * 1e3:.2f}"
        f" ms → ratio {r['flop_ratio']:.1f}), cost {r['final_cost']:.6g}, rotation error "
        f"{r['initial_rotation_error_deg']:.3f}° → {r['rotation_error_deg']:.5f}° "
        f"(max {r['max_rotation_error_deg']:.5f}°), status {','.join(r['status'])}{extra}"
    )


if __name__ == "__main__":
    sys.exit(main())
