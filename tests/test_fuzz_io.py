"""Seeded fuzz of the readers: corrupted files give a ValueError naming the file, or a sound result.

Small valid files (PLY ascii / binary little- and big-endian with a list element, 3D and 2D g2o,
a Stanford ``.conf``) are corrupted at random (``random.Random`` with a fixed seed per case) and
read back. Every read must end in one of two ways:

- a ``ValueError`` whose message names the file, and the line ("line") for the text formats
  (binary PLY names a header line, or the element / instance / byte offset);
- a result that is sound: every float finite, every pose a rigid transform, every information
  matrix symmetric. For corruptions that can only break a file (NaN / Inf / overflowing tokens,
  Latin-1 bytes, binary garbage, NaN written into binary floats), a result must moreover equal
  the parse of the valid file (the corruption hit something the reader ignores, e.g. a
  comment or the ``camera`` line of a ``.conf``). Truncations, byte flips, finite huge numbers
  and deleted or repeated lines can turn a file into another valid one: for those soundness is
  the requirement.

Any other exception (UnicodeDecodeError, OverflowError, IndexError, struct.error, …) fails.
"""

from __future__ import annotations

import math
import random
import struct

import numpy as np
import pytest
import torch

from torchslam.io.g2o import read_g2o
from torchslam.io.ply import read_ply
from torchslam.io.stanford import read_conf

ROUNDS = 25  # corruptions per (format, kind)

# ----------------------------------------------------------------------------- valid files

_VERTICES = [
    (0.5, -1.25, 2.0, 255, -3),
    (0.125, 0.25, 1e-3, 0, 7),
    (-4.0, 3.5, 0.75, 128, 0),
    (1e3, -2e-3, 3.25, 17, 2147483647),
    (0.0, 0.0, -0.5, 1, -2147483648),
    (2.5, 2.5, 2.5, 42, 12),
]
_FACES = [([0, 1, 2], 7), ([2, 3, 4, 5], 65535)]
_PLY_HEADER = (
    "ply\nformat {fmt} 1.0\ncomment fuzz me\nelement vertex 6\nproperty float x\n"
    "property float y\nproperty double z\nproperty uchar red\nproperty int label\n"
    "element face 2\nproperty list uchar int vertex_indices\nproperty ushort flags\nend_header\n"
)
# Byte offsets of the float fields of vertex k in the binary body (record: f4 f4 f8 u1 i4).
_VERTEX_SIZE = 4 + 4 + 8 + 1 + 4
_FLOAT_FIELDS = ((0, "f"), (4, "f"), (8, "d"))


def ply_ascii() -> bytes:
    rows = [f"{x!r} {y!r} {z!r} {r} {k}" for x, y, z, r, k in _VERTICES]
    rows += [f"{len(f)} {' '.join(map(str, f))} {flags}" for f, flags in _FACES]
    return (_PLY_HEADER.format(fmt="ascii") + "\n".join(rows) + "\n").encode("ascii")


def ply_binary(order: str) -> bytes:
    fmt = "binary_little_endian" if order == "<" else "binary_big_endian"
    body = b"".join(struct.pack(order + "ffdBi", *v) for v in _VERTICES)
    for face, flags in _FACES:
        body += struct.pack(order + f"B{len(face)}iH", len(face), *face, flags)
    return _PLY_HEADER.format(fmt=fmt).encode("ascii") + body


def g2o_3d() -> bytes:
    lines = ["# a small 3D graph"]
    for i in range(4):
        q = np.array([0.1 * i, -0.2, 0.3 * i, 1.0])
        q /= np.linalg.norm(q)
        lines.append(
            f"VERTEX_SE3:QUAT {i} {i * 1.5} {-0.5 * i} 0.25 " + " ".join(repr(float(v)) for v in q)
        )
    info = "100 0 0 0 0 0 100 0 0 0 0 100 0 0 0 400 0 0 400 0 400"
    for i, j in ((0, 1), (1, 2), (2, 3), (3, 0)):
        lines.append(f"EDGE_SE3:QUAT {i} {j} 1.5 -0.5 0 0 0 0.0998 0.995 {info}")
    lines.append("FIX 0")
    return ("\n".join(lines) + "\n").encode("ascii")


def g2o_2d() -> bytes:
    lines = [f"VERTEX_SE2 {i} {i * 0.5} {1.0 - i} {0.3 * i}" for i in range(4)]
    lines += [f"EDGE_SE2 {i} {i + 1} 0.5 -1 0.3 50 0 0 50 0 200" for i in range(3)]
    return ("\n".join(lines) + "\n").encode("ascii")


