"""Seeded boundary checks of pose graphs, the pose-graph solver, the metrics and g2o writing.

Every bad argument must end in a ValueError/TypeError naming the public function (or class)
and the argument; valid inputs (including round-off-sized asymmetry of information matrices
and singular PSD information) must still be accepted. Random graphs and corruptions come from
a ``torch.Generator`` / ``random.Random`` with a fixed seed.
"""

from __future__ import annotations

import math
import random

import pytest
import torch

from torchslam import _checks, metrics
from torchslam.io import g2o
from torchslam.lie import se3
from torchslam.posegraph import PoseGraph, initialization, objectives
from torchslam.posegraph.solve import (
    PoseGraphSolverConfig,
    PosePriors,
    solve_pose_graph,
)

D = torch.float64


def _poses(generator: torch.Generator, n: int, dtype: torch.dtype = D) -> torch.Tensor:
    return se3.exp(torch.randn(n, 6, generator=generator, dtype=D)).to(dtype)


def _fields(generator: torch.Generator, n: int = 5, dtype: torch.dtype = D) -> dict:
    """A consistent ring graph: odometry edges k → k + 1 and one closure n−1 → 0."""
    T = _poses(generator, n)
    edges = torch.tensor([[k, k + 1] for k in range(n - 1)] + [[n - 1, 0]])
    Z = se3.inverse(T[edges[:, 0]]) @ T[edges[:, 1]]
    A = torch.randn(n, 6, 6, generator=generator, dtype=D)
    information = A @ A.transpose(-1, -2) + 6 * torch.eye(6, dtype=D)
    return {
        "ids": torch.arange(n) * 3,
        "poses": T.to(dtype),
        "edges": edges,
        "measurements": Z.to(dtype),
        "information": information.to(dtype),
    }


def _graph(generator: torch.Generator, **changes) -> PoseGraph:
    fields = _fields(generator)
    fields.update(changes)
    return PoseGraph(**fields)


@pytest.mark.parametrize(
    ("field", "value", "words"),
    [
        ("edges", torch.tensor([[0, 1], [1, 2], [2, 9], [3, 4], [4, 0]]), ["edges[2] = [2, 9]"]),
        ("edges", torch.tensor([[0, 1], [1, 2], [2, -1], [3, 4], [4, 0]]), ["[0, 5)"]),
        ("edges", torch.tensor([[0, 1, 2]] * 5), ["shape"]),
        ("ids", torch.tensor([0, 3, 3, 6, 9]), ["strictly increasing"]),
        ("ids", torch.tensor([9, 3, 0, 6, 12]), ["strictly increasing"]),
        ("fixed", torch.tensor([7]), ["fixed[0] = 7"]),
        ("fixed", torch.tensor([-1]), ["fixed[0] = -1"]),
        ("fixed", torch.tensor([[0]]), ["(F,)"]),
    ],
)
def test_graph_indices_are_validated(generator, field, value, words):
    # A negative edge index used to wrap silently to the last vertex and "converge".
    with pytest.raises(ValueError, match=f"PoseGraph: argument '{field}'") as info:
        _graph(generator, **{field: value})
    for word in words:
        assert word in str(info.value)
    with pytest.raises(TypeError, match="PoseGraph: argument 'dimension'"):
        _graph(generator, dimension="3")


