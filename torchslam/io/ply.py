"""PLY point clouds: read ascii / binary (little- and big-endian), write ascii / binary.

numpy only. The reader is generic (any elements, scalar and list properties) and handles the
Stanford 3D Scanning Repository range scans, whose header has ``obj_info`` lines and whose
vertices are followed by a ``range_grid`` element with a list property::

    element vertex 40256          property float x / y / z
    element range_grid 204800     property list uchar int vertex_indices
    end_header

In ascii files every element instance is one line, as written by every common PLY tool; this
lets error messages name the line. Malformed headers and truncated or malformed data raise a
``ValueError`` that names the file, and the header line or the element and instance.
"""

from __future__ import annotations

import os
import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "PlyData",
    "PlyElement",
    "PlyProperty",
    "read_ply",
    "read_ply_points",
    "write_ply",
]

PlyFormat = Literal["ascii", "binary_little_endian", "binary_big_endian"]

# PLY scalar type names (both spellings of the spec) → numpy kind and size.
_TYPES: dict[str, str] = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
_END_HEADER = re.compile(rb"end_header[ \t]*\r?\n")


@dataclass(frozen=True)
class PlyProperty:
    """One property of a PLY element."""

    # property name, e.g. "x" or "vertex_indices"
    name: str
    # numpy kind of the values, e.g. "f4" (byte order is applied when reading)
    dtype: str
    # numpy kind of the list length for list properties, None for scalar properties
    count_dtype: str | None = None

    @property
    def is_list(self) -> bool:
        return self.count_dtype is not None


@dataclass(frozen=True)
class PlyElement:
    """An element declared in a PLY header, e.g. ``vertex`` with its properties."""

    # element name, e.g. "vertex"
    name: str
    # number of instances
    count: int
    # properties in file order
    properties: tuple[PlyProperty, ...]


@dataclass
class PlyData:
    """Contents of a PLY file.

    ``data[element][property]`` is a numpy array of shape (count,) for scalar properties (in
    the file's type) and a list of ``count`` 1-D arrays for list properties. Elements that
    were not requested when reading are declared in ``elements`` but absent from ``data``.
    """

    # "ascii", "binary_little_endian" or "binary_big_endian"
    format: str
    # elements declared in the header, in file order
    elements: tuple[PlyElement, ...]
    # element name → property name → values
    data: dict[str, dict[str, np.ndarray | list[np.ndarray]]]
    # "comment" lines of the header, without the keyword
    comments: list[str] = field(default_factory=list)
    # "obj_info" lines of the header, without the keyword
    obj_info: list[str] = field(default_factory=list)

    def points(self) -> np.ndarray:
        """Vertex coordinates x, y, z as float64, shape (N, 3)."""
        vertex = self.data.get("vertex")
        if vertex is None or not all(k in vertex for k in ("x", "y", "z")):
            raise ValueError("PlyData.points: the file has no vertex element with x, y, z")
        return np.stack([np.asarray(vertex[k], dtype=np.float64) for k in ("x", "y", "z")], -1)


def _error(path: str | os.PathLike, what: str) -> ValueError:
    return ValueError(f"read_ply: {os.fspath(path)}: {what}")


def _parse_header(path: str | os.PathLike, lines: list[str]) -> tuple[str, list, list, list]:
    """Parse header lines (without 'end_header'). Returns format, elements, comments, obj_info."""
    if not lines or lines[0].strip() != "ply":
        first = lines[0].strip() if lines else ""
        raise _error(path, f"line 1: expected 'ply' magic, got {first[:40]!r}")
    fmt: str | None = None
    elements: list[tuple[str, int, list[PlyProperty]]] = []
    comments: list[str] = []
    obj_info: list[str] = []
    for number, raw in enumerate(lines[1:], start=2):
        line = raw.strip()
        if not line:
            continue
        keyword, _, rest = line.partition(" ")
        words = line.split()
        if keyword == "comment":
            comments.append(rest.strip())
        elif keyword == "obj_info":
            obj_info.append(rest.strip())
        elif keyword == "format":
            if len(words) != 3 or words[1] not in _FORMATS:
                raise _error(
                    path,
                    f"line {number}: expected 'format <{'|'.join(_FORMATS)}> 1.0', got {line!r}",
                )
            if words[2] != "1.0":
                raise _error(path, f"line {number}: unsupported PLY version {words[2]!r}")
            fmt = words[1]
        elif keyword == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise _error(
                    path, f"line {number}: expected 'element <name> <count>', got {line!r}"
                )
            elements.append((words[1], int(words[2]), []))
        elif keyword == "property":
            if not elements:
                raise _error(path, f"line {number}: 'property' before any 'element'")
            props = elements[-1][2]
            if len(words) >= 2 and words[1] == "list":
                if len(words) != 5 or words[2] not in _TYPES or words[3] not in _TYPES:
                    raise _error(
                        path,
                        f"line {number}: expected 'property list <count type> <type> "
                        f"<name>', got {line!r}",
                    )
                if _TYPES[words[2]][0] == "f":
                    raise _error(path, f"line {number}: list count type must be an integer")
                props.append(PlyProperty(words[4], _TYPES[words[3]], _TYPES[words[2]]))
            else:
                if len(words) != 3 or words[1] not in _TYPES:
                    raise _error(
                        path, f"line {number}: expected 'property <type> <name>', got {line!r}"
                    )
                props.append(PlyProperty(words[2], _TYPES[words[1]]))
        else:
            raise _error(path, f"line {number}: unknown header keyword {keyword!r}")
    if fmt is None:
        raise _error(path, "header has no 'format' line")
    return fmt, elements, comments, obj_info


