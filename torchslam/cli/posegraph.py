"""``torchslam posegraph``: optimize a g2o pose graph with Levenberg-Marquardt.

Reads a g2o file (:mod:`torchslam.io.g2o`; ``--information`` chooses what happens to
information matrices that are not positive semidefinite), picks the initial poses (the chordal
relaxation by default, the file's vertex values, or the odometry chain), solves with
:func:`torchslam.posegraph.solve.solve_pose_graph` while printing one progress line per
iteration, prints a summary (standard cost ½ Σ rᵀΩr before and after, the SE-Sync objective,
status, time), and optionally writes the optimized graph as g2o and a figure of the trajectory
before and after (x-y and x-z projections of the vertex positions, and the cost curve).
"""

from __future__ import annotations

import argparse
import logging
import re
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch

from torchslam.cli import DEFAULT_THREADS, add_threads_argument, int_range, plots, using_threads
from torchslam.io import g2o
from torchslam.posegraph import certification, objectives
from torchslam.posegraph.graph import PoseGraph
from torchslam.posegraph.solve import (
    IterationInfo,
    PoseGraphSolverConfig,
    PoseGraphSolveResult,
    solve_pose_graph,
)
from torchslam.posegraph.solve import initial_poses as solve_initial_poses

__all__ = [
    "INITIALIZATIONS",
    "PoseGraphOptions",
    "add_arguments",
    "initial_poses",
    "options_from_args",
    "run_posegraph",
]

# Initial poses: the file's vertex values (for the benchmark files, the odometry chain as
# recorded; for an edge-only file, the measurements chained along a spanning tree), the
# odometry chain recomposed from the edges, or the chordal relaxation.
INITIALIZATIONS = ("file", "odometry", "chordal")
# The default: the chordal relaxation. From the file's vertices LM can stop in a local minimum
# (MIT.g2o: ½χ² = 385.1 against 20.60 from the chordal start; issue 14 reports a 5,000-pose
# synthetic graph at 2.4× the certified optimum, where GTSAM's LM stops too); from the chordal
# start LM reaches GTSAM's optima on sphere2500 and parking-garage, in as few iterations.
DEFAULT_INIT = "chordal"


@dataclass(frozen=True)
class PoseGraphOptions:
    """Options of ``torchslam posegraph`` (see ``torchslam posegraph --help``)."""

    # The g2o file to optimize.
    path: Path
    # Where to write the optimized graph (g2o), or None.
    out: Path | None = None
    # Where to write the before/after figure (PNG, PDF, … by suffix), or None.
    plot: Path | None = None
    # Initial poses: "chordal" (the default), "file" or "odometry" (see INITIALIZATIONS).
    init: Literal["file", "odometry", "chordal"] = DEFAULT_INIT
    # Maximum number of LM iterations.
    max_iterations: int = 100
    # Linear solver: "auto", "sparse" or "dense".
    linear_solver: Literal["auto", "sparse", "dense"] = "auto"
    # torch CPU threads for the run (torchslam.cli's thread policy).
    threads: int = DEFAULT_THREADS
    # --- objective and certificate (issue 14) ---
    # Objective minimized: "chi2" (½ Σ rᵀΩr) or "sesync" (SE-Sync's eq. 12).
    objective: Literal["chi2", "sesync"] = "chi2"
    # Compute SE-Sync's certificate of global optimality (posegraph.certification).
    certify: bool = False
    # --- information matrices (issue 14) ---
    # Information matrices that are not positive semidefinite: "repair", "nearest" or
    # "strict" (torchslam.io.g2o.INFORMATION_HANDLINGS, rules in torchslam.io.g2o).
    information: Literal["repair", "nearest", "strict"] = "repair"
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
        default=DEFAULT_INIT,
        help="initial poses: the chordal relaxation (default), the file's vertices (for an "
        "edge-only file: the edges chained along a spanning tree), or the odometry chain",
    )
    parser.add_argument(
        "--max-iterations",
        type=int_range(1, 100_000),
        default=100,
        help="LM iterations [1, 100000] (100)",
    )
    parser.add_argument(
        "--linear-solver",
        choices=["auto", "sparse", "dense"],
        default="auto",
        help="factorization of the reduced system: sparse (SciPy SuperLU, fill-reducing "
        "ordering), dense (batched Cholesky), or auto (default: sparse when its symbolic "
        "factorization predicts far less work)",
    )
    add_threads_argument(parser)
    # --- objective and certificate (issue 14) ---
    parser.add_argument(
        "--objective",
        choices=["chi2", "sesync"],
        default="chi2",
        help="objective: chi2 = ½ Σ rᵀΩr (default), sesync = SE-Sync's Σ κ‖R_j − R_i R̃‖² + "
        "τ‖t_j − t_i − R_i t̃‖² (Rosen et al. 2019, eq. 12)",
    )
    parser.add_argument(
        "--certify",
        action="store_true",
        help="certify the global optimum of the SE-Sync objective (SE-Sync's dual certificate; "
        "with --objective chi2 the chi2 solution is first refined on the SE-Sync objective)",
    )
    # --- information matrices (issue 14) ---
    parser.add_argument(
        "--information",
        choices=list(g2o.INFORMATION_HANDLINGS),
        default="repair",
        help="information matrices that are not positive semidefinite: keep their translation "
        "and rotation blocks (repair, default; SE-Sync's weights use only those), clip their "
        "eigenvalues (nearest), or refuse the file (strict)",
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
        objective=args.objective,
        certify=args.certify,
        information=args.information,
        covariance=getattr(args, "covariance", None),
    )


