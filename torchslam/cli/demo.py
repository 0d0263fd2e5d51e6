"""``torchslam demo``: a synthetic looping ICP-SLAM scene solved by LM, with a figure.

Generates a loop trajectory with a few hundred points per frame and Gaussian noise, starts
from drifted odometry (chained, the seed's section 0), solves with Levenberg-Marquardt while
printing one progress line per iteration, then prints a summary table and writes
``demo.png`` (top view of ground truth vs initial vs optimized trajectory, and the cost curve).
"""

from __future__ import annotations

import argparse
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from torchslam import covariance, initialization, metrics
from torchslam.cli import (
    DEFAULT_THREADS,
    _stderr,
    add_threads_argument,
    float_range,
    int_range,
    plots,
    using_threads,
)
from torchslam.data import make_scene
from torchslam.problem import PointMapProblem
from torchslam.solver import IterationInfo, SolverConfig, solve
from torchslam.solver.result import SolveResult

__all__ = [
    "LIMITS",
    "MAX_SCENE_SIZE",
    "DemoOptions",
    "add_arguments",
    "options_from_args",
    "run_demo",
    "validate",
]

# Accepted ranges of the options (inclusive; --visible-fraction excludes 0). The scene is a
# loop of radius ~4 m, so noise and drift beyond these bounds make no sense; the sizes keep
# the dense 6m × 6m Schur system and the (B, m, n) scene tensors within a few GiB.
LIMITS = {
    "poses": (3, 1000),
    "points": (3, 1_000_000),
    "visible_fraction": (0.0, 1.0),
    "noise": (0.0, 1.0),
    "drift_deg": (0.0, 45.0),
    "drift_translation": (0.0, 1.0),
    "batch_size": (1, 256),
    "seed": (0, 2**32 - 1),
}
# Largest batch_size × poses × points.
MAX_SCENE_SIZE = 10**8


@dataclass(frozen=True)
class DemoOptions:
    """Options of ``torchslam demo`` (see ``torchslam demo --help``)."""

    # Frames in the loop.
    num_poses: int = 40
    # World points.
    num_points: int = 2000
    # Fraction of the points each frame sees.
    visible_fraction: float = 0.15
    # Observation noise standard deviation (metres).
    noise: float = 0.01
    # Odometry error per step, degrees and metres (the drift of the initial guess).
    drift_deg: float = 2.0
    drift_translation: float = 0.05
    # Independent problems solved as one batch.
    batch_size: int = 1
    # Jacobian mode: "analytic" or "jacrev".
    jacobian: str = "analytic"
    # Random seed of the scene and the drift.
    seed: int = 0
    # Output folder for demo.png.
    out: Path = Path("out")
    # torch CPU threads for the run (torchslam.cli's thread policy).
    threads: int = DEFAULT_THREADS


