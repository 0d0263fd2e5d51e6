"""PLY point clouds: read ascii / binary (little- and big-endian), write ascii / binary.

numpy only. The reader is generic (any elements, scalar and list properties) and handles the
Stanford 3D Scanning Repository range scans, whose header has ``obj_info`` lines and whose
vertices are followed by a ``range_grid`` element with a list property::

    element vertex 40256          property float x / y / z
    element range_grid 204800     property list uchar int vertex_indices
    end_header

In ascii files every element instance is one line, as written by every common PLY tool; this
lets error messages name the line. Values are parsed exactly as their declared type: an integer
property takes a decimal integer within the type's range (``uchar 300`` and ``int 2.7`` are
errors, not 44 and 2), a float property a finite decimal number that fits the type (no ``nan``,
``inf`` or ``1e39`` for ``float``). In binary files, float values must be finite too.
Malformed headers (unknown keywords, missing ``format``, repeated element or property names,
elements without properties), truncated data, data beyond the declared elements and bytes that
are not ASCII text in an ascii body raise a ``ValueError`` that names the file and the header
line, the data line (ascii) or the element and instance (binary).
"""

from __future__ import annotations

import itertools
import os
import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from torchslam import _checks
from torchslam.io import _text

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
# numpy kind of each integer type → its (min, max)
_INTEGER_RANGES = {
    kind: (int(np.iinfo(kind).min), int(np.iinfo(kind).max))
    for kind in set(_TYPES.values())
    if kind[0] != "f"
}
# numpy kind → the PLY name used in messages
_TYPE_NAMES = {kind: name for name, kind in reversed(_TYPES.items())}
_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
# "end_header" on a line of its own (not at the end of a comment line)
_END_HEADER = re.compile(rb"(?m)^end_header[ \t]*\r?\n")
# Element and property names: printable ASCII without white space.
_NAME = re.compile(r"[!-~]+")
# Characters of the tokens the vectorized ascii path handles; anything else takes the slow
# path, which names the offending line.
_NOT_NUMERIC = re.compile(r"[^0-9eE+\-. \t\r\n]")
_NOT_INTEGER = re.compile(r"[.eE]")
# A line of white space only (str.split's white space, less the line break).
_BLANK_LINE = re.compile(r"\n[ \t\r\f\v\x1c-\x1f\x85]*\n")


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


def _header_lines(path: str | os.PathLike, header: bytes) -> list[str]:
    """The header's lines (split at ``\\n`` only, ``\\r`` dropped): ASCII, except that comment
    and obj_info lines may hold any bytes (decoded as UTF-8, invalid bytes replaced)."""
    raw_lines = header.split(b"\n")
    if raw_lines and raw_lines[-1] == b"":
        raw_lines.pop()
    lines = []
    for number, raw in enumerate(raw_lines, start=1):
        raw = raw.removesuffix(b"\r")
        words = raw.split(None, 1)
        if words and words[0] in (b"comment", b"obj_info"):
            lines.append(raw.decode("utf-8", errors="replace"))
            continue
        try:
            lines.append(raw.decode("ascii"))
        except UnicodeDecodeError as error:
            raise _error(
                path,
                f"line {number}: not an ASCII PLY header line (byte 0x{raw[error.start]:02x} at "
                f"column {error.start + 1})",
            ) from None
    return lines


