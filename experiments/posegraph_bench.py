"""Pose-graph Levenberg-Marquardt on the shared benchmarks: optimum, SE-Sync objective, wall time.

For sphere2500 and parking-garage (the data set ``posegraph``, ``torchslam.data.fetch``; a
missing file is skipped with a message), from two initializations:

- "odometry": the file's vertex values (the odometry chain as recorded; what GTSAM starts from),
- "chordal": :func:`torchslam.posegraph.initialization.chordal_initialization` (its own time is
  printed separately, the solve time excludes it),

it runs :func:`torchslam.posegraph.solve.solve_pose_graph` (default config: sparse SuperLU path,
vertex 0 fixed) and prints the standard cost ½ Σ rᵀΩr (r = Log(Z⁻¹ T_i⁻¹ T_j), Ω in (ω, v)
order), whether it matches GTSAM's LM value to 4 significant digits, the SE-Sync objective
(Rosen et al. IJRR 2019, eq. 12), iterations, status and the median wall time of ``--repeats``
solves with its split into linearization and linear solves.

References (issue 7, measured on our machine): GTSAM's LM reaches ½χ² = 675.70 on sphere2500 in
1.27 s and 0.63419 on parking-garage in 0.55 s; its solutions score 1730.0 and 1.2673 on the
SE-Sync objective, whose certified optima are 1687 and 1.263. If ``gtsam`` is importable, its
LM is run on the same files for a side-by-side time (it is not a dependency; skipped otherwise).

Issue 14 adds (each section is skipped with a message when its file or peer is missing):

- ``--objective sesync`` rows: LM on the SE-Sync objective from the chordal start, its value
  against the certified optima f* (4 significant digits) and SE-Sync's certificate
  (:func:`torchslam.posegraph.certify`: certified yes/no, λ_min, η);
- MIT.g2o (real, 2D): chi2 and SE-Sync objectives from the file's vertices and from chordal,
  with the certificate of the 2D SE-Sync optimum;
- synthetic graphs (:func:`torchslam.data.posegraph.make_pose_graph`: a 2,000-pose torus and a
  13³ = 2,197-pose grid, σ_R = 0.15 rad, σ_t = 0.2, loop-closure probability 0.5): file
  (odometry) start vs chordal start, and the same graphs with one planted wrong loop closure;
- whole-process wall time (start-up, reading, initialization, solve, exit) of
  ``python -m torchslam posegraph FILE --init chordal`` against a GTSAM LM script (readG2o,
  prior on vertex 0, LM from the file's vertices) run by the peers' Python
  (``$TORCHSLAM_PEERS_PYTHON`` or ../peers-venv/bin/python), each pinned to 1 and to 2 CPUs
  with ``taskset`` (and OMP/MKL threads set to match).

Run from the repository root:  .venv/bin/python experiments/posegraph_bench.py [--repeats 3]
[--threads 1] [--linear-solver auto] [--skip-synthetic] [--skip-process]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

import torchslam
from torchslam.data import fetch
from torchslam.data.posegraph import make_pose_graph
from torchslam.io import g2o
from torchslam.posegraph import certify, initialization, objectives
from torchslam.posegraph.solve import PoseGraphSolverConfig, solve_pose_graph

# name: (GTSAM LM ½χ², GTSAM LM seconds, GTSAM SE-Sync objective, certified SE-Sync optimum)
REFERENCE = {
    "sphere2500": (675.70, 1.27, 1730.0, 1687.0),
    "parking-garage": (0.63419, 0.55, 1.2673, 1.263),
}


def _same_4_digits(value: float, reference: float) -> bool:
    return f"{value:.4g}" == f"{reference:.4g}"


def _gtsam_lm(path: Path) -> tuple[float, float] | None:
    """GTSAM's LM from the file's vertices with pose 0 fixed by a tight prior: (½χ², seconds).

    None when gtsam is not importable. Written against GTSAM 4.2's Python API (readG2o,
    PriorFactorPose3, LevenbergMarquardtOptimizer); graph.error is ½ Σ rᵀΩr with the log-map
    residual, the quantity torchslam minimizes.
    """
    try:
        import gtsam
    except ImportError:
        return None
    graph, initial = gtsam.readG2o(str(path), True)
    noise = gtsam.noiseModel.Diagonal.Variances(np.full(6, 1e-6))
    graph.add(gtsam.PriorFactorPose3(0, initial.atPose3(0), noise))
    params = gtsam.LevenbergMarquardtParams()
    start = time.perf_counter()
    result = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
    seconds = time.perf_counter() - start
    return graph.error(result), seconds


def _solve_as_terms(graph: g2o.PoseGraph) -> tuple[float, int, str, float]:
    """(½χ², iterations, status, seconds) of torchslam.solve on the graph as a term."""
    N = graph.num_vertices
    fixed = torch.zeros(1, N, dtype=torch.bool)
    fixed[0, graph.fixed if graph.fixed.numel() else 0] = True
    none = torch.zeros(1, 0, dtype=torch.int64)
    empty = graph.poses.new_zeros(1, 0, 3)
    tick = time.perf_counter()
    problem = torchslam.PointMapProblem(
        graph.frame_poses()[None],
        empty,
        none,
        none,
        empty,
        fixed_poses=fixed,
        terms=[graph.relative_pose_term()],
    )
    result = torchslam.solve(problem, torchslam.SolverConfig(initial_lambda=1e-9))
    seconds = time.perf_counter() - tick
    return float(result.final_cost[0]), int(result.iterations[0]), result.status[0].name, seconds


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3, help="solves per row (median time)")
    parser.add_argument(
        "--linear-solver", choices=["auto", "sparse", "dense"], default="auto", help="(auto)"
    )
    # One thread by default: the per-edge tensors are small and SuperLU is single-threaded;
    # on this shared 2-core machine a second OpenMP thread made the linearization up to 25×
    # slower under load (busy-waiting on a descheduled thread).
    parser.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (1)")
    parser.add_argument("--skip-synthetic", action="store_true", help="skip the synthetic graphs")
    parser.add_argument("--skip-process", action="store_true", help="skip whole-process times")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    config = PoseGraphSolverConfig(linear_solver=args.linear_solver)
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} torch threads; "
        f"config: initial λ {config.initial_lambda:g}, {config.damping} damping, function "
        f"tolerance {config.function_tolerance:g}, ordering {config.ordering}; "
        f"median of {args.repeats} solves; load average {os.getloadavg()[0]:.2f} on "
        f"{os.cpu_count()} CPUs"
    )
    header = (
        f"{'file':<15} {'init':<9} {'init s':>7} {'½χ² (final)':>13} {'GTSAM':>9} {'4 dig.':>6} "
        f"{'SE-Sync obj.':>13} {'GTSAM':>8} {'f*':>7} {'it':>3} {'status':<19} {'solve s':>8} "
        f"{'GTSAM s':>8} {'ratio':>6} {'lin. s':>7} {'linsol s':>8}"
    )
    print(header)
    for name, (gtsam_cost, gtsam_seconds, gtsam_sesync, optimum) in REFERENCE.items():
        path = fetch("posegraph") / f"{name}.g2o"
        if not path.exists():
            print(f"{name}: {path} is absent, skipped")
            continue
        graph = g2o.read_g2o(path)
        for init in ("odometry", "chordal"):
            tick = time.perf_counter()
            poses = (
                graph.poses if init == "odometry" else initialization.chordal_initialization(graph)
            )
            init_seconds = time.perf_counter() - tick
            results = [
                solve_pose_graph(graph, poses, config=config) for _ in range(max(args.repeats, 1))
            ]
            result = results[0]
            seconds = statistics.median(r.time_seconds for r in results)
            sesync = float(objectives.sesync_objective(graph, result.poses))
            match = "yes" if _same_4_digits(result.final_cost, gtsam_cost) else "NO"
            print(
                f"{name:<15} {init:<9} {init_seconds:7.3f} {result.final_cost:13.8g} "
                f"{gtsam_cost:9.6g} {match:>6} "
                f"{sesync:13.6g} {gtsam_sesync:8.6g} {optimum:7.5g} {result.iterations:3d} "
                f"{result.status.name:<19} {seconds:8.3f} {gtsam_seconds:8.2f} "
                f"{seconds / gtsam_seconds:6.2f} "
                f"{statistics.median(r.linearize_seconds for r in results):7.3f} "
                f"{statistics.median(r.linear_solve_seconds for r in results):8.3f}",
                flush=True,
            )
    print(
        "\nratio = solve time / GTSAM's C++ LM time on this machine (goal ≤ 2); 'lin. s' is "
        "residuals + Jacobians + block products, 'linsol s' assembly + SuperLU factor/solve."
    )

    print(
        "\nThe same graphs through the general solver: torchslam.solve on a PointMapProblem "
        "without points whose objective is graph.relative_pose_term() on the poses T_i0 = T_i⁻¹ "
        "(pose 0 fixed, SolverConfig(initial_lambda=1e-9), reduced_solver auto → sparse):"
    )
    for name, (gtsam_cost, gtsam_seconds, _, _) in REFERENCE.items():
        path = fetch("posegraph") / f"{name}.g2o"
        if not path.exists():
            continue
        graph = g2o.read_g2o(path)
        runs = [_solve_as_terms(graph) for _ in range(max(args.repeats, 1))]
        cost, iterations, status = runs[0][:3]
        seconds = statistics.median(run[3] for run in runs)
        match = "yes" if _same_4_digits(cost, gtsam_cost) else "NO"
        print(
            f"{name:<15} ½χ² {cost:.8g} (GTSAM {gtsam_cost:.6g}, 4 digits: {match}), "
            f"{iterations} iterations, {status}, {seconds:.3f} s ({seconds / gtsam_seconds:.2f}× "
            "GTSAM)",
            flush=True,
        )

    print()
    for name in REFERENCE:
        path = fetch("posegraph") / f"{name}.g2o"
        if not path.exists():
            continue
        outcome = _gtsam_lm(path)
        if outcome is None:
            print("gtsam is not importable: GTSAM's LM comparison skipped (pip install gtsam)")
            break
        print(f"GTSAM LM on {name}: ½χ² = {outcome[0]:.8g} in {outcome[1]:.3f} s")

    _sesync_section(config)
    if not args.skip_synthetic:
        _synthetic_section(config)
    if not args.skip_process:
        _process_section(max(args.repeats, 1))
    return 0


# ------------------------------------------------------------------------------------------
# Issue 14: the SE-Sync objective, certificates, synthetic graphs, whole-process times.


def _sesync_section(config: PoseGraphSolverConfig) -> None:
    print(
        "\nThe SE-Sync objective (--objective sesync) from the chordal start, certified "
        "(certify: λ_min(S) ≥ −η, η = 1e-6·f/(dn)); f* = the certified optima of SE-Sync's "
        "paper (MIT: none published here, the certificate decides):"
    )
    print(
        f"{'file':<15} {'objective':<9} {'final':>14} {'f*':>8} {'4 dig.':>6} {'it':>3} "
        f"{'status':<19} {'solve s':>8} {'certified':>9} {'λ_min':>10} {'η':>8} "
        f"{'cert s':>7} {'SE-Sync obj.':>13} {'½χ²':>11}"
    )
    targets = {"sphere2500": 1687.0, "parking-garage": 1.263, "MIT": None}
    for name, optimum in targets.items():
        path = fetch("posegraph") / f"{name}.g2o"
        if not path.exists():
            print(f"{name}: {path} is absent, skipped")
            continue
        graph = g2o.read_g2o(path)
        starts = {"chordal": initialization.chordal_initialization(graph)}
        if name == "MIT":
            starts = {"file": graph.poses, **starts}
        for init, poses in starts.items():
            for objective in ("chi2", "sesync"):
                cfg = PoseGraphSolverConfig(linear_solver=config.linear_solver, objective=objective)
                result = solve_pose_graph(graph, poses, config=cfg)
                cert = certify(graph, result.poses)
                sesync = float(objectives.sesync_objective(graph, result.poses))
                chi2 = float(objectives.standard_cost(graph, result.poses))
                match = (
                    "-"
                    if optimum is None or objective != "sesync"
                    else ("yes" if _same_4_digits(result.final_cost, optimum) else "NO")
                )
                label = f"{name}/{init}" if name == "MIT" else name
                print(
                    f"{label:<15} {objective:<9} {result.final_cost:14.8g} "
                    f"{optimum if optimum is not None else float('nan'):8.5g} {match:>6} "
                    f"{result.iterations:3d} {result.status.name:<19} "
                    f"{result.time_seconds:8.3f} {'yes' if cert.certified else 'no':>9} "
                    f"{cert.lambda_min:10.2e} {cert.eta:8.1e} {cert.seconds:7.3f} "
                    f"{sesync:13.8g} {chi2:11.6g}",
                    flush=True,
                )
    print(
        "(a chi2 optimum is not a critical point of the SE-Sync objective: its certificate is "
        "'no' unless both optima nearly coincide; the CLI's --certify refines it first)"
    )


def _synthetic_section(config: PoseGraphSolverConfig) -> None:
    print(
        "\nSynthetic graphs (torchslam.data.posegraph.make_pose_graph, seed 1, σ_R = 0.15 rad, "
        "σ_t = 0.2, loop-closure probability 0.5); W = planted wrong loop closures; file = "
        "the noisy odometry chain (30 LM iterations at most), chordal = chordal start:"
    )
    print(
        f"{'graph':<22} {'W':>1} {'init':<8} {'objective':<9} {'final':>12} {'it':>3} "
        f"{'status':<19} {'solve s':>8} {'certified':>9} {'λ_min':>10} {'bound':>12} "
        f"{'max edge ½χ²':>13} {'at wrong edge':>13}"
    )
    for kind, n in (("torus", 2000), ("grid", 2197)):
        for wrong in (0, 1):
            scene = make_pose_graph(
                kind,
                n,
                rotation_noise=0.15,
                translation_noise=0.2,
                wrong_loop_closures=wrong,
                seed=1,
            )
            graph = scene.graph
            starts = {"chordal": initialization.chordal_initialization(graph)}
            if wrong == 0:
                starts = {"file": graph.poses, **starts}
            for init, poses in starts.items():
                for objective in ("chi2", "sesync"):
                    cfg = PoseGraphSolverConfig(
                        linear_solver=config.linear_solver,
                        objective=objective,
                        max_iterations=30 if init == "file" else 100,
                    )
                    result = solve_pose_graph(graph, poses, config=cfg)
                    cert = certify(graph, result.poses)
                    r = objectives.edge_residuals(graph, result.poses)
                    chi = 0.5 * (r[:, None, :] @ graph.information @ r[:, :, None]).flatten()
                    worst = int(chi.argmax())
                    at_wrong = "yes" if worst in scene.wrong_edges.tolist() else "no"
                    print(
                        f"{kind + f' {graph.num_vertices}/{graph.num_edges}':<22} {wrong:>1} "
                        f"{init:<8} {objective:<9} {result.final_cost:12.7g} "
                        f"{result.iterations:3d} {result.status.name:<19} "
                        f"{result.time_seconds:8.3f} {'yes' if cert.certified else 'no':>9} "
                        f"{cert.lambda_min:10.2e} {cert.lower_bound:12.7g} "
                        f"{float(chi[worst]):13.4g} {at_wrong if wrong else '-':>13}",
                        flush=True,
                    )
    print(
        "(certified and bound refer to the SE-Sync objective at the solution's rotations; "
        "'bound' = its dual lower bound f + min(λ_min, 0)·dn on the global minimum)"
    )


_GTSAM_SCRIPT = """
import sys, time
import numpy as np
import gtsam
graph, initial = gtsam.readG2o(sys.argv[1], True)
noise = gtsam.noiseModel.Diagonal.Variances(np.full(6, 1e-6))
graph.add(gtsam.PriorFactorPose3(0, initial.atPose3(0), noise))
params = gtsam.LevenbergMarquardtParams()
result = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
print(graph.error(result))
"""


def _peer_python() -> str | None:
    """The peers' Python if it imports gtsam, else None."""
    candidates = [os.environ.get("TORCHSLAM_PEERS_PYTHON")]
    candidates.append(
        str(Path(__file__).resolve().parents[1] / ".." / "peers-venv" / "bin" / "python")
    )
    for candidate in candidates:
        if candidate and Path(candidate).exists():
            ok = subprocess.run([candidate, "-c", "import gtsam"], capture_output=True, timeout=120)
            if ok.returncode == 0:
                return candidate
    return None


