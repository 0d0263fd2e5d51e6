"""Issue 16: torchslam vs Theseus (LM + CHOLMOD) on the cases of ``torchslam bench``.

Cases (the same synthetic problems as :func:`torchslam.benchmark.build`: same seeds, same
drifted-odometry start): S (m = 10 poses, n = 200 points, 1,400 observations), M (50 poses,
1,000 points, 15,000), BATCH (64 × S), TRAIN (BATCH forward + implicit backward to the
observations, a loss on the poses as in :func:`torchslam.benchmark.training_step`) and, with
``--large``, L (200 poses, 5,000 points, 100k observations: minutes for Theseus).

How it runs: both libraries in ONE process of the peers venv (``/work/peers-venv``, torch
2.13 as in the project venv), torchslam imported from this checkout (``PYTHONPATH``). Started
from any other interpreter, the script re-runs itself there with ``PYTHONPATH`` and the
``LD_LIBRARY_PATH`` that CHOLMOD (scikit-sparse) needs; when Theseus or CHOLMOD cannot be
imported it prints one ``skipped:`` line and exits 0. Theseus is never a dependency.

torchslam is timed exactly as ``torchslam bench`` times it (:func:`torchslam.benchmark.run_case`:
the whole solve including problem construction, default ``SolverConfig()``, after a warm-up
run). The two libraries alternate, one torchslam run and one Theseus run per round, and the
table gives the medians over the rounds (``--repeats``).

Theseus is used as a Theseus user would: one ``th.SE3`` variable per pose (pose 0, the gauge,
is an auxiliary variable, not optimized), one ``th.Point3`` per point, one cost function per
(pose, point) pair, r = z − T·X, written as a custom ``th.CostFunction`` with analytic
Jacobians from ``SE3.transform_from`` (faster than ``th.AutoDiffCostFunction`` and what
Theseus's own measurement costs do), vectorized by ``th.TheseusLayer``. The 64 problems of
BATCH/TRAIN go into Theseus's batch dimension, which shares one sparsity pattern across the
batch: the cost functions are the union of the problems' (pose, point) pairs (2,000 for 1,400
observations per problem) and a per-problem ``th.ScaleCostWeight`` of 0 switches off the pairs
a problem does not observe. Solver: ``th.LevenbergMarquardt`` with ``th.CholmodSparseSolver``
(which supports only a fixed scalar damping λ·I, no adaptive damping), float64, at most 100
iterations, relative and absolute error tolerances 1e-10 (torchslam: ``function_tolerance``
1e-10, ``max_iterations`` 100). TRAIN uses ``backward_mode="implicit"`` (Theseus's Gauss-Newton
implicit gradient) with the observations as differentiable inputs.

Theseus times: "setup" builds the objective, optimizer and layer (vectorization and CHOLMOD's
symbolic analysis included) once per case; "solve" is one ``TheseusLayer.forward`` from the
initial values (plus the loss and backward for TRAIN), after one warm-up forward.
The ratio is Theseus solve / torchslam whole solve, i.e. it leaves Theseus's setup out (in a
training loop the layer is built once). Costs are ½ Σ ‖z − T·X‖² over the observations,
evaluated by the same function on both solutions. For TRAIN Theseus's gradient with respect to
the observations is compared with torchslam's (relative norm of the difference), both with
torchslam's default implicit backward (exact Hessian: they differ at the level of the
residuals) and with ``ImplicitConfig(hessian="gauss_newton")``, Theseus's choice.

The machine may be shared: the load average is printed before and after.

Usage: python experiments/bench_theseus.py [--cases S M BATCH TRAIN] [--large] [--threads 1 2]
       [--repeats N] [--peers-python PATH]
"""

from __future__ import annotations

import argparse
import importlib
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