def conf() -> bytes:
    return (
        "camera -0.0172 -0.0936 -0.734 -0.0461723 0.970603 -0.235889 0.0124573\n"
        "bmesh bun000.ply 0 0 0 0 0 0 1\n"
        "bmesh bun045.ply -0.0520211 -0.000383981 -0.0109223 0.00548449 -0.294635 "
        "-0.0038555 0.955586\n"
        "bmesh top2.ply -0.0609 0.0155 -0.0287 0.5 0.5 -0.5 0.5\n"
    ).encode("ascii")


FORMATS = {
    "ply_ascii": (ply_ascii, read_ply, True),
    "ply_le": (lambda: ply_binary("<"), read_ply, False),
    "ply_be": (lambda: ply_binary(">"), read_ply, False),
    "g2o_3d": (g2o_3d, read_g2o, True),
    "g2o_2d": (g2o_2d, read_g2o, True),
    "conf": (conf, read_conf, True),
}

# ----------------------------------------------------------------------------- corruptions

# Corruptions that can only break a file: a successful read must equal the valid parse.
MUST_FAIL = ("nan", "overflow", "latin1", "garbage")
# Corruptions that may make another valid file: a successful read must be sound.
MAY_PASS = ("truncate", "flip", "huge", "delete_line", "repeat_line")


def _body_start(data: bytes) -> int:
    end = data.find(b"end_header\n")
    return end + len(b"end_header\n") if end >= 0 else 0


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _replace_token(rng: random.Random, data: bytes, choices: list[str]) -> bytes:
    """Replace one number (anywhere in a text file, header included) by one of choices."""
    lines = data.decode("ascii").split("\n")
    candidates = [
        (i, j)
        for i, line in enumerate(lines)
        for j, token in enumerate(line.split())
        if _is_number(token)
    ]
    i, j = rng.choice(candidates)
    words = lines[i].split()
    words[j] = rng.choice(choices)
    lines[i] = " ".join(words)
    return "\n".join(lines).encode("ascii")


def corrupt(rng: random.Random, data: bytes, kind: str, text: bool) -> bytes:
    if kind == "truncate":
        return data[: rng.randrange(len(data))]
    if kind == "flip":
        out = bytearray(data)
        for _ in range(rng.randint(1, 3)):
            out[rng.randrange(len(out))] = rng.randrange(256)
        return bytes(out)
    if kind == "latin1":
        k = rng.randrange(len(data) + 1)
        return data[:k] + rng.choice([b"\xe9", b"\xe0", b"\xfc", b"\xb0"]) + data[k:]
    if kind == "garbage":
        k = rng.randrange(len(data) + 1)
        chunk = bytes(rng.randrange(256) for _ in range(rng.randint(1, 12))) + b"\xff"
        return data[:k] + chunk + data[k:]
    if kind in ("delete_line", "repeat_line"):
        lines = data.split(b"\n")
        k = rng.randrange(len(lines))
        if kind == "delete_line":
            return b"\n".join(lines[:k] + lines[k + 1 :])
        return b"\n".join(lines[: k + 1] + lines[k:])
    if text:
        choices = {
            "nan": ["nan", "NaN", "-nan", "inf", "-Infinity", "+inf"],
            "overflow": ["1e400", "-1e999", "1.5e309"],
            "huge": ["1e300", "-1e300", "1e-320", "1e39", "1" + "0" * 30, "4294967296", "300"],
        }[kind]
        return _replace_token(rng, data, choices)
    # Binary PLY: write a NaN / Inf into a float field, or declare a huge count.
    start = _body_start(data)
    order = "<" if b"binary_little_endian" in data[:start] else ">"
    if kind == "nan":
        offset, code = rng.choice(_FLOAT_FIELDS)
        position = start + rng.randrange(len(_VERTICES)) * _VERTEX_SIZE + offset
        value = rng.choice([math.nan, math.inf, -math.inf])
        out = bytearray(data)
        struct.pack_into(order + code, out, position, value)
        return bytes(out)
    if kind == "overflow":
        return data.replace(b"element vertex 6", b"element vertex 1" + b"0" * 30, 1)
    # huge: a large but finite value (float32 max or 1e300 in the double)
    out = bytearray(data)
    position = start + rng.randrange(len(_VERTICES)) * _VERTEX_SIZE
    if rng.random() < 0.5:
        struct.pack_into(order + "f", out, position, 3.4028234e38)
    else:
        struct.pack_into(order + "d", out, position + 8, -1e300)
    return bytes(out)


# ----------------------------------------------------------------------------- oracle


