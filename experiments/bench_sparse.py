"""Sparse vs dense factorization of the reduced pose system on closed-loop ICP-SLAM scenes.

For each m of ``--poses``, a :func:`torchslam.data.loop.make_loop_scene` problem (m poses,
``--points-per-frame`` points born per frame, each seen by ``--window`` successive frames,
scalar observation weights 1/σ²) with the odometry and loop-closure measurements as
:class:`torchslam.RelativePoseTerm` (information from the scene's ``odometry_information()`` /
``loop_information()``), started from the chained odometry T_{i+1,0} = Z_{i,i+1}⁻¹ T_i0 and
the points averaged over their views (or the ground-truth points, ``--points ground-truth``),
is solved by :func:`torchslam.solve_tensors` with ``reduced_solver="sparse"`` always and
``"dense"`` up to ``--dense-max-poses``. The table gives the sizes (6m, E observations,
n points), the reduced solver, what ``"auto"`` would pick with the default
``dense_max_variables``, iterations, whole-solve seconds (the sparse pattern and ordering
included), seconds per iteration, final cost, status and the largest pose difference to the
sparse solution.

Then, at m = ``--factor-poses``, the real reduced matrix S (Schur complement of the damped
system at the initial guess, captured from :meth:`torchslam.solver.plan.LinearPlan.factorize`) is
factored once sparsely (:meth:`BlockPattern.factor`: SuperLU in the precomputed
fill-reducing order) and once densely (``torch.linalg.cholesky`` of S assembled as a dense
6m × 6m matrix), and the speed-up is printed; both factors solve the same right-hand side as a
cross-check.

Threads: ``--threads`` sets ``torch.set_num_threads`` (default 1). SciPy's SuperLU is
single-threaded code (it may call the BLAS SciPy links; pin that with OPENBLAS_NUM_THREADS).

Run from the repository root (writes out/bench_sparse.json):

    .venv/bin/python experiments/bench_sparse.py [--poses 100 250 500 1000 2500]
        [--dense-max-poses 1000] [--factor-poses 2500] [--threads 1]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import platform
import statistics
import time
from pathlib import Path

import numpy as np
import scipy.sparse
import torch

import torchslam
from torchslam import PointMapProblem, RelativePoseTerm, SolverConfig
from torchslam.data.loop import make_loop_scene
from torchslam.initialization import average_points, chain_relative_poses
from torchslam.lie import se3
from torchslam.solver.linearize import linearize, whitening_factors
from torchslam.solver.plan import LinearPlan, choose_reduced_solver
from torchslam.solver.sparse import BlockPattern

OUT = Path("out") / "bench_sparse.json"  # under the working directory


def build_problem(
    num_poses: int, points_per_frame: int, window: int, points: str, seed: int
) -> PointMapProblem:
    """The loop problem of the module doc (B = 1)."""
    loop = make_loop_scene(
        num_poses=num_poses, points_per_frame=points_per_frame, window=window, seed=seed
    )
    s = loop.scene
    poses = chain_relative_poses(se3.inverse(loop.odometry))[None]
    if points == "ground-truth":
        X = s.points_gt.clone()
    else:
        X = average_points(poses, s.pose_index, s.point_index, s.observations, s.num_points)
    K = loop.odometry.shape[0]
    terms = [
        RelativePoseTerm(
            loop.odometry_pairs,
            loop.odometry,
            information=loop.odometry_information().expand(K, 6, 6),
        ),
        RelativePoseTerm(loop.loop_pairs, loop.loop, information=loop.loop_information()[None]),
    ]
    return PointMapProblem(
        poses,
        X,
        s.pose_index,
        s.point_index,
        s.observations,
        weights=torch.full_like(s.observations[..., 0], loop.noise_std**-2),
        terms=terms,
    )


def run_solve(problem: PointMapProblem, reduced_solver: str, max_iterations: int) -> dict:
    config = SolverConfig(reduced_solver=reduced_solver, max_iterations=max_iterations)
    start = time.perf_counter()
    result = torchslam.solve_tensors(problem.pose_tangent, problem.points, problem.data, config)
    seconds = time.perf_counter() - start
    iterations = int(result.iterations[0])
    return {
        "reduced_solver": reduced_solver,
        "iterations": iterations,
        "seconds": seconds,
        "seconds_per_iteration": seconds / max(iterations, 1),
        "initial_cost": float(result.initial_cost[0]),
        "final_cost": float(result.final_cost[0]),
        "status": result.status[0].name,
        "converged": bool(result.converged[0]),
        "_poses": result.poses,
    }


def factor_timings(problem: PointMapProblem, repeats: int) -> dict:
    """One sparse factorization of the real S vs one dense Cholesky of it (module doc)."""
    data = problem.data
    m = data.num_poses
    xi, X = problem.pose_tangent.detach(), problem.points.detach()
    lin = linearize(xi, X, data, whitening_factors(data))
    start = time.perf_counter()
    plan = LinearPlan.build(data, SolverConfig(reduced_solver="sparse"))
    symbolic = time.perf_counter() - start

    # Capture the values of S's unique blocks where factorize hands them to the pattern.
    captured = {}
    original = BlockPattern.factor

    def capture(self: BlockPattern, values: torch.Tensor, **options):
        captured["values"] = values.detach().clone()
        return original(self, values, **options)

    lam = torch.full((1,), 1e-4, dtype=xi.dtype)  # the solver's initial λ
    BlockPattern.factor = capture
    try:
        start = time.perf_counter()
        plan.factorize(lin, lam)
        whole_factorize = time.perf_counter() - start
    finally:
        BlockPattern.factor = original
    values = captured["values"]
    pattern = plan.reduced.pattern

    sparse_seconds = []
    for _ in range(repeats):
        start = time.perf_counter()
        factor = pattern.factor(values)
        sparse_seconds.append(time.perf_counter() - start)
    assert bool(factor.ok.all()), "the sparse factorization failed"
    lu = factor.factors[0]

    # S as a dense matrix, in the original order of the unknowns.
    layout = pattern.layouts[0]
    size = 6 * m
    data_array = values.numpy().reshape(-1, 36)[layout.start : layout.stop].ravel()[layout.source]
    permuted = scipy.sparse.csc_matrix((data_array, layout.indices, layout.indptr), (size, size))
    nonzeros = permuted.nnz
    position = torch.from_numpy(layout.position)
    S = torch.from_numpy(permuted.toarray())[position][:, position]
    del permuted
    start = time.perf_counter()
    L = torch.linalg.cholesky(S)
    dense_seconds = time.perf_counter() - start

    rhs = torch.randn(1, size, generator=torch.Generator().manual_seed(0), dtype=S.dtype)
    x_dense = torch.cholesky_solve(rhs.T, L).T
    x_sparse = factor.solve(rhs)
    agreement = float((x_sparse - x_dense).abs().max() / x_dense.abs().max())
    residual = float((S @ x_sparse.T - rhs.T).abs().max() / rhs.abs().max())
    return {
        "num_poses": m,
        "size": size,
        "unique_blocks": pattern.num_unique,
        "nonzeros": nonzeros,
        "density": nonzeros / size**2,
        "factor_nonzeros": int(lu.L.nnz + lu.U.nnz),
        "symbolic_seconds": symbolic,
        "factorize_seconds": whole_factorize,
        "sparse_factor_seconds": statistics.median(sparse_seconds),
        "sparse_factor_runs": sparse_seconds,
        "dense_cholesky_seconds": dense_seconds,
        "speedup": dense_seconds / statistics.median(sparse_seconds),
        "solution_relative_difference": agreement,
        "sparse_relative_residual": residual,
    }


def _warm_up() -> None:
    problem = build_problem(12, 4, 3, "average", 0)
    for reduced in ("sparse", "dense"):
        run_solve(problem, reduced, 2)


def implicit_timings(
    num_poses: int, points_per_frame: int, window: int, points: str, seed: int, reduced: str
) -> dict:
    """Forward solve and implicit backward (both Hessian options) of a loss on the solved
    positions w.r.t. the odometry measurements and the observations."""
    out = {"num_poses": num_poses, "reduced_solver": reduced}
    for hessian in ("gauss_newton", "exact"):
        problem = build_problem(num_poses, points_per_frame, window, points, seed)
        data = problem.data
        odometry = data.terms[0].constants["measurements"].detach().requires_grad_(True)
        observations = data.observations.detach().requires_grad_(True)
        terms = (data.terms[0].replace_tensors({"constants.measurements": odometry}),)
        data = dataclasses.replace(data, observations=observations, terms=terms + data.terms[1:])
        config = SolverConfig(reduced_solver=reduced, max_iterations=300)
        start = time.perf_counter()
        result = torchslam.solve_differentiable(
            problem.pose_tangent.detach(),
            problem.points.detach(),
            data,
            config,
            implicit=torchslam.ImplicitConfig(hessian=hessian),
        )
        forward = time.perf_counter() - start
        loss = (result.poses[..., :3, 3] ** 2).sum()
        start = time.perf_counter()
        g_odometry, g_observations = torch.autograd.grad(loss, (odometry, observations))
        backward = time.perf_counter() - start
        out[hessian] = {
            "forward_seconds": forward,
            "backward_seconds": backward,
            "gradient_norm": float(
                torch.sqrt(g_odometry.square().sum() + g_observations.square().sum())
            ),
        }
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, nargs="+", default=[100, 250, 500, 1000, 2500])
    parser.add_argument(
        "--dense-max-poses", type=int, default=1000, help="largest m solved densely too (1000)"
    )
    parser.add_argument(
        "--factor-poses", type=int, default=2500, help="m of the one-factorization timing"
    )
    parser.add_argument("--points-per-frame", type=int, default=10)
    parser.add_argument("--window", type=int, default=4, help="frames that see each point")
    parser.add_argument("--points", choices=("average", "ground-truth"), default="average")
    parser.add_argument(
        "--max-iterations", type=int, default=300, help="(300: m = 2500 needs ~170 from odometry)"
    )
    parser.add_argument("--repeats", type=int, default=3, help="sparse factorizations timed")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (1)")
    parser.add_argument(
        "--implicit-poses", type=int, default=500, help="m of the implicit-backward timing"
    )
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    _warm_up()

    rows = []
    header = (
        f"{'m':>5} {'6m':>6} {'E':>7} {'n':>6} {'solver':>6} {'auto':>6} {'iters':>5} "
        f"{'solve s':>8} {'s/iter':>7} {'final cost':>12} {'status':>20} {'|Δpose|':>8}"
    )
    print(
        f"loop scenes: {args.points_per_frame} points per frame, window {args.window}, "
        f"points {args.points}, torch threads {torch.get_num_threads()}"
    )
    print(header)
    print("-" * len(header))
    for m in args.poses:
        problem = build_problem(m, args.points_per_frame, args.window, args.points, args.seed)
        data = problem.data
        E, n = int(data.valid.sum()), data.num_points
        auto = choose_reduced_solver(data, "auto", SolverConfig().dense_max_variables)
        solvers = ["sparse"] + (["dense"] if m <= args.dense_max_poses else [])
        reference = None
        for reduced in solvers:
            row = run_solve(problem, reduced, args.max_iterations)
            poses = row.pop("_poses")
            if reference is None:
                reference = poses
            row["max_pose_difference_to_sparse"] = float((poses - reference).abs().max())
            row.update({"num_poses": m, "size": 6 * m, "observations": E, "points": n})
            row["auto_picks"] = auto
            rows.append(row)
            print(
                f"{m:5d} {6 * m:6d} {E:7d} {n:6d} {reduced:>6} {auto:>6} {row['iterations']:5d} "
                f"{row['seconds']:8.2f} {row['seconds_per_iteration']:7.3f} "
                f"{row['final_cost']:12.6g} {row['status']:>20} "
                f"{row['max_pose_difference_to_sparse']:8.1e}",
                flush=True,
            )

    for m in args.poses:
        by = {r["reduced_solver"]: r for r in rows if r["num_poses"] == m}
        if "dense" in by:
            ratio = by["dense"]["seconds_per_iteration"] / by["sparse"]["seconds_per_iteration"]
            print(f"m = {m}: the sparse reduced solver is {ratio:.1f}x faster per iteration")

    print(f"\none factorization of the reduced matrix S at m = {args.factor_poses}:")
    problem = build_problem(
        args.factor_poses, args.points_per_frame, args.window, args.points, args.seed
    )
    factor = factor_timings(problem, args.repeats)
    print(
        f"  S: {factor['size']} × {factor['size']}, {factor['unique_blocks']} unique 6×6 blocks, "
        f"{factor['nonzeros']} nonzeros (density {factor['density']:.2e}); "
        f"L + U: {factor['factor_nonzeros']} nonzeros"
    )
    print(
        f"  sparse (BlockPattern.factor, SuperLU, mmd order): "
        f"{factor['sparse_factor_seconds']:.4f} s (median of {args.repeats}); "
        f"symbolic (SparseSchur.build) {factor['symbolic_seconds']:.3f} s; "
        f"whole factorize (Schur complement + factor) {factor['factorize_seconds']:.3f} s"
    )
    print(
        f"  dense  (torch.linalg.cholesky, {torch.get_num_threads()} thread(s)): "
        f"{factor['dense_cholesky_seconds']:.2f} s"
    )
    print(
        f"  speed-up dense / sparse: {factor['speedup']:.0f}x; solutions agree to "
        f"{factor['solution_relative_difference']:.1e} (relative), sparse residual "
        f"{factor['sparse_relative_residual']:.1e}"
    )

    print(f"\nimplicit backward (solve_differentiable) at m = {args.implicit_poses}:")
    implicit = [
        implicit_timings(
            args.implicit_poses,
            args.points_per_frame,
            args.window,
            args.points,
            args.seed,
            reduced,
        )
        for reduced in ("sparse", "dense")
    ]
    for row in implicit:
        for hessian in ("gauss_newton", "exact"):
            t = row[hessian]
            print(
                f"  {row['reduced_solver']:>6} {hessian:>12}: "
                f"forward {t['forward_seconds']:.2f} s, backward {t['backward_seconds']:.2f} s, "
                f"|gradient| {t['gradient_norm']:.10g}"
            )

    report = {
        "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "platform": platform.platform(),
        "solves": rows,
        "factorization": factor,
        "implicit": implicit,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2, allow_nan=True))
    print(f"\nwrote {args.out}")
    ok = all(r["converged"] for r in rows) and math.isfinite(factor["speedup"])
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