def test_graph_values_are_validated_and_round_off_accepted(generator):
    fields = _fields(generator)
    rng = random.Random(7)
    for _ in range(12):  # seeded corruptions of one entry of one field
        name = rng.choice(["poses", "measurements", "information"])
        bad = fields[name].clone()
        k, r, c = rng.randrange(bad.shape[0]), rng.randrange(3), rng.randrange(3)
        bad[k, r, c] = rng.choice([math.nan, math.inf, bad[k, r, c] + 5.0])
        with pytest.raises(ValueError, match=f"PoseGraph: argument '{name}'"):
            PoseGraph(**{**fields, name: bad})
    negative = fields["information"].clone()
    negative[3] = -negative[3]
    with pytest.raises(ValueError, match="positive semidefinite matrices; edge 3"):
        PoseGraph(**{**fields, "information": negative})
    # Round-off asymmetry (1e-12 relative, far below the 1e-8 tolerance) and a singular PSD
    # matrix (a file may hold one; only the solver needs positive definite) are accepted.
    information = fields["information"].clone()
    information[0, 0, 1] *= 1 + 1e-12
    information[1] = torch.diag(torch.tensor([1.0, 1.0, 1.0, 1.0, 1.0, 0.0], dtype=D))
    graph = PoseGraph(**{**fields, "information": information})
    with pytest.raises(ValueError, match=r"solve_pose_graph: .*'graph.information' of edge 1"):
        solve_pose_graph(graph)
    # Value checks are skipped inside validation(False), shape checks are not.
    with _checks.validation(False):
        PoseGraph(**{**fields, "information": negative})
        with pytest.raises(ValueError, match="PoseGraph: argument 'edges' must have shape"):
            PoseGraph(**{**fields, "edges": fields["edges"][:2]})


def test_with_poses_names_itself(generator):
    graph = _graph(generator)
    with pytest.raises(ValueError, match=r"PoseGraph.with_poses: argument 'poses' must have"):
        graph.with_poses(_poses(generator, 3))
    with pytest.raises(ValueError, match=r"PoseGraph.with_poses: argument 'poses' must hold rot"):
        graph.with_poses(2 * graph.poses)
    moved = graph.with_poses(_poses(generator, 5))
    assert moved.edges is graph.edges and not torch.equal(moved.poses, graph.poses)


def test_solver_arguments_and_config(generator):
    graph = _graph(generator)
    with pytest.raises(TypeError, match="solve_pose_graph: argument 'config'"):
        solve_pose_graph(graph, config={"max_iterations": 3})
    with pytest.raises(TypeError, match="solve_pose_graph: argument 'callback'"):
        solve_pose_graph(graph, callback=3)
    with pytest.raises(TypeError, match="solve_pose_graph: argument 'graph'"):
        solve_pose_graph("graph")
    with pytest.raises(TypeError, match="solve_pose_graph: argument 'fixed'"):
        solve_pose_graph(graph, fixed=torch.tensor([0.0]))
    for name, bad in (
        ("min_lambda", {"min_lambda": 1.0, "max_lambda": 1e-3}),
        ("initial_lambda", {"initial_lambda": 1.0, "max_lambda": 1e-3}),
        ("initial_lambda", {"initial_lambda": math.inf}),
        ("max_lambda", {"max_lambda": math.nan}),
        ("function_tolerance", {"function_tolerance": -1.0}),
        ("gradient_tolerance", {"gradient_tolerance": True}),
        ("max_iterations", {"max_iterations": 3.0}),
        ("dense_max_variables", {"dense_max_variables": "9"}),
        ("damping", {"damping": None}),
    ):
        with pytest.raises(ValueError, match=f"PoseGraphSolverConfig: '{name}'"):
            PoseGraphSolverConfig(**bad)
    result = solve_pose_graph(graph, config=PoseGraphSolverConfig(max_iterations=2))
    assert result.converged  # the measurements are exact: the start is the optimum


def test_pose_priors_values(generator):
    eye = torch.eye(6, dtype=D)[None]
    with pytest.raises(ValueError, match="PosePriors: argument 'poses'"):
        PosePriors(torch.tensor([0]), torch.ones(1, 4, 4, dtype=D), eye)
    with pytest.raises(ValueError, match="PosePriors: argument 'information'"):
        PosePriors(
            torch.tensor([0]), _poses(generator, 1), torch.full((1, 6, 6), math.nan, dtype=D)
        )
    with pytest.raises(ValueError, match=r"PosePriors: argument 'information' .* prior 0"):
        PosePriors(torch.tensor([0]), _poses(generator, 1), -eye)
    with pytest.raises(ValueError, match="PosePriors: argument 'indices'"):
        PosePriors(torch.tensor([-1]), _poses(generator, 1), eye)