def _parse_header(path: str | os.PathLike, lines: list[str]) -> tuple[str, list, list, list]:
    """Parse header lines (without 'end_header'). Returns format, elements, comments, obj_info."""
    if not lines or lines[0].strip() != "ply":
        first = lines[0].strip() if lines else ""
        raise _error(path, f"line 1: expected 'ply' magic, got {first[:40]!r}")
    fmt: str | None = None
    format_line = 0
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
            if fmt is not None:
                raise _error(path, f"line {number}: second 'format' line (first: {format_line})")
            fmt, format_line = words[1], number
        elif keyword == "element":
            if len(words) != 3 or not re.fullmatch("[0-9]+", words[2]):
                raise _error(
                    path, f"line {number}: expected 'element <name> <count>', got {line[:80]!r}"
                )
            _check_name(path, number, "element", words[1])
            if any(words[1] == e[0] for e in elements):
                raise _error(path, f"line {number}: element {words[1]!r} declared twice")
            _check_element_has_properties(path, elements, number)
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
                prop = PlyProperty(words[4], _TYPES[words[3]], _TYPES[words[2]])
            else:
                if len(words) != 3 or words[1] not in _TYPES:
                    raise _error(
                        path,
                        f"line {number}: expected 'property <type> <name>', got {line[:80]!r}",
                    )
                prop = PlyProperty(words[2], _TYPES[words[1]])
            _check_name(path, number, "property", prop.name)
            if any(prop.name == q.name for q in props):
                raise _error(
                    path,
                    f"line {number}: property {prop.name!r} declared twice in element "
                    f"{elements[-1][0]!r}",
                )
            props.append(prop)
        else:
            raise _error(path, f"line {number}: unknown header keyword {keyword[:40]!r}")
    _check_element_has_properties(path, elements, len(lines) + 1)
    if fmt is None:
        raise _error(path, "header has no 'format' line")
    return fmt, elements, comments, obj_info


def _check_name(path: str | os.PathLike, number: int, what: str, name: str) -> None:
    if not _NAME.fullmatch(name):
        raise _error(path, f"line {number}: {what} name {name!r} is not printable ASCII")


def _check_element_has_properties(path: str | os.PathLike, elements: list, number: int) -> None:
    """The last declared element (if any) must have properties unless it has no instances."""
    if elements and elements[-1][1] > 0 and not elements[-1][2]:
        name, count = elements[-1][0], elements[-1][1]
        raise _error(
            path,
            f"line {number}: element {name!r} declares {count} instances but no properties",
        )


def _parse_ascii(
    path: str | os.PathLike,
    body: bytes,
    first_line: int,
    elements: Sequence[PlyElement],
    wanted: set[str],
) -> dict[str, dict[str, np.ndarray | list[np.ndarray]]]:
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError as error:
        number = first_line + body.count(b"\n", 0, error.start)
        raise _error(
            path,
            f"line {number}: not an ascii PLY data line (byte 0x{body[error.start]:02x} is "
            "not ASCII; is the file binary?)",
        ) from None
    if text.endswith("\n"):
        text = text[:-1]
    lines = text.split("\n") if text else []
    # Blank lines carry no data: drop them, keeping the file line numbers for messages.
    numbers: Sequence[int] = range(first_line, first_line + len(lines))
    if lines and _BLANK_LINE.search(f"\n{text}\n"):
        numbers = [first_line + i for i, s in enumerate(lines) if s.strip()]
        lines = [s for s in lines if s.strip()]
    total = sum(e.count for e in elements)
    if len(lines) > total:
        raise _error(
            path,
            f"line {numbers[total]}: data beyond the declared elements (the header declares "
            f"{total} data lines, the file has {len(lines)})",
        )
    # Elements after the last requested one are not checked (a Stanford scan's range grid).
    wanted_positions = [i for i, e in enumerate(elements) if e.name in wanted]
    stop = wanted_positions[-1] + 1 if wanted_positions else 0
    out: dict[str, dict[str, np.ndarray | list[np.ndarray]]] = {}
    cursor = 0
    for element in elements[:stop]:
        block = lines[cursor : cursor + element.count]
        if len(block) < element.count:
            raise _error(
                path,
                f"element '{element.name}': truncated data, expected {element.count} "
                f"data lines, found {len(block)}",
            )
        block_numbers = numbers[cursor : cursor + element.count]
        cursor += element.count
        if element.name in wanted:
            out[element.name] = _parse_ascii_element(path, element, block, block_numbers)
    return out