def _timed(command: list[str], cpus: int, repeats: int) -> tuple[float, str]:
    """Median wall seconds of a subprocess pinned to ``cpus`` CPUs, and its last line."""
    env = dict(os.environ)
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        env[name] = str(cpus)
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[1])
    if shutil.which("taskset") and (os.cpu_count() or 1) >= cpus:
        command = ["taskset", "-c", ",".join(str(c) for c in range(cpus)), *command]
    times, last = [], ""
    for _ in range(repeats):
        tick = time.perf_counter()
        done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=1800)
        times.append(time.perf_counter() - tick)
        if done.returncode != 0:
            return float("nan"), done.stderr.strip().splitlines()[-1] if done.stderr else "?"
        lines = done.stdout.strip().splitlines()
        last = lines[-1] if lines else ""
    return statistics.median(times), last


def _process_section(repeats: int) -> None:
    print(
        f"\nWhole-process wall time (median of {repeats}; start-up, reading, chordal "
        "initialization, solve, exit), pinned with taskset:"
    )
    peer = _peer_python()
    if peer is None:
        print("gtsam is not importable by the peers' Python: GTSAM's column skipped")
    with tempfile.TemporaryDirectory() as tmp:
        script = Path(tmp) / "gtsam_lm.py"
        script.write_text(_GTSAM_SCRIPT)
        print(
            f"{'file':<15} {'CPUs':>4} {'torchslam s':>11} {'GTSAM s':>8} {'ratio':>6}  "
            "torchslam's last line / GTSAM ½χ²"
        )
        for name in ("sphere2500", "parking-garage"):
            path = fetch("posegraph") / f"{name}.g2o"
            if not path.exists():
                continue
            for cpus in (1, 2):
                ours, line = _timed(
                    [
                        sys.executable,
                        "-m",
                        "torchslam",
                        "posegraph",
                        str(path),
                        "--init",
                        "chordal",
                        "--threads",
                        str(cpus),
                    ],
                    cpus,
                    repeats,
                )
                theirs, error = (float("nan"), "-")
                if peer is not None:
                    theirs, error = _timed([peer, str(script), str(path)], cpus, repeats)
                print(
                    f"{name:<15} {cpus:>4} {ours:11.3f} {theirs:8.3f} {ours / theirs:6.2f}  "
                    f"{line[:60]} / {error}",
                    flush=True,
                )


if __name__ == "__main__":
    sys.exit(main())