def test_objectives_and_initializers_refuse_unusable_weights(generator):
    with pytest.raises(ValueError, match="sesync_weights: argument 'information'"):
        objectives.sesync_weights(-torch.eye(6, dtype=D)[None])
    singular = _fields(generator)["information"].clone()
    singular[2, 3:, 3:] = 0.0
    singular[2, :3, 3:] = singular[2, 3:, :3] = 0.0
    graph = _graph(generator, information=singular)
    with pytest.raises(ValueError, match=r"chordal_initialization: .* edge 2"):
        initialization.chordal_initialization(graph)
    with pytest.raises(ValueError, match=r"sesync_objective: .* edge 2"):
        objectives.sesync_objective(graph)
    with pytest.raises(TypeError, match="odometry_initialization: argument 'graph'"):
        initialization.odometry_initialization(None)
    with pytest.raises(ValueError, match="standard_cost: argument 'poses' must hold rotation"):
        objectives.standard_cost(graph, 2 * graph.poses)


def test_metrics_refuse_non_rigid_non_finite_and_empty(generator):
    P, Q = _poses(generator, 6), _poses(generator, 6)
    # 2·P used to report a 0° rotation error (a wrong answer).
    for bad in (2 * P, P.clone().index_fill_(0, torch.tensor([2]), math.nan)):
        with pytest.raises(ValueError, match="evaluate: argument 'poses'"):
            metrics.evaluate(bad, Q)
        with pytest.raises(ValueError, match="pose_errors: argument 'poses'"):
            metrics.pose_errors(bad, Q)
    points = torch.randn(4, 3, generator=generator, dtype=D)
    with pytest.raises(ValueError, match="evaluate: argument 'points'"):
        metrics.evaluate(P, Q, points.clone().fill_(math.nan), points)
    with pytest.raises(ValueError, match="evaluate: 'points' and 'points_gt'"):
        metrics.evaluate(P, Q, points, points[:3])
    with pytest.raises(ValueError, match=r"evaluate: .*at least 1 pose"):
        metrics.evaluate(P[:0], Q[:0])
    with pytest.raises(ValueError, match=r"absolute_trajectory_error: .*at least 1 pose"):
        metrics.absolute_trajectory_error(P[:0], Q[:0])
    # align="se3" needs 3 non-collinear sensor positions: the error names the caller.
    for m in (1, 2):
        with pytest.raises(ValueError, match="evaluate: the SE\\(3\\) alignment needs at least 3"):
            metrics.evaluate(P[:m], Q[:m], align="se3")
    same = P[:1].expand(4, 4, 4).clone()
    with pytest.raises(ValueError, match=r"evaluate: .*collinear or coincident"):
        metrics.evaluate(same, same, align="se3")
    with pytest.raises(ValueError, match=r"align_trajectories: .*collinear or coincident"):
        metrics.align_trajectories(same, same)
    errors = metrics.evaluate(P, P, align="se3")
    # The alignment of identical trajectories is the identity up to the SVD's round-off.
    assert errors.mean_ate < 1e-9 and errors.max_rotation_error_deg < 1e-6


def test_g2o_writer_validates(generator, tmp_path):
    graph = _graph(generator)
    path = tmp_path / "out.g2o"
    with pytest.raises(TypeError, match="format_g2o: argument 'graph'"):
        g2o.format_g2o("graph")
    with pytest.raises(ValueError, match="write_g2o: argument 'poses' must have shape"):
        g2o.write_g2o(path, graph, _poses(generator, 2))
    with pytest.raises(ValueError, match="write_g2o: argument 'poses' contains"):
        g2o.write_g2o(path, graph, torch.full((5, 4, 4), math.nan, dtype=D))
    with pytest.raises(TypeError, match="write_g2o: argument 'path'"):
        g2o.write_g2o(3, graph)
    assert not path.exists()
    g2o.write_g2o(path, graph)
    back = g2o.read_g2o(path)
    assert torch.equal(back.ids, graph.ids) and torch.equal(back.edges, graph.edges)
