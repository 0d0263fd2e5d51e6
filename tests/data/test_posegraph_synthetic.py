"""Synthetic pose graphs (torchslam.data.posegraph): structure, determinism, noise, errors."""

from __future__ import annotations

import pytest
import torch

from torchslam.data.posegraph import make_pose_graph
from torchslam.lie import se3
from torchslam.posegraph import certify, initialization, objectives
from torchslam.posegraph.solve import PoseGraphSolverConfig, solve_pose_graph


@pytest.mark.parametrize(("kind", "n"), [("torus", 60), ("grid", 27)])
def test_structure_and_determinism(kind, n):
    a = make_pose_graph(kind, n, loop_probability=1.0, seed=3)
    b = make_pose_graph(kind, n, loop_probability=1.0, seed=3)
    graph = a.graph
    assert graph.num_vertices == n and graph.num_edges > n - 1  # odometry + loop closures
    assert torch.equal(graph.measurements, b.graph.measurements)
    assert torch.equal(graph.edges[: n - 1, 1] - graph.edges[: n - 1, 0], torch.ones(n - 1).long())
    assert a.wrong_edges.numel() == 0
    # The vertices are the odometry chain composed from the noisy odometry.
    chain = initialization.odometry_initialization(graph)
    assert torch.allclose(chain, graph.poses, atol=1e-9)
    assert torch.allclose(graph.poses[0], a.truth[0])
    # Rotations of the truth are rotations.
    R = a.truth[:, :3, :3]
    eye = torch.eye(3, dtype=R.dtype).expand_as(R)
    assert torch.allclose(R.transpose(-1, -2) @ R, eye, atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(n, dtype=R.dtype), atol=1e-12)


def test_noise_level_and_wrong_loop_closures():
    scene = make_pose_graph(
        "torus", 200, rotation_noise=0.01, translation_noise=0.02, wrong_loop_closures=2, seed=5
    )
    graph = scene.graph
    assert scene.wrong_edges.tolist() == [graph.num_edges - 2, graph.num_edges - 1]
    i, j = graph.edges[:, 0], graph.edges[:, 1]
    assert bool(((j - i)[scene.wrong_edges] >= 50).all())  # at least N/4 apart
    # Residuals at the truth: whitened ones are N(0, I) on the good edges (mean square ≈ 1:
    # 6 × 300+ samples, 5 σ of the chi-square mean is below 0.2), huge on the wrong ones.
    r = objectives.edge_residuals(graph, scene.truth)
    s = (r[:, None, :] @ graph.information @ r[:, :, None]).flatten() / 6
    good = torch.ones(graph.num_edges, dtype=torch.bool)
    good[scene.wrong_edges] = False
    assert abs(float(s[good].mean()) - 1.0) < 0.2
    assert float(s[scene.wrong_edges].min()) > 1e3


def test_small_torus_reaches_a_certified_optimum():
    scene = make_pose_graph("torus", 60, rotation_noise=0.05, translation_noise=0.1, seed=2)
    graph = scene.graph
    poses = initialization.chordal_initialization(graph)
    result = solve_pose_graph(graph, poses, config=PoseGraphSolverConfig(objective="sesync"))
    assert result.converged
    assert certify(graph, result.poses).certified
    # The optimum is closer to the truth than the odometry chain is.
    err = se3.log(se3.inverse(scene.truth) @ result.poses)[:, 3:].norm(dim=-1).max()
    drift = se3.log(se3.inverse(scene.truth) @ graph.poses)[:, 3:].norm(dim=-1).max()
    assert err < drift


def test_bad_arguments():
    with pytest.raises(ValueError, match="make_pose_graph: argument 'kind'"):
        make_pose_graph("sphere")
    with pytest.raises(ValueError, match="make_pose_graph: argument 'num_poses'"):
        make_pose_graph("torus", 10)
    with pytest.raises(TypeError, match="make_pose_graph: argument 'num_poses'"):
        make_pose_graph("grid", 10.0)
    with pytest.raises(ValueError, match="make_pose_graph: the noise levels"):
        make_pose_graph("grid", 8, rotation_noise=0.0)
    with pytest.raises(ValueError, match="make_pose_graph: argument 'loop_probability'"):
        make_pose_graph("grid", 8, loop_probability=1.5)
    with pytest.raises(TypeError, match="make_pose_graph: argument 'dtype'"):
        make_pose_graph("grid", 8, dtype=torch.int64)
