"""Loop closure on a closed-loop ICP-SLAM scene: points only vs + odometry vs + loop closure.

The scene (:func:`torchslam.data.loop.make_loop_scene`) goes once around a wobbly circle and
returns to its start; each point is seen by a few successive frames only, so nothing in the
point observations links the last frames with the first: the drift accumulated along the loop
can only be corrected by the loop-closure measurement Z_{m-1,0} ≈ T_{m-1,0} T_00⁻¹.

Initial guess: the odometry chained from frame 0, T_{i+1,0} = Z_{i,i+1}⁻¹ T_i0, and the points
as the mean of their views mapped to frame 0 with those poses. Three objectives are solved
from it with :func:`torchslam.solve` (Levenberg-Marquardt, Schur complement):

- ``points``: the point observations alone (weight 1/σ² per observation);
- ``points+odometry``: + a :class:`torchslam.terms.RelativePoseTerm` per odometry step;
- ``points+odometry+loop``: + the loop-closure RelativePoseTerm.

Every term is weighted by the inverse covariance of the simulated noise: 1/σ² for the points,
diag(1/σ_rot² I₃, 1/σ_t² I₃) in (ω, v) order for the relative poses (σ_rot in radians), so the
objective is the negative log-likelihood and the solution the maximum-likelihood estimate.

The ATE is the RMSE of the sensor positions against the ground truth, without alignment (both
fix frame 0 at the identity); the aligned ATE first applies the best rigid alignment; the
end-of-loop error is the position error of frame m-1, the quantity the loop closure measures.

Defaults: 80 poses, 10 points born per frame, each seen by 3 frames, point noise 3 cm. That is
sparser than :func:`make_loop_scene`'s defaults (30 points, window 4, 1 cm), whose point chain
is so tight that its drift is comparable to the loop-closure noise and the loop closure lowers
the mean ATE by only ~1.6x (0.8x to 2.5x per seed over seeds 0-9; pass ``--points-per-frame 30
--window 4 --noise-std 0.01`` to see it). The gain varies a lot from seed to seed (a loop
closure pins the end of the drift, not its middle), so several seeds are run and the
min/median/max ATE ratio is reported.

Run from the repository root:
    .venv/bin/python experiments/loop_closure.py [--poses 80] [--seed 0] [--num-seeds 5] [--plot]
It writes out/loop_closure.json (and out/loop_closure.png, first seed, with --plot).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

from torchslam import PointMapProblem, SolverConfig, solve
from torchslam.data.loop import LoopScene, make_loop_scene
from torchslam.initialization import average_points, chain_relative_poses
from torchslam.lie import se3
from torchslam.metrics import evaluate
from torchslam.objective.terms import RelativePoseTerm

OBJECTIVES = ("points", "points+odometry", "points+odometry+loop")
OUT = Path("out")  # under the working directory


def initial_guess(loop: LoopScene) -> tuple[torch.Tensor, torch.Tensor]:
    """Poses chained from the odometry, T_{i+1,0} = Z_{i,i+1}⁻¹ T_i0, (1, m, 4, 4), and points
    averaged over their views with those poses, (1, n, 3)."""
    s = loop.scene
    poses = chain_relative_poses(se3.inverse(loop.odometry))[None]
    points = average_points(
        poses, s.pose_index, s.point_index, s.observations, s.num_points, valid=s.valid
    )
    return poses, points


def build_problem(
    loop: LoopScene, objective: str, poses: torch.Tensor, points: torch.Tensor
) -> PointMapProblem:
    """The problem of one of :data:`OBJECTIVES` at the initial guess (poses, points)."""
    if objective not in OBJECTIVES:
        raise ValueError(f"build_problem: objective must be one of {OBJECTIVES}, got {objective!r}")
    s = loop.scene
    terms = []
    if objective != "points":
        K = loop.odometry.shape[0]
        information = loop.odometry_information().expand(K, 6, 6)
        terms.append(RelativePoseTerm(loop.odometry_pairs, loop.odometry, information=information))
    if objective == "points+odometry+loop":
        information = loop.loop_information()[None]
        terms.append(RelativePoseTerm(loop.loop_pairs, loop.loop, information=information))
    weights = torch.full_like(s.observations[..., 0], 1.0 / loop.noise_std**2)
    return PointMapProblem(
        poses,
        points,
        s.pose_index,
        s.point_index,
        s.observations,
        valid=s.valid,
        weights=weights,
        terms=terms,
    )


def errors(loop: LoopScene, poses: torch.Tensor, points: torch.Tensor) -> dict[str, float]:
    """ATE (unaligned and aligned), rotation, RPE and point errors against the ground truth."""
    s = loop.scene
    e = evaluate(poses, s.poses_gt, points, s.points_gt)
    aligned = evaluate(poses, s.poses_gt, align="se3")
    return {
        "ate": float(e.ate[0]),
        "ate_aligned": float(aligned.ate[0]),
        "max_translation_error": float(e.translation_error.max()),
        "end_translation_error": float(e.translation_error[0, -1]),
        "end_rotation_error_deg": float(e.rotation_error_deg[0, -1]),
        "mean_rotation_error_deg": e.mean_rotation_error_deg,
        "max_rotation_error_deg": e.max_rotation_error_deg,
        "mean_rpe_translation": e.mean_rpe_translation,
        "mean_rpe_rotation_deg": e.mean_rpe_rotation_deg,
        "point_rmse": float(e.point_rmse[0]),
    }


def run(loop: LoopScene, config: SolverConfig | None = None) -> dict[str, object]:
    """Solve the three objectives from the odometry initial guess; errors, costs, status, time."""
    poses0, points0 = initial_guess(loop)
    report: dict[str, object] = {"initial": errors(loop, poses0, points0)}
    solutions = {}
    for objective in OBJECTIVES:
        start = time.perf_counter()
        problem = build_problem(loop, objective, poses0, points0)
        build_seconds = time.perf_counter() - start
        result = solve(problem, config)
        poses, points = result.poses.detach(), result.points.detach()
        solutions[objective] = poses
        report[objective] = {
            **errors(loop, poses, points),
            "initial_cost": float(result.initial_cost[0]),
            "final_cost": float(result.final_cost[0]),
            "status": result.status[0].name,
            "converged": result.converged[0],
            "iterations": int(result.iterations[0]),
            "solve_seconds": result.time_seconds,
            "build_seconds": build_seconds,
        }
    report["_trajectories"] = {"initial": poses0, **solutions}
    return report


def plot(loop: LoopScene, trajectories: dict[str, torch.Tensor], path: Path) -> None:
    """Top view of the sensor positions of the ground truth and the estimates (frame 0 at the
    black dot)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # Frame 0 is a sensor frame (y down, z towards the loop's centre): project onto the plane
    # of the ground-truth loop (its two principal axes) for a top view.
    gt_centres = se3.inverse(loop.scene.poses_gt[0])[:, :3, 3]
    mean = gt_centres.mean(0)
    axes = torch.linalg.svd(gt_centres - mean, full_matrices=False).Vh[:2]  # (2, 3)

    def centres(poses: torch.Tensor) -> torch.Tensor:
        c = se3.inverse(poses[0])[:, :3, 3]
        c = torch.cat((c, c[:1]))  # close the loop for the drawing
        return (c - mean) @ axes.T

    fig, ax = plt.subplots(figsize=(7, 7))
    gt = centres(loop.scene.poses_gt)
    ax.plot(gt[:, 0], gt[:, 1], "k-", lw=2.5, label="ground truth")
    styles = {
        "initial": ("tab:gray", "--"),
        "points": ("tab:orange", "-"),
        "points+odometry": ("tab:blue", "-"),
        "points+odometry+loop": ("tab:green", "-"),
    }
    for name, poses in trajectories.items():
        color, ls = styles[name]
        c = centres(poses)
        ax.plot(c[:, 0], c[:, 1], color=color, ls=ls, lw=1.2, label=name)
    ax.plot(gt[0, 0], gt[0, 1], "ko", ms=6)
    ax.set_aspect("equal")
    ax.set_xlabel("first principal axis of the loop (m)")
    ax.set_ylabel("second principal axis (m)")
    ax.set_title(f"Loop closure, m = {loop.num_poses} poses (top view)")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _print_table(report: dict[str, object]) -> None:
    print(
        f"{'':<22} {'ATE (m)':>9} {'aligned':>9} {'rot (deg)':>9} {'end err':>9} "
        f"{'final cost':>12} {'status':>18} {'iters':>5} {'time (s)':>8}"
    )
    init = report["initial"]
    print(
        f"{'initial (odometry)':<22} {init['ate']:>9.4f} {init['ate_aligned']:>9.4f} "
        f"{init['mean_rotation_error_deg']:>9.3f} {init['end_translation_error']:>9.4f}"
    )
    for objective in OBJECTIVES:
        r = report[objective]
        print(
            f"{objective:<22} {r['ate']:>9.4f} {r['ate_aligned']:>9.4f} "
            f"{r['mean_rotation_error_deg']:>9.3f} {r['end_translation_error']:>9.4f} "
            f"{r['final_cost']:>12.6g} {r['status']:>18} {r['iterations']:>5} "
            f"{r['solve_seconds']:>8.3f}"
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=80, help="poses around the loop")
    parser.add_argument("--points-per-frame", type=int, default=10)
    parser.add_argument("--window", type=int, default=3, help="frames that see each point")
    parser.add_argument("--seed", type=int, default=0, help="first seed")
    parser.add_argument("--num-seeds", type=int, default=5, help="seeds seed, seed+1, …")
    parser.add_argument("--noise-std", type=float, default=0.03, help="point noise (m)")
    parser.add_argument("--odometry-rotation-deg", type=float, default=0.5)
    parser.add_argument("--odometry-translation", type=float, default=0.02)
    parser.add_argument("--loop-rotation-deg", type=float, default=0.1)
    parser.add_argument("--loop-translation", type=float, default=0.005)
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--out", type=Path, default=OUT / "loop_closure.json")
    parser.add_argument("--plot", action="store_true", help="PNG (top view) of the first seed")
    args = parser.parse_args(argv)
    if args.noise_std <= 0:
        parser.error("--noise-std must be > 0 (its inverse square weights the points)")
    if args.num_seeds < 1:
        parser.error("--num-seeds must be >= 1")
    torch.set_num_threads(args.threads)

    per_seed = []
    for seed in range(args.seed, args.seed + args.num_seeds):
        loop = make_loop_scene(
            num_poses=args.poses,
            points_per_frame=args.points_per_frame,
            window=args.window,
            noise_std=args.noise_std,
            odometry_rotation_deg=args.odometry_rotation_deg,
            odometry_translation=args.odometry_translation,
            loop_rotation_deg=args.loop_rotation_deg,
            loop_translation=args.loop_translation,
            seed=seed,
        )
        s = loop.scene
        print(
            f"\nseed {seed}: m = {s.num_poses} poses, n = {s.num_points} points, "
            f"E = {int(s.num_observations[0])} observations, window {loop.window}"
        )
        report = run(loop)
        trajectories = report.pop("_trajectories")
        _print_table(report)
        report["seed"] = seed
        report["ate_ratio_odometry_over_loop"] = (
            report["points+odometry"]["ate"] / report["points+odometry+loop"]["ate"]
        )
        per_seed.append(report)
        if args.plot and seed == args.seed:
            png = args.out.with_suffix(".png")
            png.parent.mkdir(parents=True, exist_ok=True)
            plot(loop, trajectories, png)
            print(f"wrote {png}")

    def mean(objective: str, key: str) -> float:
        return sum(r[objective][key] for r in per_seed) / len(per_seed)

    ratios = sorted(r["ate_ratio_odometry_over_loop"] for r in per_seed)
    summary = {
        objective: {
            "mean_ate": mean(objective, "ate"),
            "mean_end_translation_error": mean(objective, "end_translation_error"),
            **(
                {"mean_solve_seconds": mean(objective, "solve_seconds")}
                if objective != "initial"
                else {}
            ),
        }
        for objective in ("initial", *OBJECTIVES)
    }
    summary["ate_ratio_odometry_over_loop"] = {
        "per_seed": [r["ate_ratio_odometry_over_loop"] for r in per_seed],
        "min": ratios[0],
        "median": ratios[len(ratios) // 2],
        "max": ratios[-1],
        "of_means": summary["points+odometry"]["mean_ate"]
        / summary["points+odometry+loop"]["mean_ate"],
    }
    print(f"\nover {len(per_seed)} seed(s) {args.seed}..{args.seed + len(per_seed) - 1}:")
    for objective in ("initial", *OBJECTIVES):
        print(
            f"  {objective:<22} mean ATE {summary[objective]['mean_ate']:.4f} m, mean end-of-loop "
            f"error {summary[objective]['mean_end_translation_error']:.4f} m"
        )
    r = summary["ate_ratio_odometry_over_loop"]
    print(
        f"  ATE(points+odometry) / ATE(points+odometry+loop): min {r['min']:.2f}, median "
        f"{r['median']:.2f}, max {r['max']:.2f}; ratio of the means {r['of_means']:.2f}"
    )

    output = {
        "scene": {
            "num_poses": args.poses,
            "points_per_frame": args.points_per_frame,
            "window": args.window,
            "seeds": list(range(args.seed, args.seed + args.num_seeds)),
            "noise_std": args.noise_std,
            "odometry_rotation_deg": args.odometry_rotation_deg,
            "odometry_translation": args.odometry_translation,
            "loop_rotation_deg": args.loop_rotation_deg,
            "loop_translation": args.loop_translation,
        },
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "summary": summary,
        "per_seed": per_seed,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(output, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
