"""g2o files as the public benchmarks ship them (issue 14): edge-only files, information
matrices that are not positive semidefinite (three handlings), the bulk parser's equivalence
with the line-by-line one."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

from torchslam.io import g2o
from torchslam.lie import se3
from torchslam.posegraph import PoseGraph


def _upper(matrix: np.ndarray) -> str:
    rows, cols = np.triu_indices(matrix.shape[0])
    return " ".join(repr(float(x)) for x in matrix[rows, cols])


def _vertex_lines_2d(poses: list[tuple[int, float, float, float]]) -> list[str]:
    return [f"VERTEX_SE2 {vid} {x!r} {y!r} {theta!r}" for vid, x, y, theta in poses]


def _edge_2d(i: int, j: int, pose: tuple[float, float, float], info: np.ndarray) -> str:
    return f"EDGE_SE2 {i} {j} {pose[0]!r} {pose[1]!r} {pose[2]!r} {_upper(info)}"


def _relative_2d(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, float, float]:
    """(x, y, θ) of pose b seen from pose a (both (x, y, θ))."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return (c * dx + s * dy, -s * dx + c * dy, b[2] - a[2])


INFO_2D = np.array([[20.0, 1.0, 0.5], [1.0, 30.0, -0.5], [0.5, -0.5, 100.0]])
# Vertex ids need not be contiguous: 10, 11, 12, 13, 20 (a square walked from 10, and 20).
TRUE_2D = [(10, 0.0, 0.0, 0.0), (11, 1.0, 0.0, 0.5), (12, 1.5, 1.0, 1.7), (13, 0.2, 1.2, 3.0)]
TRUE_2D.append((20, -0.5, 0.3, -2.0))


def _graph_2d_lines() -> tuple[list[str], list[str]]:
    """(vertex lines, edge lines) of an exact 2D graph: odometry 10→11→12→13, a reversed
    odometry edge stored 20 → 13 (index 4 → 3), and loop closures 10 → 12 and 20 → 10."""
    pose = {vid: (x, y, t) for vid, x, y, t in TRUE_2D}
    pairs = [(10, 11), (10, 12), (11, 12), (12, 13), (20, 13), (20, 10)]
    edges = [_edge_2d(i, j, _relative_2d(pose[i], pose[j]), INFO_2D) for i, j in pairs]
    return _vertex_lines_2d(TRUE_2D), edges


# ---------------------------------------------------------------------------- edge-only files


def test_edge_only_file_gives_the_graph_of_the_file_with_vertices(tmp_path):
    vertices, edges = _graph_2d_lines()
    (tmp_path / "full.g2o").write_text("\n".join(vertices + edges) + "\n")
    (tmp_path / "edges.g2o").write_text("# edges only\n" + "\n".join(edges) + "\n")
    full = g2o.read_g2o(tmp_path / "full.g2o")
    edge_only = g2o.read_g2o(tmp_path / "edges.g2o")
    assert full.source.has_vertices and not edge_only.source.has_vertices
    assert edge_only.ids.tolist() == [10, 11, 12, 13, 20]
    for name in ("ids", "edges", "measurements", "information", "fixed"):
        assert torch.equal(getattr(edge_only, name), getattr(full, name)), name
    assert edge_only.dimension == 2
    # The measurements are exact, so chaining them along any spanning tree gives the true
    # poses: products of ≤ 4 rotations and translations of size ~1, a few ulps each.
    torch.testing.assert_close(edge_only.poses, full.poses, rtol=0, atol=1e-14)