PEERS_PYTHON = Path("/work/peers-venv/bin/python")
SUITESPARSE = Path("/work/peers-venv/suitesparse/usr/lib/x86_64-linux-gnu")
CHILD_FLAG = "TORCHSLAM_BENCH_THESEUS_CHILD"
REPEATS = {"S": 5, "M": 3, "L": 1, "BATCH": 3, "TRAIN": 3}
DAMPING = 1e-4  # Theseus LM with CHOLMOD: fixed λ·I (torchslam: λ₀ = 1e-4, adaptive)
MAX_ITERATIONS = 100
TOLERANCE = 1e-10


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--cases", nargs="+", default=["S", "M", "BATCH", "TRAIN"], choices=list(REPEATS)
    )
    parser.add_argument("--large", action="store_true", help="add case L (slow in Theseus)")
    parser.add_argument("--threads", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--repeats", type=int, default=None, help="runs per case (median)")
    parser.add_argument("--peers-python", type=Path, default=PEERS_PYTHON)
    args = parser.parse_args(argv)
    if args.large and "L" not in args.cases:
        args.cases.append("L")
    missing = _theseus_missing()
    if missing:
        if os.environ.get(CHILD_FLAG) or not args.peers_python.exists():
            print(f"bench_theseus: skipped: {missing}")
            return 0
        return _rerun_in_peers_venv(args.peers_python, argv)
    return run(args)


def _theseus_missing() -> str | None:
    """None when Theseus and its CHOLMOD solver import here; else the reason, one line."""
    try:
        for module in ("theseus", "sksparse.cholmod"):  # Theseus first: the clearer message
            importlib.import_module(module)
    except (ImportError, OSError) as error:
        return f"theseus with CHOLMOD is not importable ({type(error).__name__}: {error})"
    return None


def _rerun_in_peers_venv(python: Path, argv: list[str] | None) -> int:
    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ)
    env[CHILD_FLAG] = "1"
    env["PYTHONPATH"] = os.pathsep.join(filter(None, (str(root), env.get("PYTHONPATH"))))
    env["LD_LIBRARY_PATH"] = os.pathsep.join(
        filter(None, (str(SUITESPARSE), env.get("LD_LIBRARY_PATH")))
    )
    command = [
        str(python),
        str(Path(__file__).resolve()),
        *(sys.argv[1:] if argv is None else argv),
    ]
    return subprocess.run(command, env=env, check=False).returncode


# ---------------------------------------------------------------------------------- Theseus


def _cost_function_class(th):
    """The per-observation cost r = z − T·X as a th.CostFunction with analytic Jacobians."""

    class PointObservation(th.CostFunction):
        """r = z − T·X (3,) for one (pose, point) pair. ``pose_fixed``: T is an auxiliary
        variable (the gauge pose), else an optimization variable."""

        def __init__(self, pose, point, observation, weight, pose_fixed: bool, name=None):
            super().__init__(weight, name=name)
            self.pose, self.point, self.observation = pose, point, observation
            self.pose_fixed = pose_fixed
            if pose_fixed:
                self.register_optim_vars(["point"])
                self.register_aux_vars(["pose", "observation"])
            else:
                self.register_optim_vars(["pose", "point"])
                self.register_aux_vars(["observation"])

        def error(self) -> torch.Tensor:
            return self.observation.tensor - self.pose.transform_from(self.point).tensor

        def jacobians(self) -> tuple[list[torch.Tensor], torch.Tensor]:
            blocks: list[torch.Tensor] = []
            moved = self.pose.transform_from(self.point, jacobians=blocks)
            error = self.observation.tensor - moved.tensor
            if self.pose_fixed:
                return [-blocks[1]], error
            return [-blocks[0], -blocks[1]], error

        def dim(self) -> int:
            return 3

        def _copy_impl(self, new_name=None):
            return PointObservation(
                self.pose.copy(),
                self.point.copy(),
                self.observation.copy(),
                self.weight.copy(),
                self.pose_fixed,
                name=new_name,
            )

    return PointObservation


