"""Pose-graph Levenberg-Marquardt: optimum, sparse vs dense, gauge, priors, loop closure, CLI."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from torchslam import cli, metrics
from torchslam.data import make_scene
from torchslam.io import g2o
from torchslam.lie import se3, so3
from torchslam.posegraph import PoseGraph, initialization, objectives
from torchslam.posegraph.solve import PoseGraphSolverConfig, PosePriors, solve_pose_graph
from torchslam.solver.result import Status

# Tolerances tight enough that the solve stops on round-off, not early.
TIGHT = {"function_tolerance": 1e-15, "gradient_tolerance": 1e-12, "parameter_tolerance": 1e-15}


def ring_graph(
    generator: torch.Generator,
    n: int = 16,
    noise: float = 0.03,
    loop_every: int = 4,
    dtype: torch.dtype = torch.float64,
) -> tuple[PoseGraph, torch.Tensor]:
    """A noisy ring: poses on a tilted circle, odometry k → k+1 (closing n−1 → 0), and loop
    closures k → k + loop_every for even k; anisotropic information with cross terms.

    Returns the graph (vertex values: the odometry chain of the noisy measurements, the usual
    initial guess) and the true poses (body → world). ``noise = 0`` gives exact measurements.
    """
    f64 = torch.float64
    theta = 2 * math.pi * torch.arange(n, dtype=f64) / n
    yaw = torch.stack((torch.zeros(n, dtype=f64), torch.zeros(n, dtype=f64), theta + 1.0), -1)
    tilt = 0.2 * torch.randn(n, 3, generator=generator, dtype=f64)
    R = so3.exp(yaw) @ so3.exp(tilt)
    t = torch.stack((5 * torch.cos(theta), 5 * torch.sin(theta), 0.5 * torch.sin(3 * theta)), -1)
    truth = se3.from_rotation_translation(R, t)
    odometry = [(k, (k + 1) % n) for k in range(n)]
    loops = [(k, k + loop_every) for k in range(0, n - loop_every, 2)]
    edges = torch.tensor(odometry + loops)
    e = edges.shape[0]
    Z = se3.inverse(truth[edges[:, 0]]) @ truth[edges[:, 1]]
    Z = Z @ se3.exp(noise * torch.randn(e, 6, generator=generator, dtype=f64))
    A = 0.5 * torch.randn(e, 6, 6, generator=generator, dtype=f64)
    weights = torch.tensor([100.0, 100.0, 50.0, 10.0, 10.0, 20.0], dtype=f64)
    information = A @ A.transpose(-1, -2) + torch.diag(weights)
    graph = PoseGraph(
        ids=torch.arange(n),
        poses=truth,
        edges=edges,
        measurements=Z,
        information=information,
    )
    graph = graph.with_poses(initialization.odometry_initialization(graph))
    return (
        PoseGraph(
            ids=graph.ids,
            poses=graph.poses.to(dtype),
            edges=graph.edges,
            measurements=graph.measurements.to(dtype),
            information=graph.information.to(dtype),
        ),
        truth.to(dtype),
    )


def right_gradient(graph: PoseGraph, poses: torch.Tensor) -> torch.Tensor:
    """∂F(T_i·Exp(δ_i))/∂δ at δ = 0 by autograd through objectives.standard_cost, (N, 6)."""
    delta = torch.zeros(graph.num_vertices, 6, dtype=poses.dtype, requires_grad=True)
    objectives.standard_cost(graph, poses @ se3.exp(delta)).backward()
    return delta.grad


def free_hessian(graph: PoseGraph, poses: torch.Tensor) -> torch.Tensor:
    """∂²F(T_i·Exp(δ_i))/∂δ² at δ = 0 over the free vertices (vertex 0 fixed), by autograd
    through objectives.standard_cost, (6(N − 1), 6(N − 1))."""
    H = torch.autograd.functional.hessian(
        lambda d: objectives.standard_cost(graph, poses @ se3.exp(d.reshape(-1, 6))),
        torch.zeros(6 * graph.num_vertices, dtype=poses.dtype),
    )
    return H[6:, 6:]


@pytest.fixture
def ring(generator):
    return ring_graph(generator)


@pytest.mark.parametrize("linear_solver", ["sparse", "dense"])
def test_lm_reaches_the_optimum(ring, linear_solver):
    graph, _ = ring
    config = PoseGraphSolverConfig(linear_solver=linear_solver, **TIGHT)
    result = solve_pose_graph(graph, config=config, init="file")  # LM from the drifted start
    assert result.converged, result.summary()
    assert result.initialization == "file"
    assert result.linear_solver == linear_solver
    assert result.final_cost < 0.1 * result.initial_cost
    # The cost history never increases (rejected steps repeat the cost).
    history = result.cost_history
    assert history.shape == (result.iterations + 1,)
    assert (history[1:] <= history[:-1]).all()
    assert float(history[0]) == result.initial_cost and float(history[-1]) == result.final_cost
    assert result.final_cost == pytest.approx(float(objectives.standard_cost(graph, result.poses)))
    # First-order optimality, checked by autograd through the independent cost function: the
    # gradient falls by 9+ orders of magnitude (GN converges linearly on a noisy graph, and the
    # solve stops when the cost change reaches round-off).
    # The solve stops when the model decrease ½ gᵀH⁻¹g (chart-invariant to first order) is
    # at most function_tolerance·F, where the cost's round-off hides further progress; so
    # |g| ≤ √(2·ftol·F·λ_max(H)) at the solution, with H the Gauss-Newton Hessian in the same
    # chart as g (autograd, free vertices). A factor 4 covers a last accepted step that stopped
    # by the measured decrease instead.
    initial_gradient = right_gradient(graph, graph.poses)[1:].abs().max()
    gradient = right_gradient(graph, result.poses)[1:].abs().max()
    H = free_hessian(graph, result.poses)
    floor = math.sqrt(
        2 * TIGHT["function_tolerance"] * result.final_cost * float(torch.linalg.eigvalsh(H).max())
    )
    assert gradient <= 4 * floor
    assert gradient < 1e-6 * initial_gradient
    assert result.gradient_norm == pytest.approx(float(gradient), rel=1e-3)
    # The gauge vertex did not move.
    assert torch.equal(result.poses[0], graph.poses[0])


def test_sparse_and_dense_paths_agree(ring):
    graph, _ = ring
    results = {
        solver: solve_pose_graph(graph, config=PoseGraphSolverConfig(linear_solver=solver, **TIGHT))
        for solver in ("sparse", "dense")
    }
    sparse, dense = results["sparse"], results["dense"]
    # Each solve stops once the model decrease ½ δᵀHδ of the remaining Newton step is at most
    # function_tolerance·F (round-off of the cost hides the rest), i.e. within
    # √(2·ftol·F / λ_min(H)) of the optimum in the vertices' chart; the two solutions are
    # within twice that (×4 for a last step stopped by the measured decrease instead).
    H = free_hessian(graph, dense.poses)
    radius = math.sqrt(
        2 * TIGHT["function_tolerance"] * dense.final_cost / float(torch.linalg.eigvalsh(H).min())
    )
    apart = torch.linalg.vector_norm(se3.log(se3.inverse(dense.poses) @ sparse.poses), dim=-1)
    assert float(apart.max()) <= 8 * radius < 1e-5
    assert sparse.final_cost == pytest.approx(dense.final_cost, rel=1e-12)


@pytest.mark.parametrize("linear_solver", ["sparse", "dense"])
def test_levenberg_damping_reaches_the_same_optimum(ring, linear_solver):
    graph, _ = ring
    results = [
        solve_pose_graph(
            graph,
            config=PoseGraphSolverConfig(linear_solver=linear_solver, damping=damping, **TIGHT),
        )
        for damping in ("marquardt", "levenberg")
    ]
    assert all(r.converged for r in results)
    assert (results[0].poses - results[1].poses).abs().max() < 1e-8


@pytest.mark.parametrize("ordering", ["mmd", "colamd", "natural"])
@pytest.mark.parametrize("fixed", [[0], [3, 7], []])
def test_one_sparse_step_equals_the_dense_step(generator, ordering, fixed):
    # Duplicate edges, a self-edge, an edge stored backwards and priors: every assembly case.
    graph, truth = ring_graph(generator, n=10, noise=0.1)
    extra = torch.tensor([[2, 5], [2, 5], [4, 4], [9, 1]])
    Z = se3.inverse(truth[extra[:, 0]]) @ truth[extra[:, 1]]
    graph = PoseGraph(
        ids=graph.ids,
        poses=graph.poses,
        edges=torch.cat((graph.edges, extra)),
        measurements=torch.cat((graph.measurements, Z)),
        information=torch.cat((graph.information, graph.information[:4])),
    )
    priors = PosePriors(
        indices=torch.tensor([0, 6]),
        poses=truth[[0, 6]],
        information=torch.diag(torch.arange(1.0, 7.0, dtype=torch.float64)).expand(2, 6, 6),
    )
    steps = {}
    for solver in ("sparse", "dense"):
        config = PoseGraphSolverConfig(
            linear_solver=solver, ordering=ordering, max_iterations=1, initial_lambda=1e-3
        )
        result = solve_pose_graph(
            graph, config=config, priors=priors, fixed=torch.tensor(fixed, dtype=torch.int64)
        )
        assert result.iterations == 1
        steps[solver] = result
    assert steps["sparse"].step_norm_history[0] > 1e-3
    assert (steps["sparse"].poses - steps["dense"].poses).abs().max() < 1e-12
    for k in fixed:
        assert torch.equal(steps["sparse"].poses[k], graph.poses[k])


def test_exact_measurements_converge_to_the_truth(generator):
    graph, truth = ring_graph(generator, noise=0.0)
    start = truth @ se3.exp(0.2 * torch.randn(truth.shape[0], 6, generator=generator).double())
    start[0] = truth[0]
    result = solve_pose_graph(graph, start, config=PoseGraphSolverConfig(**TIGHT))
    assert result.converged, result.summary()
    assert (result.poses - truth).abs().max() < 1e-9
    assert result.final_cost < 1e-18


def test_analytic_and_jacrev_jacobians_give_the_same_iterates(ring):
    graph, _ = ring
    runs = [
        solve_pose_graph(graph, config=PoseGraphSolverConfig(jacobian=mode, max_iterations=4))
        for mode in ("analytic", "jacrev")
    ]
    assert runs[0].iterations == runs[1].iterations == 4
    assert torch.allclose(runs[0].cost_history, runs[1].cost_history, rtol=1e-10, atol=0)
    assert (runs[0].poses - runs[1].poses).abs().max() < 1e-9


def test_priors_fix_the_gauge_and_pull_towards_their_poses(ring):
    graph, truth = ring
    with pytest.raises(ValueError, match="gauge is free"):
        solve_pose_graph(graph, fixed=torch.zeros(0, dtype=torch.int64))
    target = truth[0] @ se3.exp(torch.tensor([0.1, 0, 0, 1.0, 0, 0], dtype=torch.float64))
    priors = PosePriors(
        indices=torch.tensor([0]),
        poses=target[None],
        information=1e8 * torch.eye(6, dtype=torch.float64)[None],
    )
    result = solve_pose_graph(
        graph,
        config=PoseGraphSolverConfig(**TIGHT),
        priors=priors,
        fixed=torch.zeros(0, dtype=torch.int64),
    )
    assert result.converged, result.summary()
    # The stiff prior moves vertex 0 (free now) onto its pose; the rest follows rigidly.
    assert (result.poses[0] - target).abs().max() < 1e-6
    anchored = solve_pose_graph(graph, config=PoseGraphSolverConfig(**TIGHT))
    moved = target @ se3.inverse(anchored.poses[0]) @ anchored.poses
    assert (result.poses - moved).abs().max() < 1e-5


def test_file_fix_lines_are_the_default_gauge(ring):
    graph, _ = ring
    text = g2o.format_g2o(graph).replace("FIX", "#")
    fixed = g2o.parse_g2o(text + "FIX 5\n")
    result = solve_pose_graph(fixed, config=PoseGraphSolverConfig(max_iterations=3))
    assert torch.equal(result.poses[5], fixed.poses[5])
    assert (result.poses[0] - fixed.poses[0]).abs().max() > 1e-3


def test_float32_graph_solves(generator):
    graph, _ = ring_graph(generator, dtype=torch.float32)
    reference, _ = ring_graph(torch.Generator().manual_seed(20261122))
    result = solve_pose_graph(graph, config=PoseGraphSolverConfig(linear_solver="sparse"))
    expected = solve_pose_graph(reference, config=PoseGraphSolverConfig(**TIGHT))
    assert result.poses.dtype == torch.float32
    assert result.final_cost == pytest.approx(expected.final_cost, rel=1e-3)


def test_loop_closure_reduces_drift():
    # A loop from the synthetic ICP scenes (poses T_i0: world → frame i; invert for the graph).
    scene = make_scene(36, 10, trajectory="loop", rotation_per_frame_deg=10.0, seed=3)
    truth = se3.inverse(scene.poses_gt[0])  # body → world, frame 0 at the identity
    n = truth.shape[0]
    gen = torch.Generator().manual_seed(7)
    noise = torch.tensor([0.01, 0.01, 0.01, 0.02, 0.02, 0.02], dtype=torch.float64)
    chain = torch.stack((torch.arange(n - 1), torch.arange(1, n)), -1)
    Z = se3.inverse(truth[:-1]) @ truth[1:]
    Z = Z @ se3.exp(noise * torch.randn(n - 1, 6, generator=gen, dtype=torch.float64))
    information = torch.diag(noise**-2).expand(n - 1, 6, 6)
    odometry_only = PoseGraph(
        ids=torch.arange(n), poses=truth, edges=chain, measurements=Z, information=information
    )
    drifted = initialization.odometry_initialization(odometry_only)
    closure_Z = se3.inverse(truth[-1]) @ truth[0]  # the robot recognizes its start
    closed = PoseGraph(
        ids=torch.arange(n),
        poses=drifted,
        edges=torch.cat((chain, torch.tensor([[n - 1, 0]]))),
        measurements=torch.cat((Z, closure_Z[None])),
        information=torch.cat((information, information[:1])),
    )
    result = solve_pose_graph(closed)
    assert result.converged, result.summary()

    def ate(poses: torch.Tensor) -> float:
        return float(metrics.absolute_trajectory_error(se3.inverse(poses), se3.inverse(truth)))

    assert ate(result.poses) < 0.6 * ate(drifted)  # 0.104 m vs 0.231 m with these seeds


def test_bad_arguments_raise_clear_errors(ring):
    graph, _ = ring
    with pytest.raises(ValueError, match="linear_solver"):
        PoseGraphSolverConfig(linear_solver="cholmod")
    with pytest.raises(ValueError, match="max_iterations"):
        PoseGraphSolverConfig(max_iterations=-1)
    with pytest.raises(ValueError, match="solve_pose_graph: argument 'poses'"):
        solve_pose_graph(graph, graph.poses[:3])
    with pytest.raises(TypeError, match="float32"):
        solve_pose_graph(graph, graph.poses.float())
    with pytest.raises(ValueError, match="'fixed' must hold vertex indices"):
        solve_pose_graph(graph, fixed=torch.tensor([99]))


def test_max_iterations_status(ring):
    graph, _ = ring
    result = solve_pose_graph(graph, config=PoseGraphSolverConfig(max_iterations=1, **TIGHT))
    assert result.status == Status.MAX_ITERATIONS
    assert "max_iterations" in result.reason


# ---------------------------------------------------------------------------------------------
# The `torchslam posegraph` command.


@pytest.fixture
def tiny_g2o(ring, tmp_path) -> Path:
    graph, _ = ring
    path = tmp_path / "ring.g2o"
    g2o.write_g2o(path, graph)
    return path


def test_cli_writes_optimized_graph_and_figure(tiny_g2o, tmp_path, capsys):
    out, plot = tmp_path / "opt.g2o", tmp_path / "fig" / "trajectory.png"
    code = cli.main(["posegraph", str(tiny_g2o), "--out", str(out), "--plot", str(plot)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    lines = captured.out.splitlines()
    assert any(line.split()[:1] == ["1"] for line in lines)  # a progress line per iteration
    assert "SE-Sync objective" in captured.out and "CONVERGED" in captured.out
    assert plot.stat().st_size > 10_000
    graph, optimized = g2o.read_g2o(tiny_g2o), g2o.read_g2o(out)
    assert torch.equal(optimized.edges, graph.edges)
    before = float(objectives.standard_cost(graph))
    assert float(objectives.standard_cost(optimized)) < 0.1 * before


@pytest.mark.parametrize("init", ["file", "odometry", "chordal"])
def test_cli_initializations(tiny_g2o, init, capsys):
    assert cli.main(["posegraph", str(tiny_g2o), "--init", init, "--max-iterations", "3"]) == 0
    assert f"initialization: {init}" in capsys.readouterr().out


def test_cli_malformed_line_names_the_line(tmp_path, capsys):
    path = tmp_path / "bad.g2o"
    path.write_text(
        "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
        "EDGE_SE3:QUAT 0 1 1 0 0 0 0\n"
    )
    assert cli.main(["posegraph", str(path)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert "torchslam posegraph: error:" in err and "line 3" in err


def test_cli_missing_file_exits_2_without_traceback(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "torchslam", "posegraph", str(tmp_path / "absent.g2o")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert "absent.g2o" in proc.stderr


@pytest.mark.parametrize("reduced_solver", ["sparse", "dense"])
def test_graph_as_a_relative_pose_term_reaches_the_same_optimum(ring, reduced_solver):
    # The general solver with the edges as a RelativePoseTerm on T_i0 = T_i⁻¹ (no points)
    # minimizes the same cost as the pose-graph solver: same optimum, same poses.
    import torchslam

    graph, _ = ring
    reference = solve_pose_graph(graph, config=PoseGraphSolverConfig(**TIGHT), init="file")
    none = torch.zeros(1, 0, dtype=torch.int64)
    empty = graph.poses.new_zeros(1, 0, 3)
    problem = torchslam.PointMapProblem(
        graph.frame_poses()[None], empty, none, none, empty, terms=[graph.relative_pose_term()]
    )
    assert float(problem.cost().detach()[0]) == pytest.approx(reference.initial_cost, rel=1e-12)
    config = torchslam.SolverConfig(reduced_solver=reduced_solver, **TIGHT)
    result = torchslam.solve(problem, config)
    assert result.converged
    assert float(result.final_cost[0]) == pytest.approx(reference.final_cost, rel=1e-10)
    assert (se3.inverse(problem.poses[0]) - reference.poses).abs().max() < 1e-8


def test_default_start_is_the_chordal_relaxation_and_is_reported(ring):
    # As the command line (issue 28 §4): from the chordal relaxation, aligned so that the
    # gauge vertex stays at its file pose; the result says where it started.
    graph, _ = ring
    default = solve_pose_graph(graph, config=PoseGraphSolverConfig(**TIGHT))
    assert default.initialization == "chordal" and default.converged
    assert torch.equal(default.poses[0], graph.poses[0])
    from_file = solve_pose_graph(graph, config=PoseGraphSolverConfig(**TIGHT), init="file")
    # a ring with small noise has one optimum: both starts reach it (to the solver tolerance)
    assert default.final_cost == pytest.approx(from_file.final_cost, rel=1e-8)
    given = solve_pose_graph(graph, graph.poses, config=PoseGraphSolverConfig(**TIGHT))
    assert given.initialization == "given"
    with pytest.raises(ValueError, match="'init' must be"):
        solve_pose_graph(graph, init="zero")
