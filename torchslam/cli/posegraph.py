"""``torchslam posegraph``: optimize a g2o pose graph with Levenberg-Marquardt.

Reads a g2o file (:mod:`torchslam.io.g2o`), picks the initial poses (the file's vertex values,
the odometry chain, or the chordal relaxation), solves with
:func:`torchslam.posegraph.solve.solve_pose_graph` while printing one progress line per
iteration, prints a summary (standard cost ½ Σ rᵀΩr before and after, the SE-Sync objective,
status, time), and optionally writes the optimized graph as g2o and a figure of the trajectory
before and after (x-y and x-z projections of the vertex positions, and the cost curve).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch

from torchslam.cli import int_range, plots
from torchslam.io import g2o
from torchslam.posegraph import initialization, objectives
from torchslam.posegraph.graph import PoseGraph
from torchslam.posegraph.solve import (
    IterationInfo,
    PoseGraphSolverConfig,
    PoseGraphSolveResult,
    solve_pose_graph,
)

__all__ = [
    "INITIALIZATIONS",
    "PoseGraphOptions",
    "add_arguments",
    "initial_poses",
    "options_from_args",
    "run_posegraph",
]

# Initial poses: the file's vertex values (for the benchmark files, the odometry chain as
# recorded), the odometry chain recomposed from the edges, or the chordal relaxation.
INITIALIZATIONS = ("file", "odometry", "chordal")


@dataclass(frozen=True)
class PoseGraphOptions:
    """Options of ``torchslam posegraph`` (see ``torchslam posegraph --help``)."""

    # The g2o file to optimize.
    path: Path
    # Where to write the optimized graph (g2o), or None.
    out: Path | None = None
    # Where to write the before/after figure (PNG, PDF, … by suffix), or None.
    plot: Path | None = None
    # Initial poses: "file", "odometry" or "chordal" (see INITIALIZATIONS).
    init: Literal["file", "odometry", "chordal"] = "file"
    # Maximum number of LM iterations.
    max_iterations: int = 100
    # Linear solver: "auto", "sparse" or "dense".
    linear_solver: Literal["auto", "sparse", "dense"] = "auto"
    # torch CPU threads (torch.set_num_threads). 1 by default: the per-edge tensors are small
    # (most ops run single-threaded anyway) and SuperLU is single-threaded, while a second
    # OpenMP thread on a busy 2-core machine made the linearization 25× slower.
    threads: int = 1
    # Where to write the vertices' marginal covariances (see the covariance block below).
    covariance: Path | None = None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``torchslam posegraph``."""
    parser.add_argument("file", type=Path, help="the g2o file")
    parser.add_argument("--out", type=Path, help="write the optimized graph (g2o) here")
    parser.add_argument(
        "--plot",
        type=Path,
        help="write a figure (x-y, x-z, cost) here, e.g. trajectory.png (needs matplotlib: "
        f"{plots.INSTALL_HINT})",
    )
    parser.add_argument(
        "--init",
        choices=list(INITIALIZATIONS),
        default="file",
        help="initial poses: the file's vertices (default), the odometry chain, or chordal",
    )
    parser.add_argument(
        "--max-iterations",
        type=int_range(1, 100_000),
        default=100,
        help="LM iterations [1, 100000] (100)",
    )
    parser.add_argument(
        "--linear-solver", choices=["auto", "sparse", "dense"], default="auto", help="(auto)"
    )
    parser.add_argument(
        "--threads", type=int_range(1, 1024), default=1, help="torch CPU threads [1, 1024] (1)"
    )
    add_covariance_argument(parser)


def options_from_args(args: argparse.Namespace) -> PoseGraphOptions:
    """The :class:`PoseGraphOptions` of parsed ``torchslam posegraph`` arguments."""
    return PoseGraphOptions(
        path=args.file,
        out=args.out,
        plot=args.plot,
        init=args.init,
        max_iterations=args.max_iterations,
        linear_solver=args.linear_solver,
        threads=args.threads,
        covariance=getattr(args, "covariance", None),
    )


def initial_poses(graph: PoseGraph, init: str) -> torch.Tensor:
    """Initial poses (N, 4, 4) by name: "file", "odometry" or "chordal" (INITIALIZATIONS)."""
    if init == "file":
        return graph.poses
    if init == "odometry":
        return initialization.odometry_initialization(graph)
    if init == "chordal":
        return initialization.chordal_initialization(graph)
    raise ValueError(f"--init must be one of {INITIALIZATIONS}, got {init!r}")