def _ascii_value(token: str, kind: str) -> int | float:
    """One ascii token parsed exactly as the PLY type ``kind`` (raises TokenError)."""
    if kind[0] == "f":
        value = _text.parse_finite_float(token)
        if kind == "f4" and not _fits_float32(np.asarray([value])).all():
            raise _text.TokenError(f"{token!r} overflows the type float")
        return value
    low, high = _INTEGER_RANGES[kind]
    return _text.parse_integer(token, low, high, f"an integer of type {_TYPE_NAMES[kind]}")


def _typed_column(tokens: list[str], kind: str) -> np.ndarray | None:
    """Tokens that passed the _NOT_NUMERIC test as an array of ``kind``; None if any value
    does not parse exactly as that type (the caller's slow path then names it)."""
    try:
        values = np.array(tokens, dtype=np.float64)
    except ValueError:
        return None
    if kind[0] == "f":
        ok = _fits_float32(values) if kind == "f4" else np.isfinite(values)
        if not ok.all():
            return None
    else:
        low, high = _INTEGER_RANGES[kind]
        if values.size and (values.min() < low or values.max() > high):
            return None
        if _NOT_INTEGER.search(" ".join(tokens)):
            return None
    return values.astype(kind)


def _fits_float32(values: np.ndarray) -> np.ndarray:
    """Finite float64 values that stay finite when rounded to float32."""
    with np.errstate(over="ignore"):
        return np.isfinite(values.astype(np.float32))


def _parse_ascii_element(
    path: str | os.PathLike, element: PlyElement, block: list[str], numbers: Sequence[int]
) -> dict[str, np.ndarray | list[np.ndarray]]:
    props = element.properties
    if any(p.is_list for p in props):
        fast = _parse_ascii_rows(element, block)
    else:
        fast = _parse_ascii_table(element, block)
    if fast is not None:
        return fast
    # One line at a time: exact checks, and the message names the offending line.
    columns: dict[str, list] = {p.name: [] for p in props}
    for line, number in zip(block, numbers, strict=True):
        tokens = line.split()
        pos = 0
        try:
            for p in props:
                if p.is_list:
                    if pos >= len(tokens):
                        raise _text.TokenError(f"list '{p.name}': missing its length")
                    count_max = _INTEGER_RANGES[p.count_dtype][1]
                    n = _text.parse_integer(
                        tokens[pos], 0, count_max, f"a list length (≥ 0) for '{p.name}'"
                    )
                    values = tokens[pos + 1 : pos + 1 + n]
                    if len(values) != n:
                        raise _text.TokenError(
                            f"list '{p.name}': expected {n} values, got {len(values)}"
                        )
                    parsed = [_ascii_value(v, p.dtype) for v in values]
                    columns[p.name].append(np.array(parsed, dtype=np.float64).astype(p.dtype))
                    pos += 1 + n
                else:
                    if pos >= len(tokens):
                        raise _text.TokenError(
                            f"expected {_width_text(props)}, got {len(tokens)} values"
                        )
                    columns[p.name].append(_ascii_value(tokens[pos], p.dtype))
                    pos += 1
        except _text.TokenError as error:
            raise _error(path, f"line {number} (element '{element.name}'): {error}") from None
        if pos != len(tokens):
            raise _error(
                path,
                f"line {number} (element '{element.name}'): {len(tokens) - pos} "
                "unexpected extra value(s)",
            )
    return {
        p.name: columns[p.name]
        if p.is_list
        else np.array(columns[p.name], dtype=np.float64 if p.dtype[0] == "f" else np.int64).astype(
            p.dtype
        )
        for p in props
    }


def _width_text(props: Sequence[PlyProperty]) -> str:
    if any(p.is_list for p in props):
        return "more values"
    return f"{len(props)} values"


def _parse_ascii_table(
    element: PlyElement, block: list[str]
) -> dict[str, np.ndarray | list[np.ndarray]] | None:
    """Vectorized parse of an element of scalar properties; None when anything is off (the
    caller then parses line by line, which finds and names the problem)."""
    props = element.properties
    width = len(props)
    text = " ".join(block)
    if _NOT_NUMERIC.search(text):
        return None  # letters (nan, inf, garbage) or other characters
    tokens = text.split()
    # Per-line token counts too: equal totals could hide a short and a long line.
    if len(tokens) != width * len(block) or any(len(line.split()) != width for line in block):
        return None
    out: dict[str, np.ndarray | list[np.ndarray]] = {}
    for i, p in enumerate(props):
        column = _typed_column(tokens[i::width], p.dtype)
        if column is None:
            return None
        out[p.name] = column
    return out