def test_spanning_tree_prefers_odometry_over_loop_closures():
    """The loop closure 0 → 2 is listed before the odometry 1 → 2 and disagrees with it: the
    tree reaches vertex 2 through the odometry chain; vertex 3 through a reversed odometry
    edge; vertex 5 only through a loop closure (no odometry edge reaches it)."""
    info = _upper(np.diag([1.0, 1.0, 1.0]))
    text = "\n".join(
        [
            f"EDGE_SE2 0 1 1 0 0 {info}",
            f"EDGE_SE2 0 2 5 5 0 {info}",  # wrong loop closure: odometry says (2, 0, 0)
            f"EDGE_SE2 1 2 1 0 0 {info}",
            f"EDGE_SE2 3 2 -1 0 0 {info}",  # reversed: 3 seen from... T_3⁻¹T_2 = −1 in x
            f"EDGE_SE2 0 5 0 7 1.5707963267948966 {info}",
        ]
    )
    graph = g2o.parse_g2o(text)
    x = graph.poses[:, 0, 3].tolist()
    y = graph.poses[:, 1, 3].tolist()
    assert x[:4] == [0.0, 1.0, 2.0, 3.0]  # exact sums of 1.0 (identity rotations)
    assert y[:4] == [0.0, 0.0, 0.0, 0.0]
    assert (x[4], y[4]) == (0.0, 7.0)
    torch.testing.assert_close(
        graph.poses[4, :2, :2],
        torch.tensor([[0.0, -1.0], [1.0, 0.0]], dtype=torch.float64),
        rtol=0,
        atol=1e-16,
    )


def test_edge_only_3d_file_is_chained_from_the_identity(generator):
    truth = se3.exp(torch.randn(4, 6, generator=generator, dtype=torch.float64))
    truth[0] = torch.eye(4, dtype=torch.float64)
    edges = torch.tensor([[0, 1], [1, 2], [2, 3], [3, 0]])
    graph = PoseGraph(
        ids=torch.arange(4),
        poses=truth,
        edges=edges,
        measurements=se3.inverse(truth[edges[:, 0]]) @ truth[edges[:, 1]],
        information=torch.eye(6, dtype=torch.float64).expand(4, 6, 6),
    )
    text = g2o.format_g2o(graph)
    edge_only = g2o.parse_g2o("\n".join(ln for ln in text.split("\n") if "VERTEX" not in ln))
    assert not edge_only.source.has_vertices
    # Exact measurements (to printing precision, ~1e-16) chained over ≤ 3 edges.
    torch.testing.assert_close(edge_only.poses, truth, rtol=0, atol=1e-13)


def test_disconnected_edge_only_file_names_the_unreachable_vertex(tmp_path):
    info = _upper(np.eye(3))
    path = tmp_path / "split.g2o"
    path.write_text(f"EDGE_SE2 1 2 1 0 0 {info}\nEDGE_SE2 7 9 1 0 0 {info}\n")
    with pytest.raises(
        ValueError,
        match=r"split\.g2o: edge-only file .*vertex id 7 is not "
        r"connected to vertex id 1",
    ):
        g2o.read_g2o(path)


def test_partial_vertices_still_need_every_vertex(tmp_path):
    """Only a file without any VERTEX line is edge-only; otherwise a missing vertex is an error."""
    info = _upper(np.eye(3))
    text = f"VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 {info}\n"
    with pytest.raises(ValueError, match=r"line 2: edge refers to vertex id 1, which no VERTEX"):
        g2o.parse_g2o(text)
    with pytest.raises(ValueError, match=r"line 2: FIX refers to vertex id 3, which no edge"):
        g2o.parse_g2o(f"EDGE_SE2 0 1 1 0 0 {info}\nFIX 3\n")
    assert g2o.parse_g2o(f"EDGE_SE2 0 1 1 0 0 {info}\nFIX 1\n").fixed.tolist() == [1]


# -------------------------------------------------------- information that is not PSD

# g2o order [translation, rotation]: both 3 × 3 diagonal blocks positive definite, the cross
# block large enough to make the 6 × 6 matrix indefinite (as in a real dataset).
INDEFINITE_3D = np.diag([10.0, 10.0, 10.0, 40.0, 40.0, 40.0])
INDEFINITE_3D[0, 3] = INDEFINITE_3D[3, 0] = 30.0  # 30² > 10 · 40
GOOD_3D = np.diag([10.0, 10.0, 10.0, 40.0, 40.0, 40.0])
GOOD_3D[1, 4] = GOOD_3D[4, 1] = 5.0


def _file_3d(tmp_path):
    identity = "0 0 0 0 0 0 1"
    lines = [f"VERTEX_SE3:QUAT {k} {k} 0 0 0 0 0 1" for k in range(3)]
    lines += [
        f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {_upper(GOOD_3D)}",
        f"EDGE_SE3:QUAT 1 2 {identity} {_upper(INDEFINITE_3D)}",
        f"EDGE_SE3:QUAT 0 2 2 0 0 0 0 0 1 {_upper(INDEFINITE_3D)}",
    ]
    path = tmp_path / "indefinite.g2o"
    path.write_text("\n".join(lines) + "\n")
    return path


