"""``torchslam demo``: a synthetic looping ICP-SLAM scene solved by LM, with a figure.

Generates a loop trajectory with a few hundred points per frame and Gaussian noise, starts
from drifted odometry (chained, the seed's section 0), solves with Levenberg-Marquardt while
printing one progress line per iteration, then prints a summary table and writes
``demo.png`` (top view of ground truth vs initial vs optimized trajectory, and the cost curve).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import torch

from torchslam import initialization, metrics
from torchslam.data import make_scene
from torchslam.problem import PointMapProblem
from torchslam.solver import SolverConfig, solve
from torchslam.solver.result import SolveResult

__all__ = ["DemoOptions", "run_demo"]


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


def _positive(name: str, value: float) -> None:
    if not value > 0:
        raise ValueError(f"{name} must be > 0, got {value}")


def validate(options: DemoOptions) -> None:
    """Raise ValueError with a one-line message for an impossible option value."""
    _positive("--poses", options.num_poses)
    _positive("--points", options.num_points)
    _positive("--batch-size", options.batch_size)
    if options.num_poses < 3:
        raise ValueError(f"--poses must be ≥ 3, got {options.num_poses}")
    if not 0 < options.visible_fraction <= 1:
        raise ValueError(f"--visible-fraction must be in (0, 1], got {options.visible_fraction}")
    if options.noise < 0:
        raise ValueError(f"--noise must be ≥ 0, got {options.noise}")
    if options.drift_deg < 0 or options.drift_translation < 0:
        raise ValueError("--drift-deg and --drift-translation must be ≥ 0")
    if options.jacobian not in ("analytic", "jacrev"):
        raise ValueError(f"--jacobian must be 'analytic' or 'jacrev', got {options.jacobian!r}")


def run_demo(options: DemoOptions, echo=print) -> SolveResult:
    """Run the demo, printing progress through ``echo``; returns the solve result."""
    validate(options)
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

    def progress(info: dict) -> None:
        cost = float(info["cost"].sum())
        decrease = (previous[0] - cost) / previous[0] if previous[0] > 0 else 0.0
        previous[0] = cost
        echo(
            f"{info['iteration']:4d} {cost:13.6e} {decrease:13.3e} "
            f"{float(info['lambda'].max()):9.2e} {float(info['step_norm'].max()):9.2e} "
            f"{info['seconds'] * 1e3:6.1f}ms"
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
    path = _figure(scene, init.poses, result, options.out)
    if path is not None:
        echo(f"wrote {path}")
    return result


def _figure(scene, initial_poses: torch.Tensor, result: SolveResult, out: Path) -> Path | None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    out.mkdir(parents=True, exist_ok=True)

    def positions(T: torch.Tensor) -> torch.Tensor:  # sensor positions: translation of T_0i
        R, t = T[0, :, :3, :3], T[0, :, :3, 3]
        return -(R.transpose(-1, -2) @ t[..., None])[..., 0]

    fig, (ax, ax_cost) = plt.subplots(1, 2, figsize=(11, 4.8))
    # "Top view": the two world axes along which the true trajectory spreads most (frame 0
    # is a sensor frame, so the ground plane need not be x-y).
    gt = positions(scene.poses_gt)
    a, b = sorted(torch.argsort(gt.std(dim=0), descending=True)[:2].tolist())
    for T, label, style, width in (
        (scene.poses_gt, "ground truth", "k-", 4.0),
        (initial_poses, "initial (drifted odometry)", "r--", 1.5),
        (result.poses, "optimized (LM)", "c-", 1.5),
    ):
        p = positions(T.detach()).numpy()
        ax.plot(p[:, a], p[:, b], style, label=label, lw=width, alpha=0.9)
    pts = scene.points_gt[0].numpy()
    ax.scatter(pts[:, a], pts[:, b], s=1, c="0.8", zorder=0, label="points")
    ax.set_aspect("equal")
    ax.set_xlabel(f"{'xyz'[a]} (m)")
    ax.set_ylabel(f"{'xyz'[b]} (m)")
    ax.set_title("trajectory, top view")
    ax.legend(loc="upper right", fontsize=8)
    history = result.cost_history[0].numpy()
    ax_cost.semilogy(range(len(history)), history, "o-")
    ax_cost.set_xlabel("iteration")
    ax_cost.set_ylabel("cost ½Σ‖r‖²")
    ax_cost.set_title("Levenberg-Marquardt cost")
    ax_cost.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    path = out / "demo.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