def validate(options: DemoOptions) -> None:
    """Raise ValueError with a one-line message for an impossible option value (:data:`LIMITS`)."""
    for name, (low, high) in LIMITS.items():
        value = getattr(options, "num_" + name if name in ("poses", "points") else name)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise TypeError(f"--{name.replace('_', '-')} must be a number, got {value!r}")
        inside = low < value <= high if name == "visible_fraction" else low <= value <= high
        if not inside:  # also rejects NaN
            interval = f"{'(' if name == 'visible_fraction' else '['}{low:g}, {high:g}]"
            raise ValueError(f"--{name.replace('_', '-')} must be in {interval}, got {value}")
    size = options.batch_size * options.num_poses * options.num_points
    if size > MAX_SCENE_SIZE:
        raise ValueError(
            f"--batch-size × --poses × --points must be ≤ {MAX_SCENE_SIZE:.0e}, got {size:.3g}"
        )
    if options.jacobian not in ("analytic", "jacrev"):
        raise ValueError(f"--jacobian must be 'analytic' or 'jacrev', got {options.jacobian!r}")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``torchslam demo`` (ranges: :data:`LIMITS`)."""

    def limits(name: str) -> str:
        low, high = LIMITS[name]
        return f"{'(' if name == 'visible_fraction' else '['}{low:g}, {high:g}]"

    def integer(name: str):
        return int_range(*LIMITS[name])

    def number(name: str, **kwargs):
        return float_range(*LIMITS[name], **kwargs)

    parser.add_argument(
        "--poses", type=integer("poses"), default=40, help=f"frames {limits('poses')} (40)"
    )
    parser.add_argument(
        "--points", type=integer("points"), default=2000, help=f"points {limits('points')} (2000)"
    )
    parser.add_argument(
        "--visible-fraction",
        type=number("visible_fraction", low_open=True),
        default=0.15,
        help=f"fraction of the points each frame sees {limits('visible_fraction')} (0.15)",
    )
    parser.add_argument(
        "--noise", type=number("noise"), default=0.01, help=f"noise std, m {limits('noise')} (0.01)"
    )
    parser.add_argument(
        "--drift-deg",
        type=number("drift_deg"),
        default=2.0,
        help=f"odometry error, °/step {limits('drift_deg')} (2)",
    )
    parser.add_argument(
        "--drift-translation",
        type=number("drift_translation"),
        default=0.05,
        help=f"odometry error, m/step {limits('drift_translation')} (0.05)",
    )
    parser.add_argument(
        "--batch-size",
        type=integer("batch_size"),
        default=1,
        help=f"independent problems {limits('batch_size')} (1); batch × poses × points ≤ 1e8",
    )
    parser.add_argument(
        "--jacobian",
        choices=["analytic", "jacrev"],
        default="analytic",
        help="Jacobian blocks: analytic (default) or torch.func.jacrev (the same iterates)",
    )
    parser.add_argument("--seed", type=integer("seed"), default=0, help="random seed (0)")
    parser.add_argument("--out", type=Path, default=Path("out"), help="output folder (out)")
    add_threads_argument(parser)


def options_from_args(args: argparse.Namespace) -> DemoOptions:
    """The :class:`DemoOptions` of parsed ``torchslam demo`` arguments."""
    return DemoOptions(
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
        threads=getattr(args, "threads", DEFAULT_THREADS),
    )


def run_demo(
    options: DemoOptions,
    echo: Callable[[str], None] = print,
    warn: Callable[[str], None] = _stderr,
) -> SolveResult:
    """Run the demo, printing progress through ``echo``; returns the solve result.

    The figure needs matplotlib; without it one line ``figure skipped: …`` goes to ``warn``.

    Raises:
        ValueError: an option outside :data:`LIMITS`.
        OSError: the output folder cannot be created or written.
    """
    validate(options)
    with using_threads(options.threads):
        return _run_demo(options, echo, warn)


def _run_demo(
    options: DemoOptions, echo: Callable[[str], None], warn: Callable[[str], None]
) -> SolveResult:
    try:  # the figure's folder first: a bad --out is an error before the solve, not after it
        plots.require_matplotlib()
    except plots.MatplotlibMissingError:
        pass
    else:
        options.out.mkdir(parents=True, exist_ok=True)
    scene = make_scene(
        options.num_poses,
        options.num_points,
        batch_size=options.batch_size,
        trajectory="loop",
        visible_fraction=options.visible_fraction,
        noise_std=options.noise,
        seed=options.seed,
    )
    init = initialization.initialize_scene(
        scene,
        method="odometry",
        rotation_noise_deg=options.drift_deg,
        translation_noise=options.drift_translation,
        seed=options.seed + 1,
    )
    problem = PointMapProblem.from_scene(scene, init.poses, init.points)
    E = int(scene.valid.sum()) // options.batch_size
    echo(
        f"scene: {options.batch_size} × ({options.num_poses} poses, {options.num_points} points, "
        f"{E} observations ≈ {E // options.num_poses} per frame), noise {options.noise} m, "
        f"odometry drift {options.drift_deg}°/{options.drift_translation} m per step"
    )
    echo(f"{'iter':>4} {'cost':>13} {'rel. decrease':>13} {'lambda':>9} {'|step|':>9} {'time':>8}")
    previous = [problem.cost().detach().sum().item()]

    def progress(info: IterationInfo) -> None:
        cost = float(info.cost.sum())
        decrease = (previous[0] - cost) / previous[0] if previous[0] > 0 else 0.0
        previous[0] = cost
        if logging.getLogger("torchslam.solver").isEnabledFor(logging.INFO):
            return  # --verbose: the solver's log record says it (not twice)
        echo(
            f"{info.iteration:4d} {cost:13.6e} {decrease:13.3e} "
            f"{float(info.damping.max()):9.2e} {float(info.step_norm.max()):9.2e} "
            f"{info.seconds * 1e3:6.1f}ms"
        )

    config = SolverConfig(jacobian=options.jacobian)
    start = time.perf_counter()
    result = solve(problem, config, callback=progress)
    elapsed = time.perf_counter() - start

    before = metrics.evaluate(init.poses, scene.poses_gt, init.points, scene.points_gt)
    after = metrics.evaluate(result.poses, scene.poses_gt, result.points, scene.points_gt)
    rows = [
        (
            "cost",
            f"{float(result.initial_cost.sum()):.6g}",
            f"{float(result.final_cost.sum()):.6g}",
        ),
        (
            "rotation error mean / max (°)",
            f"{before.mean_rotation_error_deg:.4f} / {before.max_rotation_error_deg:.4f}",
            f"{after.mean_rotation_error_deg:.4f} / {after.max_rotation_error_deg:.4f}",
        ),
        ("ATE (m)", f"{before.mean_ate:.4f}", f"{after.mean_ate:.5f}"),
        ("point RMSE (m)", f"{before.mean_point_rmse:.4f}", f"{after.mean_point_rmse:.5f}"),
    ]
    echo("")
    echo(f"{'':30} {'initial':>20} {'optimized':>20}")
    for name, a, b in rows:
        echo(f"{name:30} {a:>20} {b:>20}")
    echo(
        f"solve: {elapsed * 1e3:.1f} ms, {int(result.iterations.max())} iterations, "
        f"status {result.status[0].name} ({result.reason[0]})"
    )
    try:
        path = plots.plot_demo(
            scene, init.poses, result, options.out, _position_covariances(problem, result, options)
        )
    except plots.MatplotlibMissingError as error:
        warn(f"figure skipped: {error}")
    else:
        echo(f"wrote {path}")
    return result


def _position_covariances(problem: PointMapProblem, result: SolveResult, options: DemoOptions):
    """Covariances of the optimized frame positions in world (frame 0) coordinates, (B, m, 3,
    3), for the figure's ellipses: the observations have unit weights and noise σ, so the
    covariance of the estimate is σ² H⁻¹ (:func:`torchslam.marginal_covariances`), moved to
    the positions by :func:`torchslam.covariance.position_covariance`. None when the figure
    cannot be drawn or the Hessian is singular."""
    try:
        plots.require_matplotlib()
    except plots.MatplotlibMissingError:
        return None
    blocks = covariance.marginal_covariances(problem, result, points=False)
    if not bool(blocks.ok.all()):
        return None
    return covariance.position_covariance(options.noise**2 * blocks.poses, result.poses)