def _parse_ascii(
    path: str | os.PathLike,
    body: bytes,
    first_line: int,
    elements: Sequence[PlyElement],
    wanted: set[str],
) -> dict[str, dict[str, np.ndarray | list[np.ndarray]]]:
    lines = body.decode("ascii", errors="replace").splitlines()
    wanted_positions = [i for i, e in enumerate(elements) if e.name in wanted]
    if not wanted_positions:
        return {}
    needed = sum(e.count for e in elements[: wanted_positions[-1] + 1])
    numbers: Sequence[int] = range(first_line, first_line + len(lines))
    if any(not s.strip() for s in lines[:needed]):
        # Blank lines carry no data: drop them, keeping the file line numbers for messages.
        numbers = [first_line + i for i, s in enumerate(lines) if s.strip()]
        lines = [s for s in lines if s.strip()]
    out: dict[str, dict[str, np.ndarray | list[np.ndarray]]] = {}
    cursor = 0
    for element in elements[: wanted_positions[-1] + 1]:
        block = lines[cursor : cursor + element.count]
        if len(block) < element.count:
            raise _error(
                path,
                f"element '{element.name}': truncated data, expected {element.count} "
                f"data lines, found {len(block)}",
            )
        block_numbers = numbers[cursor : cursor + element.count]
        cursor += element.count
        if element.name not in wanted:
            continue
        out[element.name] = _parse_ascii_element(path, element, block, block_numbers)
    return out


def _parse_ascii_element(
    path: str | os.PathLike, element: PlyElement, block: list[str], numbers: Sequence[int]
) -> dict[str, np.ndarray | list[np.ndarray]]:
    props = element.properties
    if not any(p.is_list for p in props):
        width = len(props)
        # Per-line token counts too: equal totals could hide a short and a long line.
        aligned = all(len(line.split()) == width for line in block)
        try:
            flat = np.array(" ".join(block).split(), dtype=np.float64) if aligned else None
        except ValueError:
            flat = None
        if flat is None:
            # Slow path only to find and name the offending line.
            for line, number in zip(block, numbers, strict=True):
                tokens = line.split()
                if len(tokens) != width:
                    raise _error(
                        path,
                        f"line {number} (element '{element.name}'): expected {width} "
                        f"values, got {len(tokens)}",
                    )
                for token in tokens:
                    try:
                        float(token)
                    except ValueError:
                        raise _error(
                            path,
                            f"line {number} (element '{element.name}'): not a number: {token!r}",
                        ) from None
            flat = np.array([float(t) for t in " ".join(block).split()], dtype=np.float64)
        table = flat.reshape(element.count, width)
        return {p.name: table[:, i].astype(p.dtype) for i, p in enumerate(props)}
    columns: dict[str, list] = {p.name: [] for p in props}
    for line, number in zip(block, numbers, strict=True):
        tokens = line.split()
        pos = 0
        try:
            for p in props:
                if p.is_list:
                    n = int(tokens[pos])
                    values = tokens[pos + 1 : pos + 1 + n]
                    if len(values) != n:
                        raise IndexError
                    columns[p.name].append(np.array(values, dtype=np.float64).astype(p.dtype))
                    pos += 1 + n
                else:
                    columns[p.name].append(float(tokens[pos]))
                    pos += 1
        except IndexError:
            raise _error(
                path, f"line {number} (element '{element.name}'): too few values"
            ) from None
        except ValueError:
            raise _error(
                path, f"line {number} (element '{element.name}'): not a number in {line!r}"
            ) from None
        if pos != len(tokens):
            raise _error(
                path,
                f"line {number} (element '{element.name}'): {len(tokens) - pos} "
                "unexpected extra value(s)",
            )
    return {
        p.name: columns[p.name] if p.is_list else np.array(columns[p.name]).astype(p.dtype)
        for p in props
    }