def _ours(g2o_matrix: np.ndarray) -> torch.Tensor:
    order = [3, 4, 5, 0, 1, 2]
    return torch.from_numpy(g2o_matrix[np.ix_(order, order)])


def test_strict_refuses_with_file_and_line(tmp_path):
    path = _file_3d(tmp_path)
    with pytest.raises(
        ValueError,
        match=r"indefinite\.g2o, line 5: the information matrix is "
        r"not positive semidefinite \(information='strict'; 2 of 3 edges",
    ):
        g2o.read_g2o(path, information="strict")


def test_repair_keeps_the_diagonal_blocks_and_counts_the_edges(tmp_path):
    path = _file_3d(tmp_path)
    with pytest.warns(UserWarning, match=r"2 of 3 edges .*the first on line 5.*'repair'"):
        graph = g2o.read_g2o(path)
    assert graph.source.information == "repair"
    assert graph.source.adjusted_edges == (1, 2)
    assert graph.source.adjusted_lines == (5, 6)
    assert torch.equal(graph.information[0], _ours(GOOD_3D))  # untouched, bit for bit
    block_diagonal = INDEFINITE_3D.copy()
    block_diagonal[:3, 3:] = block_diagonal[3:, :3] = 0.0
    for e in (1, 2):
        assert torch.equal(graph.information[e], _ours(block_diagonal))


def test_nearest_clips_the_eigenvalues(tmp_path):
    path = _file_3d(tmp_path)
    with pytest.warns(UserWarning, match="'nearest'"):
        graph = g2o.read_g2o(path, information="nearest")
    assert graph.source.adjusted_edges == (1, 2)
    assert torch.equal(graph.information[0], _ours(GOOD_3D))
    original = _ours(INDEFINITE_3D)
    nearest = graph.information[1]
    eigenvalues = torch.linalg.eigvalsh(nearest)
    # Floor 1e-6 × the largest eigenvalue (~58), up to the round-off of eigh at that scale.
    assert float(eigenvalues.min()) >= 1e-6 * float(eigenvalues.max()) * (1 - 1e-6)
    # Eigenvalues above the floor and the eigenvectors are kept, so it is at least as near
    # (Frobenius) to the file's matrix as the repaired one.
    block_diagonal = original.clone()
    block_diagonal[:3, 3:] = block_diagonal[3:, :3] = 0.0
    assert torch.linalg.norm(nearest - original) < torch.linalg.norm(block_diagonal - original)
    # One eigenvalue of the original is negative (those of [[10, 30], [30, 40]] are
    # 25 ± √1125): only it is clipped; the others agree to eigh's round-off (~1e-15 relative).
    before = torch.linalg.eigvalsh(original)
    assert int((before < 0).sum()) == 1
    torch.testing.assert_close(eigenvalues[1:], before[1:], rtol=1e-12, atol=0)


def test_repair_fails_when_a_diagonal_block_is_indefinite_but_nearest_reads_it(tmp_path):
    bad = np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # xy block: λ = −1
    path = tmp_path / "xy.g2o"
    path.write_text(f"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 {_upper(bad)}\n")
    with pytest.raises(
        ValueError,
        match=r"xy\.g2o, line 3: the information matrix is not "
        r"positive semidefinite, nor is its translation or rotation block",
    ):
        g2o.read_g2o(path)
    with pytest.warns(UserWarning):
        graph = g2o.read_g2o(path, information="nearest")
    assert float(torch.linalg.eigvalsh(graph.information[0]).min()) > 0


def test_repair_in_2d_drops_the_theta_cross_terms():
    planar = np.array([[4.0, 0.5, 3.0], [0.5, 4.0, 0.0], [3.0, 0.0, 2.0]])  # 9 > 4 · 2
    assert np.linalg.eigvalsh(planar).min() < 0
    text = f"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 {_upper(planar)}\n"
    with pytest.warns(UserWarning, match="1 of 1 edges"):
        graph = g2o.parse_g2o(text)
    keep = [3, 4, 2]  # (x, y, θ) → (v_x, v_y, ω_z)
    expected = planar.copy()
    expected[:2, 2] = expected[2, :2] = 0.0
    assert np.array_equal(graph.information[0].numpy()[np.ix_(keep, keep)], expected)


