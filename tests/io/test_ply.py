"""PLY reading and writing on small files generated here (no shared data needed)."""

from __future__ import annotations

import struct

import numpy as np
import pytest
import torch

from torchslam.io.ply import read_ply, read_ply_points, write_ply

# A miniature Stanford range scan: obj_info lines, 3 vertices, then a range_grid element whose
# list property holds 0 or 1 vertex index per grid cell (here a 2 × 3 grid).
STANFORD_ASCII = """ply
format ascii 1.0
obj_info is_cyberware_data 1
obj_info num_cols 3
obj_info num_rows 2
element vertex 3
property float x
property float y
property float z
element range_grid 6
property list uchar int vertex_indices
end_header
"""
# The real scans end each vertex line with a space.
STANFORD_ASCII += "-0.06325 0.0359793 0.0420873 \n-0.06275 0.0360343 0.0425949 \n0.5 -1.25 2 \n"
STANFORD_ASCII += "1 0\n0\n1 1\n0\n0\n1 2\n"

STANFORD_POINTS = np.array(
    [[-0.06325, 0.0359793, 0.0420873], [-0.06275, 0.0360343, 0.0425949], [0.5, -1.25, 2.0]]
)


def _write(tmp_path, name: str, content: bytes | str):
    path = tmp_path / name
    path.write_bytes(content.encode("ascii") if isinstance(content, str) else content)
    return path