def _parse_ascii_rows(
    element: PlyElement, block: list[str]
) -> dict[str, np.ndarray | list[np.ndarray]] | None:
    """Faster parse of an element with list properties (one Python loop over the lines, the
    type checks vectorized); None when anything is off, as for :func:`_parse_ascii_table`."""
    props = element.properties
    if _NOT_NUMERIC.search(" ".join(block)):
        return None
    tokens_of: dict[str, list] = {p.name: [] for p in props}
    lengths: dict[str, list[int]] = {p.name: [] for p in props if p.is_list}
    try:
        for line in block:
            tokens = line.split()
            pos = 0
            for p in props:
                if p.is_list:
                    n = int(tokens[pos])
                    end = pos + 1 + n
                    if n < 0 or end > len(tokens):
                        return None
                    tokens_of[p.name].extend(tokens[pos + 1 : end])
                    lengths[p.name].append(n)
                    pos = end
                else:
                    tokens_of[p.name].append(tokens[pos])
                    pos += 1
            if pos != len(tokens):
                return None
    except (IndexError, ValueError):
        return None
    out: dict[str, np.ndarray | list[np.ndarray]] = {}
    for p in props:
        values = _typed_column(tokens_of[p.name], p.dtype)
        if values is None:
            return None
        if p.is_list:
            sizes = lengths[p.name]
            if sizes and max(sizes) > _INTEGER_RANGES[p.count_dtype][1]:
                return None
            ends = list(itertools.accumulate(sizes))
            out[p.name] = [values[e - n : e] for n, e in zip(sizes, ends, strict=True)]
        else:
            out[p.name] = values
    return out


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
        for instance in range(element.count):
            for p, count, value in unpackers:
                if count is None:
                    item = value.unpack_from(body, offset)[0]
                    offset += value.size
                else:
                    n = count.unpack_from(body, offset)[0]
                    offset += count.size
                    if n < 0:
                        raise _error(
                            path,
                            f"element '{element.name}', instance {instance}: list "
                            f"'{p.name}' has a negative length {n}",
                        )
                    end = offset + n * value.size
                    if end > size:
                        raise struct.error("truncated")
                    item = np.frombuffer(body, order + p.dtype, n, offset).astype(p.dtype)
                    if p.dtype[0] == "f" and not np.isfinite(item).all():
                        raise _error(
                            path,
                            f"element '{element.name}', instance {instance}: list "
                            f"'{p.name}' holds a non-finite value",
                        )
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
    if keep:
        _check_finite(path, element, result)
    return offset, result


def _check_finite(
    path: str | os.PathLike, element: PlyElement, columns: dict[str, np.ndarray | list]
) -> None:
    """Binary float values must be finite: name the first instance holding a NaN or ±Inf."""
    for p in element.properties:
        values = columns[p.name]
        if p.is_list or p.dtype[0] != "f":
            continue
        finite = np.isfinite(values)
        if not finite.all():
            instance = int(np.argmin(finite))
            raise _error(
                path,
                f"element '{element.name}', instance {instance} of {element.count}: property "
                f"'{p.name}' is {values[instance]} (binary float values must be finite)",
            )


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
                _check_finite(path, element, out[element.name])
            offset += size
        else:
            keep = element.name in wanted
            offset, columns = _parse_binary_rows(path, body, offset, order, element, keep)
            if keep:
                out[element.name] = columns
        if index == len(elements) - 1 and offset != len(body):
            raise _error(
                path,
                f"{len(body) - offset} byte(s) of data beyond the declared elements (the last, "
                f"'{element.name}', ends at byte {offset} of the body)",
            )
    return out