def run_posegraph(
    options: PoseGraphOptions, echo: Callable[[str], None] = print
) -> PoseGraphSolveResult:
    """Run the command, printing through ``echo``; returns the solve result.

    Raises:
        ValueError: malformed file (the message names the line), bad option, broken chain,
            a figure asked for (``plot``) while matplotlib is missing (raised before solving).
        OSError: a file that cannot be read or written.
    """
    if options.max_iterations < 1:
        raise ValueError(f"--max-iterations must be ≥ 1, got {options.max_iterations}")
    if options.threads < 1:
        raise ValueError(f"--threads must be ≥ 1, got {options.threads}")
    check_covariance_option(options)
    if options.out is not None and options.out.is_dir():
        raise ValueError(f"--out {options.out} is a directory; give a file name (e.g. out.g2o)")
    if options.plot is not None:
        plots.check_figure_format(options.plot)  # before the solve, not after it
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(options.threads)
    try:
        return _run(options, echo)
    finally:
        torch.set_num_threads(previous_threads)


def _run(options: PoseGraphOptions, echo: Callable[[str], None]) -> PoseGraphSolveResult:
    graph = g2o.read_g2o(options.path)
    poses = initial_poses(graph, options.init)
    num_odometry = int(graph.odometry_mask().sum())
    echo(
        f"{options.path}: {graph.num_vertices} vertices, {graph.num_edges} edges "
        f"({num_odometry} odometry, {graph.num_edges - num_odometry} loop closures), "
        f"{graph.dimension}D, initialization: {options.init}"
    )
    echo(f"{'iter':>4} {'cost':>14} {'lambda':>9} {'|step|':>9} {'step':>8} {'time':>9}")

    def progress(info: IterationInfo) -> None:
        # One graph: the batch of the loop's IterationInfo has one problem.
        echo(
            f"{info.iteration:4d} {float(info.cost[0]):14.8g} {float(info.damping[0]):9.2e} "
            f"{float(info.step_norm[0]):9.2e} "
            f"{'accepted' if bool(info.accepted[0]) else 'rejected':>8} {info.seconds:8.3f}s"
        )

    config = PoseGraphSolverConfig(
        max_iterations=options.max_iterations, linear_solver=options.linear_solver
    )
    result = solve_pose_graph(graph, poses, config=config, callback=progress)
    sesync_before = float(objectives.sesync_objective(graph, poses))
    sesync_after = float(objectives.sesync_objective(graph, result.poses))
    echo("")
    echo(f"{'':28} {'initial':>16} {'optimized':>16}")
    echo(f"{'cost ½Σ rᵀΩr':28} {result.initial_cost:16.8g} {result.final_cost:16.8g}")
    echo(f"{'SE-Sync objective':28} {sesync_before:16.8g} {sesync_after:16.8g}")
    echo(
        f"status {result.status.name} ({result.reason}) after {result.iterations} iterations, "
        f"{result.time_seconds:.3f} s ({result.linear_solver} linear solver; "
        f"linearization {result.linearize_seconds:.3f} s, "
        f"linear solves {result.linear_solve_seconds:.3f} s)"
    )
    if options.out is not None:
        options.out.parent.mkdir(parents=True, exist_ok=True)
        g2o.write_g2o(options.out, graph, result.poses)
        echo(f"wrote {options.out}")
    write_covariance_option(options, graph, result, config, echo)
    if options.plot is not None:
        plot = options.plot if options.plot.suffix else options.plot.with_suffix(".png")
        plots.plot_trajectories(plot, poses, result, title=options.path.name)
        echo(f"wrote {plot}")
    return result


# ------------------------------------------------------------------------------------------
# --covariance: the vertices' marginal covariances (torchslam.posegraph.covariance)


def add_covariance_argument(parser: argparse.ArgumentParser) -> None:
    """The ``--covariance OUT.txt`` option."""
    parser.add_argument(
        "--covariance",
        type=Path,
        help="write each vertex's marginal covariance here, one line 'id c11 c12 … c66' "
        "(36 values row-major, (ω, v) order, right perturbation of the body → world vertex "
        "pose, relative to the fixed vertex)",
    )


def check_covariance_option(options: PoseGraphOptions) -> None:
    """ValueError for a ``--covariance`` path that is a folder (before the solve)."""
    if options.covariance is not None and options.covariance.is_dir():
        raise ValueError(
            f"--covariance {options.covariance} is a directory; give a file name (e.g. cov.txt)"
        )


def write_covariance_option(
    options: PoseGraphOptions,
    graph: PoseGraph,
    result: PoseGraphSolveResult,
    config: PoseGraphSolverConfig,
    echo: Callable[[str], None],
) -> None:
    """Compute and write the covariances when ``--covariance`` was given."""
    if options.covariance is None:
        return
    if not bool(torch.isfinite(result.poses).all()):
        echo(f"{options.covariance} not written: the solve failed ({result.status.name})")
        return
    import time

    from torchslam.posegraph.covariance import marginal_covariances, write_covariances

    start = time.perf_counter()
    covariances = marginal_covariances(graph, result, config=config)
    options.covariance.parent.mkdir(parents=True, exist_ok=True)
    write_covariances(options.covariance, graph, covariances)
    echo(
        f"wrote {options.covariance} ({graph.num_vertices} marginal covariances, "
        f"{covariances.method}, {time.perf_counter() - start:.3f} s)"
    )