def _stanford_binary(points: np.ndarray, grid: list[list[int]], order: str = "<") -> bytes:
    fmt = "binary_little_endian" if order == "<" else "binary_big_endian"
    header = (
        f"ply\nformat {fmt} 1.0\nobj_info is_cyberware_data 1\ncomment made in a test\n"
        f"element vertex {len(points)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element range_grid {len(grid)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    body = b"".join(struct.pack(order + "3f", *p) for p in points)
    for cell in grid:
        body += struct.pack(order + "B", len(cell)) + struct.pack(order + f"{len(cell)}i", *cell)
    return header.encode("ascii") + body


def test_read_stanford_ascii_with_range_grid(tmp_path):
    path = _write(tmp_path, "scan.ply", STANFORD_ASCII)
    data = read_ply(path)
    assert data.format == "ascii"
    assert [(e.name, e.count) for e in data.elements] == [("vertex", 3), ("range_grid", 6)]
    assert data.obj_info == ["is_cyberware_data 1", "num_cols 3", "num_rows 2"]
    np.testing.assert_array_equal(data.points(), STANFORD_POINTS.astype(np.float32))
    assert data.points().dtype == np.float64
    grid = data.data["range_grid"]["vertex_indices"]
    assert [g.tolist() for g in grid] == [[0], [], [1], [], [], [2]]
    assert all(g.dtype == np.int32 for g in grid)
    assert sum(len(g) for g in grid) == 3  # one grid cell per vertex, as in the real scans


def test_read_points_skips_range_grid_and_returns_float64_tensor(tmp_path):
    path = _write(tmp_path, "scan.ply", STANFORD_ASCII)
    points = read_ply_points(path)
    assert isinstance(points, torch.Tensor)
    assert points.dtype == torch.float64 and points.shape == (3, 3)
    expected = torch.from_numpy(STANFORD_POINTS.astype(np.float32).astype(np.float64))
    assert torch.equal(points, expected)
    assert "range_grid" not in read_ply(path, elements=("vertex",)).data


def test_crlf_line_endings_are_accepted(tmp_path):
    path = _write(tmp_path, "crlf.ply", STANFORD_ASCII.replace("\n", "\r\n"))
    np.testing.assert_array_equal(read_ply(path).points(), STANFORD_POINTS.astype(np.float32))


@pytest.mark.parametrize("order", ["<", ">"], ids=["little", "big"])
def test_read_stanford_binary_with_range_grid(tmp_path, order):
    grid = [[0], [], [1], [], [], [2]]
    path = _write(tmp_path, "scan.ply", _stanford_binary(STANFORD_POINTS, grid, order))
    data = read_ply(path)
    assert data.comments == ["made in a test"]
    np.testing.assert_array_equal(data.points(), STANFORD_POINTS.astype(np.float32))
    assert [g.tolist() for g in data.data["range_grid"]["vertex_indices"]] == grid


def test_ascii_and_binary_agree_on_mixed_properties(tmp_path):
    header = (
        "element vertex 2\nproperty double x\nproperty double y\nproperty double z\n"
        "property uchar red\nproperty short s\n"
        "element face 1\nproperty uchar flag\nproperty list uchar uint vertex_indices\n"
        "property float area\nend_header\n"
    )
    ascii_file = (
        "ply\nformat ascii 1.0\n" + header + "0.1 0.2 0.3 255 -7\n1e-3 2 3 0 8\n7 3 0 1 1 0.5\n"
    )
    binary = ("ply\nformat binary_little_endian 1.0\n" + header).encode("ascii")
    binary += struct.pack("<3dBh", 0.1, 0.2, 0.3, 255, -7) + struct.pack("<3dBh", 1e-3, 2, 3, 0, 8)
    binary += struct.pack("<BB3If", 7, 3, 0, 1, 1, 0.5)
    for name, content in (("a.ply", ascii_file), ("b.ply", binary)):
        data = read_ply(_write(tmp_path, name, content))
        vertex, face = data.data["vertex"], data.data["face"]
        np.testing.assert_array_equal(data.points(), [[0.1, 0.2, 0.3], [1e-3, 2, 3]])
        assert vertex["red"].dtype == np.uint8 and vertex["red"].tolist() == [255, 0]
        assert vertex["s"].dtype == np.int16 and vertex["s"].tolist() == [-7, 8]
        assert face["flag"].tolist() == [7] and face["area"].tolist() == [0.5]
        assert face["vertex_indices"][0].dtype == np.uint32
        assert face["vertex_indices"][0].tolist() == [0, 1, 1]


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
@pytest.mark.parametrize("coordinate_type", ["double", "float"])
@pytest.mark.parametrize("with_colors", [False, True])
def test_write_read_round_trip(tmp_path, generator, fmt, coordinate_type, with_colors):
    points = torch.randn(50, 3, generator=generator, dtype=torch.float64)
    if coordinate_type == "double":
        points[0] = torch.tensor([1e-300, -1e300, 0.1], dtype=torch.float64)  # extreme, finite
    colors = torch.randint(0, 256, (50, 3), generator=generator) if with_colors else None
    path = tmp_path / "cloud.ply"
    write_ply(path, points, colors, format=fmt, coordinate_type=coordinate_type, comments=["hello"])
    data = read_ply(path)
    assert data.format == fmt and data.comments == ["hello"]
    expected = points.numpy()
    if coordinate_type == "float":
        expected = expected.astype(np.float32).astype(np.float64)
    np.testing.assert_array_equal(data.points(), expected)  # bit-exact
    if with_colors:
        for i, key in enumerate(("red", "green", "blue")):
            assert data.data["vertex"][key].dtype == np.uint8
            np.testing.assert_array_equal(data.data["vertex"][key], colors[:, i].numpy())
    else:
        assert "red" not in data.data["vertex"]


def test_write_float_colors_are_scaled(tmp_path):
    path = tmp_path / "c.ply"
    write_ply(path, np.zeros((2, 3)), np.array([[0.0, 0.5, 1.0], [1.0, 0.0, 0.25]]))
    vertex = read_ply(path).data["vertex"]
    assert vertex["red"].tolist() == [0, 255]
    assert vertex["green"].tolist() == [128, 0]
    assert vertex["blue"].tolist() == [255, 64]


def test_write_empty_cloud(tmp_path):
    path = tmp_path / "empty.ply"
    for fmt in ("ascii", "binary_little_endian"):
        write_ply(path, np.zeros((0, 3)), format=fmt)
        assert read_ply(path).points().shape == (0, 3)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("plx\nformat ascii 1.0\nend_header\n", "line 1: expected 'ply'"),
        ("ply\nformat ascii 1.0\nelement vertex 1\n", "not terminated by an 'end_header'"),
        ("ply\nformat ascii 2.0\nend_header\n", "line 2: expected version '1.0'"),
        ("ply\nformat utf8 1.0\nend_header\n", "line 2: don't understand format 'utf8'"),
        ("ply\nformat ascii 1.0\nelement vertex x\nend_header\n", "line 3: expected 'element"),
        (
            "ply\nformat ascii 1.0\nproperty float x\nend_header\n",
            "line 3: expected one of {element, comment",
        ),
        (
            "ply\nformat ascii 1.0\nelement vertex 1\nproperty real x\nend_header\n",
            "line 4: unknown property type 'real'",
        ),
        (
            "ply\nformat ascii 1.0\nelement f 1\nproperty list float int v\nend_header\n",
            "line 4: list count type must be an integer",
        ),
        ("ply\nformat ascii 1.0\nbogus\nend_header\n", "line 3: expected one of {element"),
        ("ply\nelement vertex 0\nend_header\n", "line 2: expected one of {format"),
    ],
)
def test_malformed_header_names_file_and_line(tmp_path, content, message):
    path = _write(tmp_path, "bad.ply", content)
    with pytest.raises(ValueError, match=message) as info:
        read_ply(path)
    assert "bad.ply" in str(info.value)


def test_truncated_ascii_names_element(tmp_path):
    lines = STANFORD_ASCII.splitlines()
    path = _write(tmp_path, "short.ply", "\n".join(lines[:-3]) + "\n")
    with pytest.raises(ValueError, match=r"short\.ply: element 'range_grid': truncated data"):
        read_ply(path)
    # Only the vertices are needed here, and they are complete.
    assert read_ply_points(path).shape == (3, 3)
    path = _write(tmp_path, "shorter.ply", "\n".join(lines[:13]) + "\n")
    with pytest.raises(ValueError, match="element 'vertex': truncated data, expected 3"):
        read_ply_points(path)


