"""Bundle adjustment against native Ceres: a real BAL file and synthetic scenes of growing size.

Part 1, the table of issue 27: the Ladybug file ``problem-21-11315-pre.txt`` (21 cameras,
11,315 points, 36,455 observations; fetched by ``torchslam.data.files.fetch("bal-ladybug-21")``)
with the full BAL problem (poses, intrinsics (f, k1, k2) and points free), solved by torchslam
(:func:`torchslam.bundle_adjustment.problem_from_bal`, :data:`~torchslam.bundle_adjustment.
BA_CONFIG`) and by a native Ceres build (``experiments/ceres/bal_ceres.cc``: autodiff Snavely
residuals, DENSE_SCHUR, Levenberg-Marquardt, the same tolerances), each in its own process
(solve time without reading, max RSS of the process), interleaved, at 1 and 2 threads; medians
of ``--repeats`` runs.

Part 2: synthetic BAL scenes (:func:`torchslam.data.bal_scene.make_bal_scene`, 4 views per
point) from 10 cameras / 1k points to 200 cameras / 100k points: time per iteration against
the number of observations, both solvers, and a log–log figure ``OUT/ba_scaling.png``.

Ceres is optional: the driver is compiled into ``OUT`` when ``g++`` and Debian's
``libceres-dev`` are present (``apt-get install libceres-dev``), else its columns say "n/a".

Run on a quiet machine: ``python experiments/ba_bench.py [--repeats 3] [--out out/ba]``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
SIZES = [(10, 1000), (20, 5000), (50, 10000), (100, 30000), (200, 100000)]


def _child(path: str, threads: int) -> None:
    """Solve one BAL file in this process and print one JSON line (the torchslam side)."""
    import resource
    import time

    import torch

    torch.set_num_threads(threads)
    import torchslam
    from torchslam.bundle_adjustment import BA_CONFIG, problem_from_bal
    from torchslam.io.bal import read_bal

    bal = read_bal(path)
    problem = problem_from_bal(bal)
    start = time.perf_counter()
    result = torchslam.solve(problem, BA_CONFIG)
    seconds = time.perf_counter() - start
    print(
        json.dumps(
            {
                "initial_cost": float(result.initial_cost[0]),
                "final_cost": float(result.final_cost[0]),
                "iterations": int(result.iterations[0]),
                # one factorization and solve per iteration; a linearization at the start and
                # at every evaluated candidate
                "linear_solves": int(result.iterations[0]),
                "jacobian_evaluations": int(result.linearizations[0]),
                "seconds": seconds,
                "status": result.status[0].name,
                "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            }
        )
    )


def _run(command: list[str]) -> dict:
    """Run a child; its JSON line, with its own max RSS (os.wait4) when it does not say."""
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(process.pid, 0)
    out = process.stdout.read().decode()
    err = process.stderr.read().decode()
    process.returncode = os.waitstatus_to_exitcode(status)
    lines = [line for line in out.splitlines() if line.startswith("{")]
    if not lines:
        raise RuntimeError(f"{command[0]} failed ({process.returncode}): {err[-2000:]}")
    record = json.loads(lines[-1])
    record.setdefault("max_rss_mb", usage.ru_maxrss / 1024)
    return record


def _solves(record: dict) -> str:
    """'linear solves/Jacobian evaluations' of a record (n/a where the solver did not say)."""
    solves, jacobians = record.get("linear_solves"), record.get("jacobian_evaluations")
    if solves is None or solves != solves:  # missing or NaN
        return "n/a"
    return f"{solves:.0f}/{jacobians:.0f}"


def build_ceres(out: Path) -> Path | None:
    """The Ceres driver compiled into ``out`` (None when g++ or Ceres is missing)."""
    if shutil.which("g++") is None or not Path("/usr/include/ceres/ceres.h").exists():
        return None
    binary = out / "bal_ceres"
    source = HERE / "ceres" / "bal_ceres.cc"
    if not binary.exists() or binary.stat().st_mtime < source.stat().st_mtime:
        subprocess.run(
            ["g++", "-O2", "-std=c++17", str(source), "-I/usr/include/eigen3", "-lceres",
             "-lglog", "-o", str(binary)],
            check=True,
        )  # fmt: skip
    return binary


def compare(path: Path, ceres: Path | None, threads: int, repeats: int) -> dict:
    """Medians of ``repeats`` interleaved runs of both solvers on ``path``."""
    ours, theirs = [], []
    for _ in range(repeats):
        ours.append(_run([sys.executable, __file__, "--child", str(path), str(threads)]))
        if ceres is not None:
            theirs.append(_run([str(ceres), str(path), "--threads", str(threads)]))

    def median(runs: list[dict], key: str) -> float:
        return statistics.median(r[key] for r in runs) if runs else float("nan")

    keys = ("seconds", "max_rss_mb", "iterations", "linear_solves", "jacobian_evaluations")
    row = {
        "threads": threads,
        "torchslam": {k: median(ours, k) for k in keys},
        "ceres": {k: median(theirs, k) for k in keys},
    }
    row["torchslam"]["final_cost"] = ours[0]["final_cost"]
    row["torchslam"]["status"] = ours[0]["status"]
    row["ceres"]["final_cost"] = theirs[0]["final_cost"] if theirs else float("nan")
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3, help="runs per figure (3)")
    parser.add_argument("--out", type=Path, default=Path("out/ba"), help="output folder")
    parser.add_argument("--no-scaling", action="store_true", help="skip part 2")
    parser.add_argument(
        "--sizes", default=None, help="part 2's scenes as C:N,C:N,… (default 10:1000 … 200:100000)"
    )
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    from torchslam.data.files import fetch

    ceres = build_ceres(args.out)
    if ceres is None:
        print("Ceres: not found (apt-get install libceres-dev); its columns are n/a")
    path = fetch("bal-ladybug-21") / "problem-21-11315-pre.txt"
    print(f"\n{path.name}: full BAL (poses, f, k1, k2, points free); medians of {args.repeats}")
    print("(it: iterations as each solver counts them; sol/jac: linear solves and Jacobian "
          "evaluations)")  # fmt: skip
    print(
        f"{'threads':>7} | {'torchslam s':>11} {'it':>3} {'sol/jac':>7} {'final ½Σr²':>14} "
        f"{'RSS MB':>7} | {'Ceres s':>8} {'it':>3} {'sol/jac':>7} {'final ½Σr²':>14} "
        f"{'RSS MB':>7} | {'time':>6} {'RSS':>5}"
    )
    rows = []
    for threads in (1, 2):
        row = compare(path, ceres, threads, args.repeats)
        rows.append(row)
        t, c = row["torchslam"], row["ceres"]
        print(
            f"{threads:>7} | {t['seconds']:>11.3f} {t['iterations']:>3.0f} {_solves(t):>7} "
            f"{t['final_cost']:>14.7e} {t['max_rss_mb']:>7.0f} | {c['seconds']:>8.3f} "
            f"{c['iterations']:>3.0f} {_solves(c):>7} {c['final_cost']:>14.7e} "
            f"{c['max_rss_mb']:>7.0f} | {t['seconds'] / c['seconds']:>5.2f}× "
            f"{t['max_rss_mb'] / c['max_rss_mb']:>4.1f}×"
        )
    (args.out / "ba_ladybug.json").write_text(json.dumps(rows, indent=1))
    if args.no_scaling:
        return 0
    sizes = SIZES
    if args.sizes:
        sizes = [tuple(int(v) for v in item.split(":")) for item in args.sizes.split(",")]
    from torchslam.data.bal_scene import make_bal_scene
    from torchslam.io.bal import write_bal

    print("\nSynthetic scenes (4 views per point), 1 thread: seconds per linear solve (an "
          "iteration: a solve, a cost and, once accepted, a linearization)")  # fmt: skip
    print(f"{'cameras':>7} {'points':>7} {'obs':>7} | {'torchslam':>9} {'sol':>3} | "
          f"{'Ceres':>9} {'sol':>3} | {'ratio':>5}")  # fmt: skip
    scaling = []
    for C, N in sizes:
        file = args.out / f"synthetic-{C}-{N}.txt"
        if not file.exists():
            write_bal(file, make_bal_scene(C, N, views=4, seed=C).problem)
        row = compare(file, ceres, 1, max(1, args.repeats // 2))
        t, c = row["torchslam"], row["ceres"]
        per_t = t["seconds"] / max(t["linear_solves"], 1)
        per_c = c["seconds"] / max(c["linear_solves"], 1)
        scaling.append({"cameras": C, "points": N, "observations": 4 * N,
                        "torchslam": per_t, "ceres": per_c})  # fmt: skip
        print(f"{C:>7} {N:>7} {4 * N:>7} | {per_t:>9.4f} {t['linear_solves']:>3.0f} | "
              f"{per_c:>9.4f} {c['linear_solves']:>3.0f} | {per_t / per_c:>4.2f}×")  # fmt: skip
    (args.out / "ba_scaling.json").write_text(json.dumps(scaling, indent=1))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("figure skipped: matplotlib is missing")
        return 0
    fig, ax = plt.subplots(figsize=(5, 4))
    obs = [s["observations"] for s in scaling]
    ax.loglog(obs, [s["torchslam"] for s in scaling], "o-", label="torchslam")
    if ceres is not None:
        ax.loglog(obs, [s["ceres"] for s in scaling], "s-", label="Ceres (DENSE_SCHUR)")
    ax.loglog(obs, [scaling[0]["torchslam"] * o / obs[0] for o in obs], "k:", label="linear")
    ax.set_xlabel("observations")
    ax.set_ylabel("seconds per linear solve (1 thread)")
    ax.set_title("Bundle adjustment, synthetic BAL scenes")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "ba_scaling.png", dpi=120)
    print(f"wrote {args.out / 'ba_scaling.png'}")
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--child":
        _child(sys.argv[2], int(sys.argv[3]))
    else:
        raise SystemExit(main())