def _assert_sound(result) -> None:
    """Finite floats everywhere, rigid poses, symmetric information."""
    if isinstance(result, dict):  # read_conf
        poses = torch.stack(list(result.values()))
        _assert_rigid(poses)
        return
    if hasattr(result, "poses"):  # PoseGraph
        _assert_rigid(result.poses)
        _assert_rigid(result.measurements)
        info = result.information
        assert bool(torch.isfinite(info).all())
        assert torch.equal(info, info.transpose(-1, -2))
        assert bool((result.edges >= 0).all() and (result.edges < result.num_vertices).all())
        assert bool((result.ids >= 0).all())
        return
    for element in result.data.values():  # PlyData
        for values in element.values():
            for array in values if isinstance(values, list) else [values]:
                if array.dtype.kind == "f":
                    assert np.isfinite(array).all()


def _assert_rigid(T: torch.Tensor) -> None:
    if T.numel() == 0:  # e.g. a truncated graph without edges
        return
    assert bool(torch.isfinite(T).all())
    R = T[..., :3, :3]
    identity = torch.eye(3, dtype=T.dtype).expand_as(R)
    # Unit quaternions → rotation matrices: orthonormal to a few ulps of 1.
    assert float((R.transpose(-1, -2) @ R - identity).abs().max()) < 1e-12
    assert bool((torch.linalg.det(R) > 0).all())
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T.dtype).expand((*T.shape[:-2], 4))
    assert torch.equal(T[..., 3, :], bottom)


def _assert_same(result, reference) -> None:
    if isinstance(result, dict):
        assert list(result) == list(reference)
        for key in result:
            assert torch.equal(result[key], reference[key])
    elif hasattr(result, "poses"):
        for name in ("ids", "poses", "edges", "measurements", "information", "fixed"):
            assert torch.equal(getattr(result, name), getattr(reference, name)), name
        assert result.dimension == reference.dimension
    else:
        assert result.format == reference.format and result.elements == reference.elements
        for name, element in reference.data.items():
            for prop, values in element.items():
                got = result.data[name][prop]
                if isinstance(values, list):
                    assert len(got) == len(values)
                    for a, b in zip(got, values, strict=True):
                        np.testing.assert_array_equal(a, b)
                else:
                    np.testing.assert_array_equal(got, values)
                    assert got.dtype == values.dtype


@pytest.mark.parametrize("kind", MUST_FAIL + MAY_PASS)
@pytest.mark.parametrize("fmt", list(FORMATS))
def test_corrupted_file_is_an_error_naming_file_or_a_sound_result(fmt, kind, tmp_path):
    make, reader, text = FORMATS[fmt]
    valid = make()
    suffix = fmt.split("_")[0]
    reference_path = tmp_path / f"valid.{suffix}"
    reference_path.write_bytes(valid)
    reference = reader(reference_path)
    _assert_sound(reference)
    rng = random.Random(f"{fmt}/{kind}")  # str seeds are hashed deterministically (SHA-512)
    outcomes = {"error": 0, "same": 0, "other": 0}
    for round_ in range(ROUNDS):
        data = corrupt(rng, valid, kind, text)
        path = tmp_path / f"case{round_}.{suffix}"
        path.write_bytes(data)
        try:
            result = reader(path)
        except ValueError as error:
            message = str(error)
            assert path.name in message, message
            if text:
                assert "line" in message, message
            else:
                assert any(w in message for w in ("line", "element", "byte")), message
            assert "\n" not in message
            outcomes["error"] += 1
            continue
        _assert_sound(result)
        if kind in MUST_FAIL:
            _assert_same(result, reference)
            outcomes["same"] += 1
        else:
            outcomes["other"] += 1
    if kind in MUST_FAIL and (fmt != "conf" or kind != "nan"):
        # Most of these corruptions land in data the reader checks (the .conf's camera line,
        # which it ignores, takes a larger share of the tokens).
        assert outcomes["error"] >= ROUNDS // 2, outcomes


def test_ply_ascii_values_parse_exactly_as_their_type(tmp_path):
    """The reported cases: uchar 300 is not 44, int 2.7 is not 2, NaN is not a coordinate."""
    rows = ["1 2 3 4 5"] * 2
    header = (
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
        "property float z\nproperty uchar red\nproperty int label\nend_header\n"
    )
    path = tmp_path / "v.ply"
    for bad, fragment in (
        ("1 2 3 300 5", "uchar in [0, 255], got 300"),
        ("1 2 3 4 2.7", "int, got '2.7'"),
        ("1 nan 3 4 5", "finite number, got 'nan'"),
        ("1 2 1e39 4 5", "overflows the type float"),
        ("1 2 3 -1 5", "uchar in [0, 255], got -1"),
        ("1 2 3 4 1_0", "int, got '1_0'"),
    ):
        path.write_text(header + "\n".join([rows[0], bad]) + "\n")
        with pytest.raises(ValueError, match=r"v\.ply: line 11 \(element 'vertex'\)") as info:
            read_ply(path)
        assert fragment in str(info.value)