@pytest.mark.parametrize(
    ("bad_line", "message"),
    [
        ("0.5 -1.25", "line 15 \\(element 'vertex'\\): expected 3 values, got 2"),
        ("0.5 -1.25 abc", "line 15 \\(element 'vertex'\\): expected a number, got 'abc'"),
    ],
)
def test_malformed_ascii_vertex_names_line(tmp_path, bad_line, message):
    content = STANFORD_ASCII.replace("0.5 -1.25 2 ", bad_line)
    with pytest.raises(ValueError, match=message):
        read_ply(_write(tmp_path, "bad.ply", content))


def test_misaligned_ascii_vertex_lines_are_caught(tmp_path):
    # Same number of values in total, but one line short and the next long.
    content = STANFORD_ASCII.replace("0.0360343 0.0425949 \n0.5", "0.0360343 \n0.0425949 0.5")
    with pytest.raises(ValueError, match=r"line 14 \(element 'vertex'\): expected 3 values, got 2"):
        read_ply(_write(tmp_path, "bad.ply", content))


def test_malformed_ascii_list_names_line(tmp_path):
    content = STANFORD_ASCII.replace("1 1\n", "2 1\n")
    message = r"line 18 \(element 'range_grid'\): list 'vertex_indices': expected 2 values, got 1"
    with pytest.raises(ValueError, match=message):
        read_ply(_write(tmp_path, "bad.ply", content))
    content = STANFORD_ASCII.replace("1 1\n", "1 1 5\n")
    with pytest.raises(ValueError, match=r"line 18 .*1 unexpected extra value"):
        read_ply(_write(tmp_path, "bad.ply", content))


def test_truncated_binary_names_element(tmp_path):
    full = _stanford_binary(STANFORD_POINTS, [[0], [], [1], [], [], [2]])
    path = _write(tmp_path, "cut.ply", full[:-3])
    with pytest.raises(ValueError, match=r"cut\.ply: element 'range_grid': truncated binary"):
        read_ply(path)
    assert read_ply_points(path).shape == (3, 3)
    header_end = full.index(b"end_header\n") + len(b"end_header\n")
    path = _write(tmp_path, "cut2.ply", full[: header_end + 20])
    with pytest.raises(ValueError, match="element 'vertex': truncated binary data"):
        read_ply_points(path)


def test_unknown_element_request_and_missing_vertex(tmp_path):
    path = _write(tmp_path, "scan.ply", STANFORD_ASCII)
    with pytest.raises(ValueError, match="requested element"):
        read_ply(path, elements=("face",))
    path = _write(
        tmp_path,
        "novertex.ply",
        "ply\nformat ascii 1.0\nelement thing 1\nproperty int a\nend_header\n3\n",
    )
    with pytest.raises(ValueError, match="no vertex element"):
        read_ply(path).points()


def test_write_rejects_bad_input(tmp_path):
    path = tmp_path / "x.ply"
    with pytest.raises(ValueError, match="'points' must have shape \\(N, 3\\)"):
        write_ply(path, np.zeros((4, 2)))
    with pytest.raises(ValueError, match="'colors' must have shape"):
        write_ply(path, np.zeros((4, 3)), np.zeros((3, 3), dtype=np.uint8))
    with pytest.raises(ValueError, match=r"0\.\.255"):
        write_ply(path, np.zeros((1, 3)), np.array([[0, 256, 0]]))
    with pytest.raises(ValueError, match="'format'"):
        write_ply(path, np.zeros((1, 3)), format="binary")  # type: ignore[arg-type]


def test_negative_ascii_list_length_names_line(tmp_path):
    content = STANFORD_ASCII.replace("0\n1 1\n", "0\n-1 1\n").replace("uchar int", "char int")
    with pytest.raises(ValueError, match=r"line 18 \(element 'range_grid'\): expected a list len"):
        read_ply(_write(tmp_path, "bad.ply", content))


def test_header_text_lines_may_hold_any_text(tmp_path):
    # UTF-8 in a comment, an obj_info line after the elements (plyfile alone refuses both).
    content = STANFORD_ASCII.replace("obj_info num_rows 2\n", "comment Créé à Paris\n")
    content = content.replace("end_header\n", "obj_info num_rows 2\nend_header\n")
    data = read_ply(_write(tmp_path, "utf8.ply", content.encode("utf-8")))
    assert data.comments == ["Créé à Paris"]
    assert data.obj_info == ["is_cyberware_data 1", "num_cols 3", "num_rows 2"]
    np.testing.assert_array_equal(data.points(), STANFORD_POINTS.astype(np.float32))


def test_write_rejects_bad_comments(tmp_path):
    path = tmp_path / "x.ply"
    with pytest.raises(ValueError, match="write_ply: comments must be ASCII"):
        write_ply(path, np.zeros((1, 3)), comments=["é"])
    with pytest.raises(TypeError, match="write_ply: argument 'comments' must hold str"):
        write_ply(path, np.zeros((1, 3)), comments=[3])  # type: ignore[list-item]
    write_ply(path, np.zeros((1, 3)), comments="one comment")
    assert read_ply(path).comments == ["one comment"]
