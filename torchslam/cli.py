"""The ``torchslam`` command: a thin argparse front end over the library.

Subcommands: ``demo`` (synthetic ICP-SLAM solve with live progress and a figure),
``bench`` (the solver benchmark), ``posegraph`` (optimize a g2o pose graph) and ``register``
(multiview registration of range scans). Bad input (a
missing file, a malformed file, an impossible option value) gives a one-line message on stderr
and exit status 2 — never a traceback.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["main"]


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def _non_negative_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number ≥ 0, got {text!r}") from None
    if not value >= 0:  # also rejects NaN
        raise argparse.ArgumentTypeError(f"expected a number ≥ 0, got {text}")
    return value


def _fraction(text: str) -> float:
    value = _non_negative_float(text)
    if not 0 < value <= 1:
        raise argparse.ArgumentTypeError(f"expected a fraction in (0, 1], got {text}")
    return value


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="torchslam",
        description="ICP-SLAM as batched, differentiable least squares on SE(3).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    demo = sub.add_parser(
        "demo",
        help="solve a synthetic looping ICP-SLAM scene with LM and plot it",
        description="Generate a looping synthetic scene with noise and drifted odometry, solve "
        "it with Levenberg-Marquardt (one progress line per iteration), print a summary table "
        "and write demo.png.",
    )
    demo.add_argument("--poses", type=_positive_int, default=40, help="frames (default 40)")
    demo.add_argument("--points", type=_positive_int, default=2000, help="points (default 2000)")
    demo.add_argument(
        "--visible-fraction", type=_fraction, default=0.15, help="points seen per frame (0.15)"
    )
    demo.add_argument("--noise", type=_non_negative_float, default=0.01, help="noise std, m")
    demo.add_argument(
        "--drift-deg", type=_non_negative_float, default=2.0, help="odometry error, °/step (2)"
    )
    demo.add_argument(
        "--drift-translation", type=_non_negative_float, default=0.05, help="m/step (0.05)"
    )
    demo.add_argument("--batch-size", type=_positive_int, default=1, help="problems (default 1)")
    demo.add_argument("--jacobian", choices=["analytic", "jacrev"], default="analytic")
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--out", type=Path, default=Path("out"), help="output folder (out)")

    bench = sub.add_parser(
        "bench",
        help="run the solver benchmark (cases S, M, L, O, BATCH)",
        description="Time the solver on the synthetic cases S, M, L, O, BATCH (float64), compare "
        "with scipy.optimize.least_squares, write bench_solver.json and bench_solver.png.",
    )
    from torchslam.benchmark import add_arguments

    add_arguments(bench)

    posegraph = sub.add_parser(
        "posegraph",
        help="optimize a g2o pose graph with Levenberg-Marquardt",
        description="Read a 3D (VERTEX_SE3:QUAT/EDGE_SE3:QUAT) or 2D (VERTEX_SE2/EDGE_SE2) g2o "
        "pose graph, minimize ½ Σ rᵀΩr with Levenberg-Marquardt and a sparse linear solver "
        "(one progress line per iteration), print the costs before and after, optionally "
        "write the optimized graph and a figure of the trajectory before and after.",
    )
    posegraph.add_argument("file", type=Path, help="the g2o file")
    posegraph.add_argument("--out", type=Path, help="write the optimized graph (g2o) here")
    posegraph.add_argument(
        "--plot", type=Path, help="write a figure (x-y, x-z, cost) here, e.g. trajectory.png"
    )
    posegraph.add_argument(
        "--init",
        choices=["file", "odometry", "chordal"],
        default="file",
        help="initial poses: the file's vertices (default), the odometry chain, or chordal",
    )
    posegraph.add_argument(
        "--max-iterations", type=_positive_int, default=100, help="LM iterations (100)"
    )
    posegraph.add_argument(
        "--linear-solver", choices=["auto", "sparse", "dense"], default="auto", help="(auto)"
    )
    posegraph.add_argument(
        "--threads", type=_positive_int, default=1, help="torch CPU threads (default 1)"
    )
    register = sub.add_parser(
        "register",
        help="register range scans (PLY) by pairwise ICP + joint ICP-SLAM",
        description="Multiview registration: pairwise ICP along the given scan order, chained "
        "poses, point tracks, then the joint ICP-SLAM least-squares solve (robust), "
        "re-associated a few rounds. Writes poses.txt, merged.ply and registration.png.",
    )
    from torchslam.register import add_arguments as add_register_arguments

    add_register_arguments(register)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``torchslam`` console script; returns the exit status."""
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        if args.command == "demo":
            from torchslam.demo import DemoOptions, run_demo

            run_demo(
                DemoOptions(
                    num_poses=args.poses,
                    num_points=args.points,
                    visible_fraction=args.visible_fraction,
                    noise=args.noise,
                    drift_deg=args.drift_deg,
                    drift_translation=args.drift_translation,
                    batch_size=args.batch_size,
                    jacobian=args.jacobian,
                    seed=args.seed,
                    out=args.out,
                )
            )
        elif args.command == "bench":
            from torchslam.benchmark import run

            run(args)
        elif args.command == "posegraph":
            from torchslam.posegraph.command import PoseGraphOptions, run_posegraph

            run_posegraph(
                PoseGraphOptions(
                    path=args.file,
                    out=args.out,
                    plot=args.plot,
                    init=args.init,
                    max_iterations=args.max_iterations,
                    linear_solver=args.linear_solver,
                    threads=args.threads,
                )
            )
        elif args.command == "register":
            from torchslam.register import run as run_register

            return run_register(args)
    except (ValueError, TypeError, OSError) as error:
        print(f"torchslam {args.command}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"torchslam {args.command}: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