def read_ply(path: str | os.PathLike, elements: Sequence[str] | None = None) -> PlyData:
    """Read a PLY file (ascii, binary_little_endian or binary_big_endian).

    Args:
        path: file to read.
        elements: names of the elements to parse (a single str names one); ``None`` parses
            all. Reading stops after the last requested element, so ``elements=("vertex",)``
            skips the 204800-line ``range_grid`` of a Stanford scan. A requested name that the
            file does not declare raises ``ValueError``.

    Returns:
        :class:`PlyData`; ``data["vertex"]["x"]`` etc. keep the file's scalar types.

    Raises:
        ValueError: malformed header (names the header line), or truncated / malformed data,
            a value outside its declared type, a non-finite float, data beyond the declared
            elements (names the element and, for ascii, the file line; module docstring).
        TypeError: ``path`` is not a str / os.PathLike, ``elements`` not a str or a sequence
            of str.
        OSError: the file cannot be read (FileNotFoundError for a missing one).
    """
    fn = "read_ply"
    path = _checks.check_path(fn, path, is_file=True)
    if isinstance(elements, str):
        elements = (elements,)
    elif elements is not None:
        if not isinstance(elements, (Sequence, set, frozenset)):
            raise TypeError(
                f"{fn}: argument 'elements' must be None, a str or a sequence of str, "
                f"got {_checks.describe(elements)}"
            )
        for item in elements:
            if not isinstance(item, str):
                raise TypeError(
                    f"{fn}: argument 'elements' must hold str element names, "
                    f"got {_checks.describe(item)}"
                )
    with open(path, "rb") as f:
        raw = f.read()
    match = _END_HEADER.search(raw)
    if match is None:
        if not raw.startswith(b"ply"):
            raise _error(path, "line 1: not a PLY file (no 'ply' magic)")
        raise _error(path, "header is not terminated by an 'end_header' line")
    # Split at "\n" only (splitlines would also split at form feeds, shifting line numbers).
    header_lines = _header_lines(path, raw[: match.start()])
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

    Raises:
        ValueError: as :func:`read_ply`, or no ``vertex`` element with x, y, z (naming the
            file); a coordinate that overflows ``dtype`` (e.g. 1e300 for float32).
        TypeError: ``dtype`` is not torch.float32 / torch.float64 (an integer dtype would
            truncate the coordinates), ``path`` not a str / os.PathLike.
    """
    _checks.check_float_dtype("read_ply_points", dtype)
    path = _checks.check_path("read_ply_points", path, is_file=True)
    data = read_ply(path, elements=("vertex",))
    vertex = data.data["vertex"]
    missing = [k for k in ("x", "y", "z") if k not in vertex]
    if missing:
        raise _error(path, f"element 'vertex' has no property {', '.join(map(repr, missing))}")
    points = torch.from_numpy(data.points()).to(dtype)
    # The values are finite float64 (read_ply checks); a narrower dtype may overflow.
    if dtype.is_floating_point and dtype.itemsize < 8 and not bool(torch.isfinite(points).all()):
        raise _error(path, f"vertex coordinates overflow {dtype}")
    return points


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

    Raises:
        ValueError: wrong shapes, non-finite points (or points that overflow ``float``), colours
            outside 0..255, comments with newlines, an unknown format.
    """
    path = _checks.check_path("write_ply", path)
    pts = points.detach().cpu().numpy() if isinstance(points, Tensor) else np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"write_ply: argument 'points' must have shape (N, 3), got {pts.shape}")
    if not np.issubdtype(pts.dtype, np.number) or np.issubdtype(pts.dtype, np.complexfloating):
        raise TypeError(f"write_ply: argument 'points' must be real numbers, got {pts.dtype}")
    if not np.isfinite(pts).all():
        raise ValueError("write_ply: argument 'points' must be finite (NaN or Inf found)")
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
    if coord == "f4" and not _fits_float32(pts.astype(np.float64)).all():
        raise ValueError("write_ply: argument 'points' overflows coordinate_type 'float'")
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