def initial_poses(graph: PoseGraph, init: str) -> torch.Tensor:
    """Initial poses (N, 4, 4) by name: "file", "odometry" or "chordal" (INITIALIZATIONS), as
    :func:`torchslam.posegraph.solve.initial_poses` gives them to the API's solve."""
    if init not in INITIALIZATIONS:
        raise ValueError(f"--init must be one of {INITIALIZATIONS}, got {init!r}")
    return solve_initial_poses(graph, init)


def _as_options(message: str) -> str:
    """A library message's ``information='repair'`` as the option ``--information repair``."""
    return re.sub(r"\binformation='([a-z]+)'", r"--information \1", message)


def run_posegraph(
    options: PoseGraphOptions,
    echo: Callable[[str], None] = print,
    *,
    verdict: Callable[[str], None] | None = None,
    on_certificate: Callable[[certification.Certificate], None] | None = None,
) -> PoseGraphSolveResult:
    """Run the command, printing through ``echo``; returns the solve result.

    With ``certify``: the certificate line goes through ``verdict`` (default ``echo``; the
    command prints it even under ``--quiet``), the certificate to ``on_certificate``, and
    ``out`` receives the poses that were certified (for the chi2 objective, its solution
    refined on the SE-Sync objective), as the output line says.

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
    with using_threads(options.threads):
        return _run(options, echo, verdict or echo, on_certificate)


def _run(
    options: PoseGraphOptions,
    echo: Callable[[str], None],
    verdict: Callable[[str], None],
    on_certificate: Callable[[certification.Certificate], None] | None,
) -> PoseGraphSolveResult:
    with warnings.catch_warnings():  # the reader's warning: the summary below says it
        warnings.simplefilter("ignore", UserWarning)
        try:
            graph = g2o.read_g2o(options.path, information=options.information)
        except ValueError as error:  # the reader's hints in the command line's words
            raise ValueError(_as_options(str(error))) from error
    poses = initial_poses(graph, options.init)
    num_odometry = int(graph.odometry_mask().sum())
    echo(
        f"{options.path}: {graph.num_vertices} vertices, {graph.num_edges} edges "
        f"({num_odometry} odometry, {graph.num_edges - num_odometry} loop closures), "
        f"{graph.dimension}D, initialization: {_describe_init(graph, options.init)}"
    )
    echo(_describe_information(graph))
    echo(f"{'iter':>4} {'cost':>14} {'lambda':>9} {'|step|':>9} {'step':>8} {'time':>9}")

    def progress(info: IterationInfo) -> None:
        # One graph: the batch of the loop's IterationInfo has one problem.
        if logging.getLogger("torchslam.posegraph").isEnabledFor(logging.INFO):
            return  # --verbose: the solver's log record says it (not twice)
        echo(
            f"{info.iteration:4d} {float(info.cost[0]):14.8g} {float(info.damping[0]):9.2e} "
            f"{float(info.step_norm[0]):9.2e} "
            f"{'accepted' if bool(info.accepted[0]) else 'rejected':>8} {info.seconds:8.3f}s"
        )

    config = PoseGraphSolverConfig(
        max_iterations=options.max_iterations,
        linear_solver=options.linear_solver,
        objective=options.objective,
    )
    result = solve_pose_graph(graph, poses, config=config, callback=progress)
    # --- objective and certificate (issue 14): both objectives before and after ---
    sesync_before = float(objectives.sesync_objective(graph, poses))
    sesync_after = float(objectives.sesync_objective(graph, result.poses))
    if options.objective == "sesync":
        chi2_before = float(objectives.standard_cost(graph, poses))
        chi2_after = float(objectives.standard_cost(graph, result.poses))
    else:
        chi2_before, chi2_after = result.initial_cost, result.final_cost
    echo("")
    echo(f"{'':28} {'initial':>16} {'optimized':>16}   (minimized: {options.objective})")
    echo(f"{'cost ½Σ rᵀΩr':28} {chi2_before:16.8g} {chi2_after:16.8g}")
    echo(f"{'SE-Sync objective':28} {sesync_before:16.8g} {sesync_after:16.8g}")
    echo(
        f"status {result.status.name} ({result.reason}) after {result.iterations} iterations, "
        f"{result.time_seconds:.3f} s ({result.linear_solver} linear solver; "
        f"linearization {result.linearize_seconds:.3f} s, "
        f"linear solves {result.linear_solve_seconds:.3f} s)"
    )
    written, what = result.poses, ""
    if options.certify:
        certificate, written = _certify(graph, result, options, echo, verdict)
        if on_certificate is not None:
            on_certificate(certificate)
        if options.objective != "sesync":
            what = " (the SE-Sync-refined poses that were certified)"
    if options.out is not None:
        options.out.parent.mkdir(parents=True, exist_ok=True)
        g2o.write_g2o(options.out, graph, written)
        echo(f"wrote {options.out}{what}")
    write_covariance_option(options, graph, result, config, echo)
    if options.plot is not None:
        plot = options.plot if options.plot.suffix else options.plot.with_suffix(".png")
        plots.plot_trajectories(plot, poses, result, title=options.path.name, graph=graph)
        echo(f"wrote {plot}")
    return result


# --- objective and certificate (issue 14) ---
def _certify(
    graph: PoseGraph,
    result: PoseGraphSolveResult,
    options: PoseGraphOptions,
    echo: Callable[[str], None],
    verdict: Callable[[str], None],
) -> tuple[certification.Certificate, torch.Tensor]:
    """Print SE-Sync's certificate for the SE-Sync objective; returns it and the certified
    poses. The certificate concerns that objective's optimum: a chi2 solution is first refined
    on the SE-Sync objective (LM from the chi2 poses) and the refined poses are certified."""
    poses = result.poses
    if options.objective != "sesync":
        config = PoseGraphSolverConfig(
            max_iterations=options.max_iterations,
            linear_solver=options.linear_solver,
            objective="sesync",
        )
        refined = solve_pose_graph(graph, poses, config=config)
        poses = refined.poses
        echo(
            f"SE-Sync refinement of the chi2 solution: objective {refined.initial_cost:.8g} -> "
            f"{refined.final_cost:.8g} in {refined.iterations} iterations "
            f"({refined.status.name}, {refined.time_seconds:.3f} s)"
        )
    certificate = certification.certify(graph, poses)
    verdict(
        f"certified global optimum: {'yes' if certificate.certified else 'no'} "
        f"(λ_min = {certificate.lambda_min:.3e}, η = {certificate.eta:.1e}; SE-Sync objective "
        f"{certificate.objective:.8g} ≥ f* ≥ {certificate.lower_bound:.8g}; "
        f"{certificate.seconds:.3f} s)"
    )
    return certificate, poses


# --- summary lines of the initializer and the information handling (issue 14) ---


def _describe_init(graph: PoseGraph, init: str) -> str:
    """The initializer's name, and where "file" poses came from in an edge-only file."""
    if init == "file" and graph.source is not None and not graph.source.has_vertices:
        return "file (no VERTEX lines: the edges chained along a spanning tree)"
    return init