class TheseusProblem:
    """A scene's problems as one batched Theseus objective, optimizer and layer.

    Pairs: the union over the batch of the observed (pose, point) pairs, k = 0…P−1;
    ``pair_of`` (B, E) gives each valid observation's pair (−1 for invalid entries).
    """

    def __init__(self, scene, init):
        import theseus as th

        self.th = th
        B, m, n = scene.batch_size, scene.num_poses, scene.num_points
        valid = scene.valid
        key = scene.pose_index * n + scene.point_index
        pairs = torch.unique(key[valid])
        self.pair_pose, self.pair_point = pairs // n, pairs % n
        self.pair_of = torch.where(valid, torch.searchsorted(pairs, key), -1)
        P = len(pairs)
        b_index = torch.arange(B)[:, None].expand_as(key)[valid]
        self.b_index, self.k_index = b_index, self.pair_of[valid]
        observed = torch.zeros(B, P, dtype=torch.bool)
        observed[self.b_index, self.k_index] = True
        self.scene, self.init, self.B, self.m, self.n, self.P = scene, init, B, m, n, P

        dtype = torch.float64
        objective = th.Objective(dtype=dtype)
        self.poses = [
            th.SE3(tensor=init.poses[:, i, :3, :].clone(), name=f"T{i}") for i in range(m)
        ]
        self.points = [th.Point3(tensor=init.points[:, j].clone(), name=f"X{j}") for j in range(n)]
        observations = self.scatter(scene.observations)
        unit = th.ScaleCostWeight(torch.ones(1, 1, dtype=dtype), name="unit")
        PointObservation = _cost_function_class(th)
        for k in range(P):
            i, j = int(self.pair_pose[k]), int(self.pair_point[k])
            z = th.Variable(observations[:, k].clone(), name=f"z{k}")
            if bool(observed[:, k].all()):
                weight = unit
            else:
                scale = th.Variable(observed[:, k, None].to(dtype), name=f"w{k}")
                weight = th.ScaleCostWeight(scale, name=f"weight{k}")
            objective.add(
                PointObservation(self.poses[i], self.points[j], z, weight, i == 0, name=f"r{k}")
            )
        self.optimizer = th.LevenbergMarquardt(
            objective,
            linear_solver_cls=th.CholmodSparseSolver,
            linearization_cls=th.SparseLinearization,
            max_iterations=MAX_ITERATIONS,
            abs_err_tolerance=TOLERANCE,
            rel_err_tolerance=TOLERANCE,
        )
        self.layer = th.TheseusLayer(self.optimizer)
        self.objective = objective

    def scatter(self, observations: torch.Tensor) -> torch.Tensor:
        """(B, E, 3) observations → (B, P, 3) per pair (0 where a problem lacks the pair)."""
        out = observations.new_zeros(self.B, self.P, 3)
        out = out.index_put((self.b_index, self.k_index), observations[self.scene.valid])
        return out

    def inputs(self, observations: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """The layer's inputs: initial poses (1…m−1) and points; observations if given."""
        tensors = {f"T{i}": self.init.poses[:, i, :3, :].clone() for i in range(1, self.m)}
        tensors.update({f"X{j}": self.init.points[:, j].clone() for j in range(self.n)})
        if observations is not None:
            # unbind: one backward node for all pairs (P slices would each materialize a
            # full-size gradient in the backward)
            per_pair = self.scatter(observations).unbind(1)
            tensors.update({f"z{k}": z for k, z in enumerate(per_pair)})
        return tensors

    def solve(self) -> tuple[dict, object]:
        with torch.no_grad():
            return self.layer.forward(self.inputs(), optimizer_kwargs={"damping": DAMPING})

    def training_step(self, target: torch.Tensor) -> tuple[dict, object, torch.Tensor, float]:
        """Forward (implicit backward mode) with the observations as the differentiable input,
        the loss Σ ‖Log(T_i) − ξ*_i‖² of training_step, and its backward. Returns the solution,
        info, the observations' gradient (B, E, 3) and the backward's seconds."""
        observations = self.scene.observations.clone().requires_grad_(True)
        solution, info = self.layer.forward(
            self.inputs(observations),
            optimizer_kwargs={"damping": DAMPING, "backward_mode": "implicit"},
        )
        loss = (pose_tangent(self, solution) - target).square().sum()
        t = time.perf_counter()
        loss.backward()
        return solution, info, observations.grad, time.perf_counter() - t


def pose_matrices(problem: TheseusProblem, solution: dict) -> torch.Tensor:
    """(B, m, 4, 4) poses of a Theseus solution (pose 0: the fixed gauge)."""
    rows = [problem.init.poses[:, 0, :3, :]]
    rows += [solution[f"T{i}"] for i in range(1, problem.m)]
    top = torch.stack(rows, dim=1)
    bottom = problem.init.poses[:, :, 3:, :].to(top.dtype)
    return torch.cat((top, bottom), dim=2)


def pose_tangent(problem: TheseusProblem, solution: dict) -> torch.Tensor:
    from torchslam.lie import se3

    return se3.log(pose_matrices(problem, solution))


def point_cost(scene, poses: torch.Tensor, points: torch.Tensor) -> float:
    """½ Σ ‖z − T_i X_j‖² over the valid observations of all problems."""
    from torchslam.lie import se3

    B = scene.batch_size
    b = torch.arange(B)[:, None].expand_as(scene.pose_index)
    T = poses[b, scene.pose_index]
    X = points[b, scene.point_index]
    r = scene.observations - se3.act(T, X)
    return float(0.5 * r[scene.valid].square().sum())


# ---------------------------------------------------------------------------------- cases


def run_pair(case: str, repeats: int) -> tuple[dict, dict]:
    """Both libraries on ``case``, alternating: each round runs torchslam's timed solve
    (:func:`torchslam.benchmark.run_case` with one repeat after its own warm-up run, i.e. the
    measurement of ``torchslam bench``) and then one Theseus solve; medians over the rounds.
    Theseus's layer is built (timed as setup) and warmed up once before the rounds."""
    from torchslam.benchmark import build, run_case, scene_tangent

    scene, init, _ = build(case)
    target = scene_tangent(scene)
    t = time.perf_counter()
    problem = TheseusProblem(scene, init)
    setup = time.perf_counter() - t

    def theseus_once():
        if case == "TRAIN":
            return problem.training_step(target)
        return (*problem.solve(), None, 0.0)

    theseus_once()  # warm-up
    ours_times, ours_backward, theirs_times, theirs_backward = [], [], [], []
    for _ in range(repeats):
        timed = run_case(case, 1, rate=1.0, with_scipy=False)
        ours_times.append(timed["median_s"])
        ours_backward.append(timed.get("backward_s", 0.0))
        t = time.perf_counter()
        solution, info, grad, backward_s = theseus_once()
        theirs_times.append(time.perf_counter() - t)
        theirs_backward.append(backward_s)
    poses = pose_matrices(problem, solution).detach()
    points = torch.stack([solution[f"X{j}"] for j in range(problem.n)], dim=1).detach()
    theirs = {
        "setup_s": setup,
        "solve_s": statistics.median(theirs_times),
        "backward_s": statistics.median(theirs_backward),
        "iterations": int(info.converged_iter.max()),
        "status": sorted({str(s).split(".")[-1] for s in info.status}),
        "cost": point_cost(scene, poses, points),
        "pairs": problem.P,
    }
    ours = torchslam_solution(case)
    ours["solve_s"] = statistics.median(ours_times)
    ours["backward_s"] = statistics.median(ours_backward)
    ours["iterations"] = timed["iterations"]
    if case == "TRAIN":
        theirs["grad"] = grad[scene.valid]
    return ours, theirs


def torchslam_solution(case: str) -> dict:
    """Cost (and for TRAIN the observations' gradient, as training_step computes it) of
    torchslam's solution, untimed."""
    import torchslam as ts
    from torchslam.benchmark import build, training_step

    scene, init, loss = build(case)
    row = {}
    for hessian in ("exact", "gauss_newton") if case == "TRAIN" else ():
        observations = scene.observations.clone().requires_grad_(True)
        result, _ = training_step(scene, init, hessian, observations)
        row[f"grad_{hessian}"] = observations.grad[scene.valid]
    if case != "TRAIN":
        problem = ts.PointMapProblem.from_scene(scene, init.poses, init.points, loss=loss)
        result = ts.solve(problem)
    row["cost"] = point_cost(scene, result.poses.detach(), result.points.detach())
    return row


def run(args: argparse.Namespace) -> int:
    import theseus as th

    import torchslam

    print(
        f"torch {torch.__version__}, theseus {th.__version__}, torchslam from "
        f"{Path(torchslam.__file__).parent}; load average before: {_load()}"
    )
    rows = []
    for threads in args.threads:
        torch.set_num_threads(threads)
        for case in args.cases:
            repeats = args.repeats or REPEATS[case]
            ours, theirs = run_pair(case, repeats)
            row = {"case": case, "threads": threads, "ours": ours, "theirs": theirs}
            for hessian in ("exact", "gauss_newton") if case == "TRAIN" else ():
                reference = ours[f"grad_{hessian}"]
                difference = (theirs["grad"] - reference).norm() / reference.norm()
                row[f"grad_diff_{hessian}"] = float(difference)
            rows.append(row)
            print(_line(row), flush=True)
    print(f"load average after: {_load()}\n")
    print(
        f"{'case':6} {'thr':>3} {'torchslam':>10} {'Theseus':>9} {'ratio':>7} "
        f"{'Th. setup':>9} {'iters ts/Th':>11} {'cost torchslam':>15} {'cost Theseus':>15}"
    )
    for r in rows:
        ours, theirs = r["ours"], r["theirs"]
        print(
            f"{r['case']:6} {r['threads']:3d} {_seconds(ours['solve_s']):>10} "
            f"{_seconds(theirs['solve_s']):>9} {theirs['solve_s'] / ours['solve_s']:6.1f}× "
            f"{_seconds(theirs['setup_s']):>9} {ours['iterations']:>5}/{theirs['iterations']:<5} "
            f"{ours['cost']:15.10g} {theirs['cost']:15.10g}"
        )
    print(
        "ratio = Theseus solve (layer forward; for TRAIN + loss + backward) / torchslam whole "
        "solve (problem construction included); Theseus setup (objective, optimizer, layer) "
        "excluded from the ratio."
    )
    return 0


def _line(r: dict) -> str:
    ours, theirs = r["ours"], r["theirs"]
    text = (
        f"{r['case']} ({r['threads']} thread{'s' if r['threads'] > 1 else ''}): torchslam "
        f"{_seconds(ours['solve_s'])} ({ours['iterations']} it., cost {ours['cost']:.10g}); "
        f"Theseus {_seconds(theirs['solve_s'])} + setup {_seconds(theirs['setup_s'])} "
        f"({theirs['iterations']} it., {theirs['pairs']} cost functions, cost "
        f"{theirs['cost']:.10g}, status {','.join(theirs['status'])})"
    )
    if "grad_diff_exact" in r:
        text += (
            f"; backward torchslam {_seconds(ours['backward_s'])}, Theseus "
            f"{_seconds(theirs['backward_s'])}; Theseus's observation gradient vs torchslam's "
            f"(relative norm of the difference): {r['grad_diff_exact']:.2e} with torchslam's "
            f"default exact-Hessian implicit backward, {r['grad_diff_gauss_newton']:.2e} with "
            "its Gauss-Newton one"
        )
    return text


def _seconds(value: float) -> str:
    return f"{value * 1e3:.1f}ms" if value < 1 else f"{value:.2f}s"


def _load() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "unknown"


if __name__ == "__main__":
    sys.exit(main())
