"""g2o pose-graph files: conventions, round trips, error messages, the shared real data."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.helpers import dataset_folder
from torchslam.io import g2o
from torchslam.lie import se3
from torchslam.posegraph import PoseGraph, between

DATA = dataset_folder("posegraph")


def _upper(matrix: np.ndarray) -> list[float]:
    rows, cols = np.triu_indices(matrix.shape[0])
    return matrix[rows, cols].tolist()


def _line(*items: object) -> str:
    return " ".join(str(x) for x in items)


def test_read_3d_conventions(tmp_path):
    """Quaternion order (x, y, z, w), sorted ids, T_ij = T_i⁻¹ T_j, information reordered."""
    s = math.sqrt(0.5)
    # g2o-ordered information [translation, rotation] with every entry distinct.
    A = np.arange(36, dtype=np.float64).reshape(6, 6) / 10.0
    info_g2o = A @ A.T + 7 * np.eye(6)
    text = "\n".join(
        [
            "# a comment line",
            _line("VERTEX_SE3:QUAT", 7, 1.0, 2.0, 3.0, 0.0, 0.0, s, s),  # 90° about z
            "",
            _line("VERTEX_SE3:QUAT", 3, 0, 0, 0, 0, 0, 0, 1) + "   # trailing comment",
            _line("EDGE_SE3:QUAT", 3, 7, 1.0, 2.0, 3.0, 0.0, 0.0, s, s, *_upper(info_g2o)),
            "FIX 3",
            "PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1",
        ]
    )
    path = tmp_path / "tiny.g2o"
    path.write_text(text)
    graph = g2o.read_g2o(path)
    assert graph.dimension == 3
    assert graph.ids.tolist() == [3, 7]
    assert graph.edges.tolist() == [[0, 1]]
    assert graph.fixed.tolist() == [0]
    assert graph.poses.dtype == torch.float64
    expected = torch.tensor(
        [[0.0, -1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0], [0, 0, 0, 1]],
        dtype=torch.float64,
    )
    torch.testing.assert_close(graph.poses[1], expected, rtol=0, atol=1e-15)
    torch.testing.assert_close(graph.poses[0], torch.eye(4, dtype=torch.float64))
    # The measurement equals T_3⁻¹ T_7, so the between residual vanishes.
    r = between.between_residual(
        graph.poses[graph.edges[:, 0]], graph.poses[graph.edges[:, 1]], graph.measurements
    )
    assert r.abs().max() <= 1e-15
    # Information: ours = [[I_RR, I_Rt], [I_tR, I_tt]] of g2o's [[I_tt, I_tR], [I_Rt, I_RR]].
    ours = graph.information[0].numpy()
    np.testing.assert_array_equal(ours[:3, :3], info_g2o[3:, 3:])
    np.testing.assert_array_equal(ours[3:, 3:], info_g2o[:3, :3])
    np.testing.assert_array_equal(ours[:3, 3:], info_g2o[3:, :3])
    np.testing.assert_array_equal(ours[3:, :3], info_g2o[:3, 3:])


def test_quaternion_is_normalized_and_written_scalar_last(tmp_path):
    path = tmp_path / "q.g2o"
    path.write_text(_line("VERTEX_SE3:QUAT", 0, 0, 0, 0, 0, 0, 2.0, 2.0) + "\n")
    graph = g2o.read_g2o(path)
    R = graph.poses[0, :3, :3]
    torch.testing.assert_close(R.T @ R, torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-15)
    written = g2o.format_g2o(graph).split()
    q = [float(x) for x in written[-4:]]
    np.testing.assert_allclose(q, [0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-15)


def _random_graph(dimension: int, generator: torch.Generator) -> PoseGraph:
    n, e = 6, 9
    xi = torch.randn(n + e, 6, generator=generator, dtype=torch.float64) * 2.0
    if dimension == 2:
        xi[:, :2] = 0.0
        xi[:, 5] = 0.0
    T = se3.exp(xi)
    A = torch.randn(e, 6, 6, generator=generator, dtype=torch.float64)
    information = A @ A.transpose(-1, -2) + torch.eye(6, dtype=torch.float64)
    if dimension == 2:
        # Round trips keep only the (v_x, v_y, ω_z) block and the out-of-plane rule.
        keep = torch.tensor([2, 3, 4])
        planar = information[:, keep][:, :, keep]
        information = torch.zeros_like(information)
        information[:, keep[:, None], keep[None, :]] = planar
        information[:, 0, 0] = information[:, 1, 1] = planar[:, 0, 0]
        information[:, 5, 5] = 0.5 * (planar[:, 1, 1] + planar[:, 2, 2])
    edges = torch.randint(0, n, (e, 2), generator=generator)
    return PoseGraph(
        ids=torch.tensor([0, 2, 5, 6, 10, 11]),
        poses=T[:n],
        edges=edges,
        measurements=T[n:],
        information=information,
        dimension=dimension,
        fixed=torch.tensor([0, 4]),
    )


@pytest.mark.parametrize("dimension", [3, 2])
def test_round_trip_is_exact_to_printing_precision(dimension, tmp_path, generator):
    graph = _random_graph(dimension, generator)
    path = tmp_path / "graph.g2o"
    g2o.write_g2o(path, graph)
    back = g2o.read_g2o(path)
    assert back.dimension == dimension
    assert torch.equal(back.ids, graph.ids)
    assert torch.equal(back.edges, graph.edges)
    assert torch.equal(back.fixed, graph.fixed)
    # Only the quaternion ↔ matrix (or θ ↔ (cos, sin)) conversions round: a few ulps.
    torch.testing.assert_close(back.poses, graph.poses, rtol=0, atol=1e-14)
    torch.testing.assert_close(back.measurements, graph.measurements, rtol=0, atol=1e-14)
    assert torch.equal(back.information, graph.information)
    # Writing what was read reproduces every number of the file to printing precision.
    again = g2o.format_g2o(back).split()
    first = path.read_text().split()
    assert len(again) == len(first)
    for a, b in zip(again, first, strict=True):
        if a != b:
            assert abs(float(a) - float(b)) <= 1e-14 * max(1.0, abs(float(b)))


def test_write_alternative_poses(tmp_path, generator):
    graph = _random_graph(3, generator)
    poses = se3.exp(torch.randn(6, 6, generator=generator, dtype=torch.float64))
    g2o.write_g2o(tmp_path / "out.g2o", graph, poses)
    back = g2o.read_g2o(tmp_path / "out.g2o")
    torch.testing.assert_close(back.poses, poses, rtol=0, atol=1e-14)
    with pytest.raises(ValueError, match=r"format_g2o: argument 'poses' must have shape"):
        g2o.format_g2o(graph, poses[:3])


def test_read_2d_lifts_into_se3(tmp_path):
    info = np.array([[10.0, 1.0, 2.0], [1.0, 20.0, 3.0], [2.0, 3.0, 50.0]])
    text = "\n".join(
        [
            _line("VERTEX_SE2", 0, 0.0, 0.0, 0.0),
            _line("VERTEX_SE2", 1, 1.0, 2.0, math.pi / 2),
            _line("EDGE_SE2", 0, 1, 1.0, 2.0, math.pi / 2, *_upper(info)),
        ]
    )
    graph = g2o.parse_g2o(text)
    assert graph.dimension == 2
    expected = torch.tensor(
        [[0.0, -1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 2.0], [0.0, 0.0, 1.0, 0.0], [0, 0, 0, 1]],
        dtype=torch.float64,
    )
    torch.testing.assert_close(graph.poses[1], expected, rtol=0, atol=1e-15)
    torch.testing.assert_close(graph.measurements[0], expected, rtol=0, atol=1e-15)
    ours = graph.information[0].numpy()
    keep = [3, 4, 2]  # (x, y, θ) → (v_x, v_y, ω_z)
    np.testing.assert_array_equal(ours[np.ix_(keep, keep)], info)
    np.testing.assert_array_equal(np.diag(ours)[[0, 1, 5]], [50.0, 50.0, 15.0])
    assert np.linalg.eigvalsh(ours).min() > 0
    # Off the planar block and the out-of-plane diagonal, everything is zero.
    mask = np.ones((6, 6), dtype=bool)
    mask[np.ix_(keep, keep)] = False
    mask[[0, 1, 5], [0, 1, 5]] = False
    assert (ours[mask] == 0).all()


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("VERTEX_SE3:QUAT 1 0 0 0 0 0 0", r"VERTEX_SE3:QUAT expects 8 fields after the tag, got 7"),
        ("VERTEX_SE3:QUAT 1 0 0 zero 0 0 0 1", r"expected a number, got 'zero'"),
        ("VERTEX_SE3:QUAT 1 0 0 nan 0 0 0 1", r"expected a finite number, got 'nan'"),
        ("VERTEX_SE3:QUAT 1.5 0 0 0 0 0 0 1", r"expected an integer vertex id, got '1.5'"),
        ("VERTEX_SE3:QUAT 1 0 0 0 0 0 0 0", r"the quaternion \(qx, qy, qz, qw\) is zero"),
        ("VERTEX_XY 1 0 0", r"unknown tag 'VERTEX_XY'"),
        ("EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1", r"EDGE_SE3:QUAT expects 30 fields .* got 9"),
        ("VERTEX_SE2 1 0 0 0", r"VERTEX_SE2 is a 2D tag but line 1 made this a 3D graph"),
        ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1", r"duplicate vertex id 0 \(first defined on line 1\)"),
        (
            "EDGE_SE3:QUAT 0 9 0 0 0 0 0 0 1" + " 1" * 21,
            r"edge refers to vertex id 9, which no VERTEX",
        ),
        ("FIX 4", r"FIX refers to vertex id 4"),
        ("FIX", r"FIX expects at least one vertex id"),
    ],
)
def test_malformed_lines_name_file_and_line(line, message, tmp_path):
    path = tmp_path / "bad.g2o"
    path.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n\n# comment\n" + line + "\n")
    with pytest.raises(ValueError, match=r"bad\.g2o, line 4: " + message):
        g2o.read_g2o(path)


def test_empty_file_is_an_error(tmp_path):
    path = tmp_path / "empty.g2o"
    path.write_text("# nothing\n\n")
    with pytest.raises(ValueError, match=r"empty\.g2o: no vertices"):
        g2o.read_g2o(path)


def test_vertices_only(tmp_path):
    graph = g2o.parse_g2o("VERTEX_SE2 4 1 2 0.5\nVERTEX_SE2 2 0 0 0\n")
    assert graph.num_vertices == 2 and graph.num_edges == 0
    assert graph.ids.tolist() == [2, 4]
    assert graph.information.shape == (0, 6, 6)
    assert g2o.parse_g2o(g2o.format_g2o(graph)).num_vertices == 2


@pytest.mark.parametrize(
    ("name", "vertices", "edges", "odometry"),
    [("sphere2500", 2500, 4949, 2499), ("parking-garage", 1661, 6275, 1660)],
)
def test_shared_posegraph_data(name, vertices, edges, odometry):
    path = DATA / f"{name}.g2o"
    if not path.exists():
        pytest.skip(f"data file {path} is absent (torchslam data fetch posegraph)")
    graph = g2o.read_g2o(path)
    assert graph.num_vertices == vertices
    assert graph.num_edges == edges
    assert graph.ids.tolist() == list(range(vertices))
    assert int(graph.odometry_mask().sum()) == odometry
    torch.testing.assert_close(graph.poses[0], torch.eye(4, dtype=torch.float64))
    assert torch.linalg.eigvalsh(graph.information).min() > 0
    first = graph.information[0]
    if name == "sphere2500":  # README: translation 10·I, rotation ≈ diag(400, 400, 99)
        torch.testing.assert_close(first[3:, 3:], 10 * torch.eye(3, dtype=torch.float64))
        torch.testing.assert_close(
            first.diagonal()[:3],
            torch.tensor([400.0, 400.0, 99.0], dtype=torch.float64),
            rtol=0.01,
            atol=0,
        )
    else:  # README: first edge diag ≈ (1, 1, 1, 4, 4, 4) in g2o's [t, R] order
        torch.testing.assert_close(
            first.diagonal(),
            torch.tensor([4.0, 4.0, 4.0, 1, 1, 1], dtype=torch.float64),
            rtol=0.01,
            atol=0,
        )