def test_no_warning_and_nothing_adjusted_for_positive_definite_files(tmp_path):
    vertices, edges = _graph_2d_lines()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        graph = g2o.parse_g2o("\n".join(vertices + edges))
    assert graph.source.adjusted_edges == ()


def test_information_argument_is_checked(tmp_path):
    with pytest.raises(ValueError, match=r"parse_g2o: argument 'information' must be one of"):
        g2o.parse_g2o("VERTEX_SE2 0 0 0 0\n", information="clip")
    with pytest.raises(TypeError, match=r"read_g2o: argument 'information' must be a str"):
        g2o.read_g2o(_file_3d(tmp_path), information=None)


# ------------------------------------------------- bulk parser vs line-by-line parser


def test_unusual_blanks_take_the_line_by_line_parser_with_the_same_result():
    """A form feed / no-break space between fields is white space for str.split but not for
    the bulk parser, which hands the file to the line-by-line parser: same graph, bit for bit.
    """
    vertices, edges = _graph_2d_lines()
    text = "\n".join(vertices + edges) + "\nFIX 10\n"
    odd = text.replace("EDGE_SE2 10 12 ", "EDGE_SE2\u00a010\x0c12 ", 1)
    a, b = g2o.parse_g2o(text), g2o.parse_g2o(odd)
    for name in ("ids", "poses", "edges", "measurements", "information", "fixed"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


@pytest.mark.parametrize(
    ("token", "message"),
    [
        ("1_0", r"expected a number, got '1_0'"),
        ("١", r"expected a number, got '١'"),
        ("1e999", r"expected a finite number"),
        ("0x10", r"expected a number, got '0x10'"),
        ("1e", r"expected a number, got '1e'"),
    ],
)
def test_numbers_the_bulk_parser_cannot_vouch_for_name_their_line(token, message):
    vertices, edges = _graph_2d_lines()
    edges[2] = edges[2].replace(" 20.0 ", f" {token} ", 1)
    with pytest.raises(ValueError, match=rf"<string>, line 8: {message}"):
        g2o.parse_g2o("\n".join(vertices + edges))


def test_bulk_scan_never_accepts_what_the_line_scan_refuses():
    """Seeded: one token of a valid file replaced by a tricky one. Whenever the bulk scan
    vouches for the file, the line-by-line scan accepts it too, with the same numbers."""
    import random

    from torchslam.io.g2o import _scan_fast, _scan_lines, _Unsure

    vertices, edges = _graph_2d_lines()
    lines = [*vertices, "FIX 10", *edges]
    tricky = [
        "1_0",
        "١",
        "nan",
        "-inf",
        "1e999",
        "1e-400",
        "+.5",
        "1.",
        ".",
        "-",
        "1e+",
        "007",
        "+3",
        "-3",
        "9" * 30,
        "0x1",
        "1e5",
        "",
        "1 2",
        "\t4",
        "EDGE_SE2",
        "#",
    ]
    rng = random.Random(14)

    def fail(lineno: int, message: str) -> ValueError:
        return ValueError(message)

    vouched = 0
    for _ in range(300):
        k = rng.randrange(len(lines))
        words = lines[k].split()
        words[rng.randrange(len(words))] = rng.choice(tricky)
        case = [*lines[:k], " ".join(words), *lines[k + 1 :]]
        try:
            fast = _scan_fast(case)
        except _Unsure:
            continue
        vouched += 1
        slow = _scan_lines(case, fail)  # must not raise
        assert fast.vertex_ids == slow.vertex_ids and fast.edge_ids == slow.edge_ids
        assert fast.fixed_ids == slow.fixed_ids
        assert np.array_equal(fast.vertex_values, slow.vertex_values)
        assert np.array_equal(fast.edge_values, slow.edge_values)
    assert vouched > 20  # the bulk scan does take the plain replacements
