"""Issue 14 on the pose-graph side: the spanning-tree initializer, the command's defaults
(chordal start, information handling) and summary lines, 2D figures with loop closures."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.posegraph.test_solve import ring_graph
from torchslam import cli
from torchslam.cli import plots
from torchslam.io import g2o
from torchslam.posegraph import PoseGraph, initialization
from torchslam.posegraph.solve import PoseGraphSolverConfig, solve_pose_graph


def _numbers(values: np.ndarray) -> str:
    return " ".join(repr(float(x)) for x in values)


def _upper(matrix: np.ndarray) -> str:
    rows, cols = np.triu_indices(matrix.shape[0])
    return _numbers(matrix[rows, cols])


def test_spanning_tree_of_a_ring_with_loops_is_its_odometry_chain(generator):
    """The ring's loop closures (k → k + 4, and 15 → 0) are never taken while odometry edges
    reach the vertex: the tree composes the same products as the odometry chain."""
    graph, _ = ring_graph(generator)
    tree = initialization.spanning_tree_initialization(graph)
    assert torch.equal(tree, initialization.odometry_initialization(graph))


def test_spanning_tree_crosses_a_broken_odometry_chain(generator):
    """Without the odometry edge 7 → 8, vertices 8.. are reached through a loop closure; the
    measurements are exact, so every vertex lands on its true pose."""
    graph, truth = ring_graph(generator, noise=0.0)
    keep = ~((graph.edges[:, 0] == 7) & (graph.edges[:, 1] == 8))
    broken = PoseGraph(
        ids=graph.ids,
        poses=truth,
        edges=graph.edges[keep],
        measurements=graph.measurements[keep],
        information=graph.information[keep],
    )
    with pytest.raises(ValueError, match="odometry chain is broken"):
        initialization.odometry_initialization(broken)
    # ≤ 16 exact compositions of well-conditioned rigid transforms: round-off only.
    torch.testing.assert_close(
        initialization.spanning_tree_initialization(broken), truth, rtol=0, atol=1e-12
    )


def test_spanning_tree_refuses_a_disconnected_graph(generator):
    graph, _ = ring_graph(generator)
    island = PoseGraph(
        ids=torch.tensor([0, 1, 5]),
        poses=graph.poses[:3],
        edges=torch.tensor([[0, 1]]),
        measurements=graph.measurements[:1],
        information=graph.information[:1],
    )
    with pytest.raises(ValueError, match=r"spanning_tree_initialization: .* vertex id 5 to"):
        initialization.spanning_tree_initialization(island)
    with pytest.raises(TypeError, match="spanning_tree_initialization: argument 'graph'"):
        initialization.spanning_tree_initialization(graph.poses)


# ------------------------------------------------------------------------------- command


def _planar_loop(path, *, vertices: bool = True, indefinite: int = 0) -> None:
    """A noisy 2D square loop of 12 poses (odometry and 3 loop closures), exact enough that
    LM converges in a few iterations; the first ``indefinite`` edges get an information
    matrix whose (x, θ) cross term makes it indefinite."""
    rng = np.random.default_rng(7)
    n = 12
    angle = 2 * math.pi * np.arange(n) / n
    truth = np.stack((3 * np.cos(angle), 3 * np.sin(angle), angle + math.pi / 2), -1)
    pairs = [(k, k + 1) for k in range(n - 1)] + [(11, 0), (0, 6), (3, 9)]
    good = np.array([[50.0, 0.0, 0.0], [0.0, 50.0, 0.0], [0.0, 0.0, 200.0]])
    bad = good.copy()
    bad[0, 2] = bad[2, 0] = 150.0  # 150² > 50 · 200
    lines = []
    drift = np.cumsum(rng.normal(0, 0.05, (n, 3)), axis=0)
    if vertices:
        lines += [f"VERTEX_SE2 {k} {_numbers(truth[k] + drift[k])}" for k in range(n)]
    for e, (i, j) in enumerate(pairs):
        a, b = truth[i], truth[j]
        c, s = math.cos(a[2]), math.sin(a[2])
        d = np.array(
            [
                c * (b[0] - a[0]) + s * (b[1] - a[1]),
                -s * (b[0] - a[0]) + c * (b[1] - a[1]),
                b[2] - a[2],
            ]
        ) + rng.normal(0, 0.01, 3)
        info = bad if e < indefinite else good
        lines.append(f"EDGE_SE2 {i} {j} {_numbers(d)} {_upper(info)}")
    path.write_text("\n".join(lines) + "\n")


def _run(argv, capsys):
    code = cli.main(argv)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_default_is_chordal_and_the_summary_names_it(tmp_path, capsys):
    path = tmp_path / "loop.g2o"
    _planar_loop(path)
    code, out, err = _run(["posegraph", str(path)], capsys)
    assert code == 0, err
    assert "2D, initialization: chordal" in out
    assert "information: repair (all 14 matrices positive semidefinite, used as read)" in out
    code, out, err = _run(["posegraph", str(path), "--init", "file"], capsys)
    assert code == 0, err
    assert "initialization: file\n" in out


def test_edge_only_file_runs_and_says_where_file_poses_come_from(tmp_path, capsys):
    full, edges = tmp_path / "full.g2o", tmp_path / "edges.g2o"
    _planar_loop(full)
    _planar_loop(edges, vertices=False)
    code, out, err = _run(["posegraph", str(edges), "--init", "file"], capsys)
    assert code == 0, err
    assert "initialization: file (no VERTEX lines: the edges chained along a spanning tree)" in out
    # The default (chordal) does not depend on the vertex values: same optimum, same numbers.
    results = [
        _run(["posegraph", str(p), "--out", str(p.with_suffix(".out"))], capsys)
        for p in (full, edges)
    ]
    assert all(code == 0 for code, _, _ in results)
    costs = [out.split("cost ½Σ rᵀΩr")[1].split()[:2] for _, out, _ in results]
    assert costs[0] == costs[1]


def test_information_handlings_on_the_command_line(tmp_path, capsys):
    path = tmp_path / "bad.g2o"
    _planar_loop(path, indefinite=2)
    code, out, err = _run(["posegraph", str(path)], capsys)
    assert code == 0, err
    assert (
        "information: repair: 2 of 14 edges not positive semidefinite (first on line 13): "
        "kept their translation and rotation blocks" in out
    )
    assert "Warning" not in err  # the summary says it once
    code, out, err = _run(["posegraph", str(path), "--information", "nearest"], capsys)
    assert code == 0, err
    assert "information: nearest: 2 of 14 edges" in out
    code, out, err = _run(["posegraph", str(path), "--information", "strict"], capsys)
    assert code == 2
    assert len(err.strip().splitlines()) == 1
    assert "bad.g2o, line 13: the information matrix is not positive semidefinite" in err
    code, _, err = _run(["posegraph", str(path), "--information", "clip"], capsys)
    assert code == 2 and "--information" in err


def test_2d_figure_has_one_plane_and_draws_the_loop_closures(tmp_path, monkeypatch):
    path = tmp_path / "loop.g2o"
    _planar_loop(path)
    graph = g2o.read_g2o(path)
    result = solve_pose_graph(graph, config=PoseGraphSolverConfig(max_iterations=3))
    plt = plots.require_pyplot()
    figures = []
    close = plt.close
    monkeypatch.setattr(plt, "close", lambda fig: (figures.append(fig), close(fig)))
    out = tmp_path / "fig.png"
    plots.plot_trajectories(out, graph.poses, result, title="loop", graph=graph)
    assert out.stat().st_size > 10_000
    (figure,) = figures
    assert len(figure.axes) == 2  # x-y plane and the cost
    assert figure.axes[0].get_title() == "x-y plane"
    (closures,) = figure.axes[0].collections
    assert len(closures.get_segments()) == 3  # 11 → 0, 0 → 6, 3 → 9
    # A 3D graph (or none given) keeps the two projections.
    plots.plot_trajectories(tmp_path / "fig3.png", graph.poses, result)
    assert len(figures[-1].axes) == 3