def test_binary_ply_non_finite_names_the_instance(tmp_path):
    data = bytearray(ply_binary("<"))
    struct.pack_into("<d", data, _body_start(bytes(data)) + 3 * _VERTEX_SIZE + 8, math.inf)
    path = tmp_path / "b.ply"
    path.write_bytes(bytes(data))
    with pytest.raises(
        ValueError, match=r"b\.ply: element 'vertex', instance 3 of 6: property 'z'"
    ):
        read_ply(path)


@pytest.mark.parametrize(
    ("quaternion", "expected"),
    [
        ("1e200 1e200 0 0", [[0, 1, 0], [1, 0, 0], [0, 0, -1]]),  # 180° about (1, 1, 0)/√2
        ("1e-200 0 0 0", [[1, 0, 0], [0, -1, 0], [0, 0, -1]]),  # 180° about x
        ("0 0 0 5e-324", [[1, 0, 0], [0, 1, 0], [0, 0, 1]]),  # the smallest subnormal w
        ("0 0 1e308 1e308", [[0, -1, 0], [1, 0, 0], [0, 0, 1]]),  # 90° about z
    ],
)
def test_g2o_quaternions_normalize_robustly(quaternion, expected, tmp_path):
    path = tmp_path / "q.g2o"
    path.write_text(f"VERTEX_SE3:QUAT 0 1 2 3 {quaternion}\n")
    R = read_g2o(path).poses[0, :3, :3]
    # The scaled quaternion has entries 0, 1/√2 or 1: R is exact to a few ulps.
    torch.testing.assert_close(R, torch.tensor(expected, dtype=torch.float64), atol=1e-15, rtol=0)


@pytest.mark.parametrize(
    ("line", "fragment"),
    [
        ("VERTEX_SE3:QUAT 1" + "0" * 30 + " 0 0 0 0 0 0 1", "integer vertex id in [0, "),
        ("VERTEX_SE3:QUAT -1 0 0 0 0 0 0 1", "integer vertex id in [0, "),
        ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1e-400", "quaternion (qx, qy, qz, qw) is zero"),
        ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 -inf", "expected a finite number, got '-inf'"),
        ("VERTEX_SE3:QUAT ٣ 0 0 0 0 0 0 1", "expected an integer vertex id, got '٣'"),
    ],
)
def test_g2o_bad_numbers_name_file_and_line(line, fragment, tmp_path):
    path = tmp_path / "n.g2o"
    path.write_text("# header\n" + line + "\n", encoding="utf-8")
    with pytest.raises(ValueError, match=r"n\.g2o, line 2: ") as info:
        read_g2o(path)
    assert fragment in str(info.value)


def test_g2o_information_must_be_positive_semidefinite(tmp_path):
    path = tmp_path / "i.g2o"
    vertices = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n"
    path.write_text(vertices + "EDGE_SE2 0 1 1 0 0 1 2 0 1 0 1\n")  # [[1, 2], [2, 1]]: λ = −1
    with pytest.raises(ValueError, match=r"i\.g2o, line 3: the information matrix is not pos"):
        read_g2o(path)
    path.write_text(vertices + "EDGE_SE2 0 1 1 0 0 1 1 0 1 0 0\n")  # singular is fine
    assert read_g2o(path).num_edges == 1


def test_text_readers_reject_binary_with_file_and_line(tmp_path):
    for name, reader in (("x.g2o", read_g2o), ("x.conf", read_conf)):
        path = tmp_path / name
        path.write_bytes(b"# fine\n" + bytes(range(256)))
        with pytest.raises(ValueError, match=rf"{name.replace('.', '[.]')}: line 2: not a text"):
            reader(path)


def test_conf_nan_names_file_and_line(tmp_path):
    path = tmp_path / "c.conf"
    path.write_text("camera 0 0 0 0 0 0 1\nbmesh a.ply 0 nan 0 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"c\.conf: line 2: .*finite number, got 'nan'"):
        read_conf(path)
    path.write_text("camera 0 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"c\.conf: no 'bmesh' lines"):
        read_conf(path)


def test_readers_accept_crlf_and_keep_line_numbers(tmp_path):
    path = tmp_path / "crlf.g2o"
    path.write_bytes(b"VERTEX_SE2 0 0 0 0\r\n\x0c\r\nVERTEX_SE2 0 1 0 0\r\n")
    with pytest.raises(ValueError, match=r"crlf\.g2o, line 3: duplicate vertex id 0"):
        read_g2o(path)