_STRUCT_CODES = {
    "i1": "b",
    "u1": "B",
    "i2": "h",
    "u2": "H",
    "i4": "i",
    "u4": "I",
    "f4": "f",
    "f8": "d",
}


def _parse_binary_rows(
    path: str | os.PathLike,
    body: bytes,
    offset: int,
    order: str,
    element: PlyElement,
    keep: bool,
) -> tuple[int, dict[str, np.ndarray | list[np.ndarray]]]:
    """Walk the instances of an element with list properties (sequential: sizes vary)."""
    props = element.properties
    columns: dict[str, list] = {p.name: [] for p in props}
    unpackers = []
    for p in props:
        value = struct.Struct(order + _STRUCT_CODES[p.dtype])
        count = struct.Struct(order + _STRUCT_CODES[p.count_dtype]) if p.is_list else None
        unpackers.append((p, count, value))
    size = len(body)
    instance = 0
    try:
        for instance in range(element.count):  # noqa: B007 (read in the except clause)
            for p, count, value in unpackers:
                if count is None:
                    item = value.unpack_from(body, offset)[0]
                    offset += value.size
                else:
                    n = count.unpack_from(body, offset)[0]
                    offset += count.size
                    end = offset + n * value.size
                    if n < 0 or end > size:
                        raise struct.error("truncated")
                    item = np.frombuffer(body, order + p.dtype, n, offset).astype(p.dtype)
                    offset = end
                if keep:
                    columns[p.name].append(item)
    except struct.error:
        raise _error(
            path,
            f"element '{element.name}': truncated binary data at instance {instance} "
            f"of {element.count}",
        ) from None
    result = {
        p.name: columns[p.name] if p.is_list else np.array(columns[p.name], dtype=p.dtype)
        for p in props
    }
    return offset, result


def _parse_binary(
    path: str | os.PathLike,
    body: bytes,
    order: str,
    elements: Sequence[PlyElement],
    wanted: set[str],
) -> dict[str, dict[str, np.ndarray | list[np.ndarray]]]:
    out: dict[str, dict[str, np.ndarray | list[np.ndarray]]] = {}
    offset = 0
    for index, element in enumerate(elements):
        if not (wanted & {e.name for e in elements[index:]}):
            break
        props = element.properties
        if not any(p.is_list for p in props):
            record = np.dtype([(p.name, order + p.dtype) for p in props])
            size = record.itemsize * element.count
            if offset + size > len(body):
                got = (len(body) - offset) // max(record.itemsize, 1)
                raise _error(
                    path,
                    f"element '{element.name}': truncated binary data, expected "
                    f"{element.count} instances of {record.itemsize} bytes, found {got}",
                )
            if element.name in wanted:
                table = np.frombuffer(body, dtype=record, count=element.count, offset=offset)
                out[element.name] = {p.name: table[p.name].astype(p.dtype) for p in props}
            offset += size
            continue
        keep = element.name in wanted
        offset, columns = _parse_binary_rows(path, body, offset, order, element, keep)
        if keep:
            out[element.name] = columns
    return out


def read_ply(path: str | os.PathLike, elements: Sequence[str] | None = None) -> PlyData:
    """Read a PLY file (ascii, binary_little_endian or binary_big_endian).

    Args:
        path: file to read.
        elements: names of the elements to parse; ``None`` parses all. Reading stops after the
            last requested element, so ``elements=("vertex",)`` skips the 204800-line
            ``range_grid`` of a Stanford scan. A requested name that the file does not declare
            raises ``ValueError``.

    Returns:
        :class:`PlyData`; ``data["vertex"]["x"]`` etc. keep the file's scalar types.

    Raises:
        ValueError: malformed header (names the header line), or truncated / malformed data
            (names the element and, for ascii, the file line).
    """
    with open(path, "rb") as f:
        raw = f.read()
    match = _END_HEADER.search(raw)
    if match is None:
        if not raw.startswith(b"ply"):
            raise _error(path, "line 1: not a PLY file (no 'ply' magic)")
        raise _error(path, "header is not terminated by an 'end_header' line")
    header_lines = raw[: match.start()].decode("ascii", errors="replace").splitlines()
    fmt, declared, comments, obj_info = _parse_header(path, header_lines)
    element_list = tuple(PlyElement(n, c, tuple(p)) for n, c, p in declared)
    names = [e.name for e in element_list]
    wanted = set(names) if elements is None else set(elements)
    missing = wanted - set(names)
    if missing:
        raise ValueError(
            f"read_ply: {os.fspath(path)}: requested element(s) {sorted(missing)} not declared; "
            f"the file declares {names}"
        )
    body = raw[match.end() :]
    if fmt == "ascii":
        first_line = len(header_lines) + 2  # the 1-based line after 'end_header'
        data = _parse_ascii(path, body, first_line, element_list, wanted)
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        data = _parse_binary(path, body, order, element_list, wanted)
    return PlyData(fmt, element_list, data, comments, obj_info)


