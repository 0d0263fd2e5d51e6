"""``torchslam ba``: bundle adjustment of a BAL file (Bundle Adjustment in the Large).

Reads FILE (:func:`torchslam.io.read_bal`; ``.bz2`` too), builds the problem of
:func:`torchslam.bundle_adjustment.problem_from_bal` (each camera a pose plus an intrinsics
block (f, k1, k2), free unless ``--fixed-intrinsics``; nothing held fixed, as Ceres on BAL),
solves it with the library's defaults for bundle adjustment
(:data:`torchslam.bundle_adjustment.BA_CONFIG`: Levenberg-Marquardt, points eliminated by the
Schur complement, Ceres' tolerances), printing one line per iteration like Ceres (off under
``--quiet``) and a summary: initial and final cost ½Σr², iterations, status, time per phase.
``--out OUT.txt`` writes the optimized problem in BAL format (the same observations, the
cameras and points updated). Exit status as :mod:`torchslam.cli`.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

from torchslam.cli import _stderr, add_threads_argument, int_range, using_threads

__all__ = ["add_arguments", "main", "parse_loss", "run"]

_LOSSES = ("huber", "cauchy", "tukey")


def parse_loss(text: str):
    """``--loss``: ``none`` or ``NAME:SCALE`` (huber, cauchy, tukey; SCALE in pixels) →
    a kernel of :mod:`torchslam.losses` (None for none)."""
    from torchslam import losses

    if text == "none":
        return None
    name, _, scale = text.partition(":")
    try:
        value = float(scale)
    except ValueError:
        value = float("nan")
    if name not in _LOSSES or not (value > 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(
            f"expected 'none' or NAME:SCALE with NAME one of {', '.join(_LOSSES)} and SCALE a "
            f"positive number of pixels (e.g. huber:1), got {text!r}"
        )
    kernel = {"huber": losses.HuberLoss, "cauchy": losses.CauchyLoss, "tukey": losses.TukeyLoss}
    return kernel[name](value)


parse_loss.__name__ = "loss"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``torchslam ba``."""
    parser.add_argument("file", type=Path, help="a BAL problem file (.txt or .txt.bz2)")
    parser.add_argument(
        "--loss",
        type=parse_loss,
        default=None,
        help="robust kernel on each observation's squared reprojection error: none (default) "
        "or huber:S, cauchy:S, tukey:S with S in pixels",
    )
    parser.add_argument(
        "--fixed-intrinsics",
        action="store_true",
        help="hold every camera's (f, k1, k2) at the file's values (default: optimize them)",
    )
    parser.add_argument(
        "--max-iterations",
        type=int_range(1, 100000),
        default=50,
        help="Levenberg-Marquardt iterations at most (50, as Ceres)",
    )
    parser.add_argument(
        "--out", type=Path, default=None, help="write the optimized problem here, BAL format"
    )
    add_threads_argument(parser)


def run(
    args: argparse.Namespace,
    echo: Callable[[str], None] = print,
    warn: Callable[[str], None] = _stderr,
):
    """Run ``torchslam ba`` (module docstring); returns the :class:`torchslam.SolveResult`.

    Raises:
        ValueError: a malformed file (naming it and the line). OSError: unreadable or
            unwritable files.
    """
    import dataclasses

    from torchslam.bundle_adjustment import BA_CONFIG, bal_from_problem, problem_from_bal
    from torchslam.io.bal import read_bal, write_bal
    from torchslam.solver import solve

    if args.out is not None and args.out.is_dir():
        raise ValueError(f"--out {args.out} is a directory; give a file name (e.g. out.txt)")
    with using_threads(args.threads):
        tick = time.perf_counter()
        bal = read_bal(args.file)
        reading = time.perf_counter() - tick
        C, P, n_obs = bal.cameras.shape[0], bal.points.shape[0], bal.observations.shape[0]
        intrinsics = "fixed" if args.fixed_intrinsics else "free"
        loss = "" if args.loss is None else f"; loss {args.loss!r}"
        echo(
            f"{args.file}: {C} cameras, {P} points, {n_obs} observations; intrinsics (f, k1, k2) "
            f"{intrinsics}{loss}"
        )
        tick = time.perf_counter()
        problem = problem_from_bal(bal, intrinsics=intrinsics, loss=args.loss)
        building = time.perf_counter() - tick
        config = dataclasses.replace(BA_CONFIG, max_iterations=args.max_iterations)
        echo(f"{'iter':>4} {'cost':>14} {'cost_change':>12} {'|gradient|':>10} "
             f"{'|step|':>10} {'lambda':>9} {'accepted':>8} {'time':>8}")  # fmt: skip
        last = [float(problem.cost().detach()[0])]
        echo(f"{0:>4} {last[0]:>14.6e} {0.0:>12.2e} {'':>10} {'':>10} {'':>9} {'':>8} "
             f"{0.0:>7.2f}s")  # fmt: skip

        def on_iteration(info) -> None:
            cost = float(info.cost[0])
            echo(
                f"{info.iteration:>4} {cost:>14.6e} {last[0] - cost:>12.2e} "
                f"{float(info.gradient_norm[0]):>10.2e} {float(info.step_norm[0]):>10.2e} "
                f"{float(info.damping[0]):>9.2e} {bool(info.accepted[0])!s:>8} "
                f"{info.seconds:>7.2f}s"
            )
            last[0] = cost

        result = solve(problem, config, callback=on_iteration)
        status = result.status[0]
        other = result.time_seconds - result.linearize_seconds - result.linear_solve_seconds
        echo("")
        echo("Solver summary (½ Σ ‖r‖², pixels²)")
        echo(f"  initial cost   {float(result.initial_cost[0]):.7e}")
        echo(f"  final cost     {float(result.final_cost[0]):.7e}")
        echo(
            f"  iterations     {int(result.iterations[0])} (linear solves; Jacobian "
            f"evaluations {int(result.linearizations[0])})"
        )
        echo(f"  status         {status.name}: {result.reason[0]}")
        echo(
            f"  time           {result.time_seconds:.3f} s solving (linearize "
            f"{result.linearize_seconds:.3f} s, linear solves {result.linear_solve_seconds:.3f} "
            f"s, other {other:.3f} s); reading {reading:.3f} s, building {building:.3f} s"
        )
        if args.out is not None:
            write_bal(args.out, bal_from_problem(problem, bal))
            echo(f"wrote {args.out}")
    return result


def main(argv: list[str] | None = None) -> int:
    """``python -m torchslam.cli.ba``: the same as ``torchslam ba``."""
    from torchslam import cli

    return cli.main(["ba", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    raise SystemExit(main())