def _describe_information(graph: PoseGraph) -> str:
    """One line: the information handling and how many edges it changed."""
    source = graph.source
    handling = source.information if source is not None else "repair"
    adjusted = source.adjusted_edges if source is not None else ()
    if not adjusted:
        return (
            f"information: {handling} (all {graph.num_edges} matrices positive semidefinite, "
            "used as read)"
        )
    what = {
        "repair": "kept their translation and rotation blocks, dropped the cross blocks",
        "nearest": "clipped their eigenvalues to the nearest positive-definite matrices",
    }[handling]
    return (
        f"information: {handling}: {len(adjusted)} of {graph.num_edges} edges not positive "
        f"semidefinite (first on line {source.adjusted_lines[0]}): {what}"
    )


# ------------------------------------------------------------------------------------------
# --covariance: the vertices' marginal covariances (torchslam.posegraph.covariance)


def add_covariance_argument(parser: argparse.ArgumentParser) -> None:
    """The ``--covariance OUT.txt`` option."""
    parser.add_argument(
        "--covariance",
        type=Path,
        help="write each vertex's marginal covariance here, one line 'id c11 c12 … c66' "
        "(36 values row-major, (ω, v) order, right perturbation of the body → world vertex "
        "pose, relative to the fixed vertex); for a 2D graph 'id c11 … c33' in (x, y, θ) "
        "order, as GTSAM's Pose2 marginals",
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
        f"wrote {options.covariance} ({graph.num_vertices} marginal covariances of the chi² "
        f"objective at the solution, {covariances.method}, {time.perf_counter() - start:.3f} s)"
    )