def read_ply_points(path: str | os.PathLike, *, dtype: torch.dtype = torch.float64) -> Tensor:
    """Read the vertex coordinates of a PLY file as a tensor of shape (N, 3).

    Only the ``vertex`` element is parsed (e.g. a Stanford ``range_grid`` is skipped).

    Args:
        path: file to read.
        dtype: dtype of the result, float64 by default.

    Returns:
        Points x, y, z, shape (N, 3), in the file's units (metres for the Stanford scans).
    """
    return torch.from_numpy(read_ply(path, elements=("vertex",)).points()).to(dtype)


def write_ply(
    path: str | os.PathLike,
    points: Tensor | np.ndarray,
    colors: Tensor | np.ndarray | None = None,
    *,
    format: PlyFormat = "binary_little_endian",
    coordinate_type: Literal["float", "double"] = "double",
    comments: Sequence[str] = (),
) -> None:
    """Write a point cloud as a PLY ``vertex`` element (x, y, z and optional red, green, blue).

    Args:
        path: file to write (overwritten).
        points: coordinates, shape (N, 3).
        colors: optional per-vertex colours, shape (N, 3), integer 0..255 (written as uchar);
            float input in [0, 1] is scaled by 255 and rounded.
        format: ``"binary_little_endian"`` (default), ``"binary_big_endian"`` or ``"ascii"``.
        coordinate_type: ``"double"`` (default, lossless for float64) or ``"float"``.
        comments: header comment lines (no newlines).
    """
    pts = points.detach().cpu().numpy() if isinstance(points, Tensor) else np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"write_ply: argument 'points' must have shape (N, 3), got {pts.shape}")
    if format not in _FORMATS:
        raise ValueError(f"write_ply: argument 'format' must be one of {_FORMATS}, got {format!r}")
    if coordinate_type not in ("float", "double"):
        raise ValueError(
            f"write_ply: argument 'coordinate_type' must be 'float' or 'double', "
            f"got {coordinate_type!r}"
        )
    rgb = None
    if colors is not None:
        rgb = colors.detach().cpu().numpy() if isinstance(colors, Tensor) else np.asarray(colors)
        if rgb.shape != pts.shape:
            raise ValueError(
                f"write_ply: argument 'colors' must have shape {pts.shape}, got {rgb.shape}"
            )
        if np.issubdtype(rgb.dtype, np.floating):
            rgb = np.rint(np.clip(rgb, 0.0, 1.0) * 255.0)
        elif rgb.size and (rgb.min() < 0 or rgb.max() > 255):
            raise ValueError("write_ply: integer 'colors' must lie in 0..255")
        rgb = rgb.astype(np.uint8)
    for comment in comments:
        if "\n" in comment or "\r" in comment:
            raise ValueError("write_ply: comments must not contain newlines")
    header = ["ply", f"format {format} 1.0"]
    header += [f"comment {c}" for c in comments]
    header += [f"element vertex {pts.shape[0]}"]
    header += [f"property {coordinate_type} {k}" for k in ("x", "y", "z")]
    if rgb is not None:
        header += [f"property uchar {k}" for k in ("red", "green", "blue")]
    header += ["end_header"]
    coord = "f8" if coordinate_type == "double" else "f4"
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        if format == "ascii":
            # 17 (9) significant digits make float64 (float32) values exact on a round trip.
            digits = "%.17g" if coordinate_type == "double" else "%.9g"
            table = pts.astype(coord).astype(np.float64)
            fmt = [digits] * 3
            if rgb is not None:
                table = np.concatenate((table, rgb.astype(np.float64)), axis=1)
                fmt += ["%d"] * 3
            np.savetxt(f, table, fmt=fmt, delimiter=" ")
        else:
            order = "<" if format == "binary_little_endian" else ">"
            fields = [(k, order + coord) for k in ("x", "y", "z")]
            if rgb is not None:
                fields += [(k, "u1") for k in ("red", "green", "blue")]
            table = np.empty(pts.shape[0], dtype=np.dtype(fields))
            for i, k in enumerate(("x", "y", "z")):
                table[k] = pts[:, i]
            if rgb is not None:
                for i, k in enumerate(("red", "green", "blue")):
                    table[k] = rgb[:, i]
            f.write(table.tobytes())
