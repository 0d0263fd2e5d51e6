"""PLY point clouds: read ascii / binary (little- and big-endian), write ascii / binary.

The header is parsed and files are written by the ``plyfile`` package; the data is read here,
vectorized with numpy. plyfile reads ascii data and binary list properties one line or one
instance at a time in Python (3.3 s of CPU for one Stanford range scan, against 0.07 s for its
vertices and 0.25 s for all of it here), and takes ``nan`` for a float. The reader is generic
(any elements, scalar and list properties) and handles the Stanford 3D Scanning Repository
range scans, whose header has ``obj_info`` lines and whose vertices are followed by a
``range_grid`` element with a list property::

    element vertex 40256          property float x / y / z
    element range_grid 204800     property list uchar int vertex_indices
    end_header

In ascii files every element instance is one line, as written by every common PLY tool; this
lets error messages name the line. Values are parsed exactly as their declared type: an integer
property takes a decimal integer within the type's range (``uchar 300`` and ``int 2.7`` are
errors, not 44 and 2), a float property a finite decimal number that fits the type (no ``nan``,
``inf`` or ``1e39`` for ``float``). In binary files, float values must be finite too.
Malformed headers (what plyfile refuses, and besides: counts that are not decimal digits,
repeated element or property names, names that are not printable ASCII, types outside the PLY
specification, float list lengths, elements without properties), truncated data, data beyond
the declared elements and bytes that are not ASCII text in an ascii body raise a
``ValueError`` that names the file and the header line, the data line (ascii) or the element
and instance (binary).
"""

from __future__ import annotations

import io
import itertools
import os
import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import plyfile
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

# The scalar type names of the PLY specification (both spellings) → numpy kind. plyfile also
# takes numpy codes ("f4") as type names; a PLY file does not.
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
# Characters of the tokens the vectorized ascii path handles; anything else takes the
# line-by-line path, which names the offending line.
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


Columns = dict[str, np.ndarray | list[np.ndarray]]


def _error(path: str | os.PathLike, what: str) -> ValueError:
    return ValueError(f"read_ply: {os.fspath(path)}: {what}")


# ----------------------------------------------------------------------------------- header


def _read_header(path: str, raw: bytes) -> tuple[str, tuple[PlyElement, ...], list, list, int]:
    """Parse the header of the file contents ``raw``.

    Returns the format, the elements, the comment and obj_info texts and the length of the
    header in bytes (the body starts there).
    """
    match = _END_HEADER.search(raw)
    if match is None:
        if not raw.startswith(b"ply"):
            raise _error(path, "line 1: not a PLY file (no 'ply' magic)")
        raise _error(path, "header is not terminated by an 'end_header' line")
    # The header's lines, split at "\n" only ("\r" dropped): ASCII, except that comment and
    # obj_info lines may hold any text (decoded as UTF-8, invalid bytes replaced). plyfile, which
    # refuses such text (and obj_info after an element), sees empty comments in their place.
    raw_lines = raw[: match.start()].split(b"\n")[:-1]
    texts: dict[str, list[str]] = {"comment": [], "obj_info": []}
    lines = []
    for number, line in enumerate(raw_lines, start=1):
        words = line.split(None, 1)
        if words and words[0] in (b"comment", b"obj_info"):
            rest = words[1].decode("utf-8", errors="replace").strip() if len(words) > 1 else ""
            texts[words[0].decode()].append(rest)
            lines.append("comment")
            continue
        try:
            lines.append(line.decode("ascii").strip())  # stripped: "ply " is the magic too
        except UnicodeDecodeError as error:
            raise _error(
                path,
                f"line {number}: not an ASCII PLY header line (byte 0x{line[error.start]:02x} "
                f"at column {error.start + 1})",
            ) from None
    _check_declarations(path, lines)
    try:
        text = "\n".join([*lines, "end_header\n"])
        header = plyfile.PlyData._parse_header(io.StringIO(text))
    except plyfile.PlyHeaderParseError as error:
        raise _error(path, f"line {error.line}: {error.message}") from None
    elements = tuple(
        PlyElement(
            e.name,
            e.count,
            tuple(
                PlyProperty(p.name, p.val_dtype, getattr(p, "len_dtype", None))
                for p in e.properties
            ),
        )
        for e in header.elements
    )
    fmt = "ascii" if header.text else _FORMATS[1 if header.byte_order == "<" else 2]
    return fmt, elements, texts["comment"], texts["obj_info"], match.end()


def _check_declarations(path: str, lines: list[str]) -> None:
    """What plyfile's header parser lets through: element counts that are not decimal digits
    (``-1``, ``1_0``), repeated or unprintable names, type names outside the PLY specification,
    float list lengths, elements with instances but no properties. Lines of another shape are
    left to plyfile."""
    element: tuple[str, int] | None = None  # the element being declared: name, count
    elements: set[str] = set()
    properties: set[str] = set()
    for number, line in enumerate(lines, start=1):
        words = line.split()
        if words[:1] == ["element"] and len(words) == 3:
            _check_has_properties(path, number, element, properties)
            name, count = words[1], words[2]
            if not re.fullmatch("[0-9]+", count):
                raise _error(
                    path, f"line {number}: expected 'element <name> <count>', got {line[:80]!r}"
                )
            _check_name(path, number, "element", name)
            if name in elements:
                raise _error(path, f"line {number}: element {name!r} declared twice")
            elements.add(name)
            element, properties = (name, int(count)), set()
        elif words[:1] == ["property"] and element is not None and len(words) in (3, 5):
            types, name = words[1:-1], words[-1]
            if len(words) == 5:
                if types[0] != "list":
                    continue  # plyfile names the error
                types = types[1:]
            for type_name in types:
                if type_name not in _TYPES:
                    raise _error(
                        path,
                        f"line {number}: unknown property type {type_name[:40]!r}",
                    )
            if len(types) == 2 and _TYPES[types[0]][0] == "f":
                raise _error(path, f"line {number}: list count type must be an integer")
            _check_name(path, number, "property", name)
            if name in properties:
                raise _error(
                    path,
                    f"line {number}: property {name!r} declared twice in element {element[0]!r}",
                )
            properties.add(name)
    _check_has_properties(path, len(lines) + 1, element, properties)


def _check_name(path: str, number: int, what: str, name: str) -> None:
    if not _NAME.fullmatch(name):
        raise _error(path, f"line {number}: {what} name {name!r} is not printable ASCII")


def _check_has_properties(
    path: str, number: int, element: tuple[str, int] | None, properties: set[str]
) -> None:
    """The element declared last (if any) must have properties unless it has no instances."""
    if element is not None and element[1] > 0 and not properties:
        raise _error(
            path,
            f"line {number}: element {element[0]!r} declares {element[1]} instances but no "
            "properties",
        )


# ------------------------------------------------------------------------------------ ascii


def _read_ascii(
    path: str, body: bytes, first_line: int, elements: Sequence[PlyElement], wanted: set[str]
) -> dict[str, Columns]:
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
    out: dict[str, Columns] = {}
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
            columns = _ascii_columns(element, block)
            if columns is None:  # something is off: find it and name its line
                columns = _ascii_columns_by_line(path, element, block, block_numbers)
            out[element.name] = columns
    return out


def _ascii_columns(element: PlyElement, block: list[str]) -> Columns | None:
    """Vectorized parse of an element's lines: every token converted at once, each property
    found on every line by a cursor array (one entry per line) that steps over a scalar or a
    list (its length, then its values). None when anything is off (the caller then parses line
    by line, which finds and names the problem)."""
    text = "\n".join(block)
    if _NOT_NUMERIC.search(text):
        return None  # letters (nan, inf, garbage) or other characters
    tokens = text.split()
    try:
        values = np.array(tokens, dtype=np.float64)
    except ValueError:  # e.g. "1-2" or "."
        return None
    # Tokens per line, without a Python loop over the lines: a token starts at a character
    # that is not white space and follows white space (or opens the text).
    # (After the _NOT_NUMERIC test, white space is the only text at or below " ".)
    chars = np.frombuffer(text.encode("ascii"), dtype=np.uint8)
    space = chars <= ord(" ")
    starts = ~space
    starts[1:] &= space[:-1]
    line_breaks = np.flatnonzero(chars == ord("\n"))
    line_of_token = np.searchsorted(line_breaks, np.flatnonzero(starts))
    widths = np.bincount(line_of_token, minlength=len(block))
    ends = np.cumsum(widths)
    cursor = ends - widths  # the first token of each line
    out: Columns = {}
    integer_tokens = []  # positions of the tokens that must be integer literals
    for p in element.properties:
        if (cursor >= ends).any():
            return None  # a line too short
        if p.is_list:
            lengths = _typed(values[cursor], p.count_dtype)
            if lengths is None or ((lengths < 0) | (lengths >= ends - cursor)).any():
                return None  # a negative length, or more values than the line holds
            integer_tokens.append(cursor)
            positions, bounds = _ranges(cursor + 1, lengths.astype(np.int64))
            cursor = cursor + 1 + lengths
        else:
            positions, bounds = cursor, None
            cursor = cursor + 1
        column = _typed(values[positions], p.dtype)
        if column is None:
            return None
        if p.dtype[0] != "f":
            integer_tokens.append(positions)
        out[p.name] = column if bounds is None else _split(column, bounds)
    if (cursor != ends).any():
        return None  # a line too long
    if integer_tokens:
        positions = np.concatenate(integer_tokens)
        if len(positions) < len(tokens):
            text = " ".join(map(tokens.__getitem__, positions.tolist()))
        if _NOT_INTEGER.search(text):
            return None  # "2.7" or "1e3" for an integer
    return out


def _ranges(starts: np.ndarray, lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The positions start, start + 1, …, start + length − 1 of every range, concatenated, and
    where each range starts in the result (length len(starts) + 1)."""
    offsets = np.zeros(len(lengths) + 1, dtype=np.int64)
    np.cumsum(lengths, out=offsets[1:])
    positions = np.repeat(starts - offsets[:-1], lengths) + np.arange(offsets[-1])
    return positions, offsets


def _split(values: np.ndarray, offsets: np.ndarray) -> list[np.ndarray]:
    """``values`` cut at ``offsets`` (from :func:`_ranges`) into one array per instance."""
    bounds = offsets.tolist()
    return [values[a:b] for a, b in itertools.pairwise(bounds)]


def _typed(values: np.ndarray, kind: str) -> np.ndarray | None:
    """float64 values of ascii tokens as an array of ``kind``; None if any value does not fit
    (a float that overflows, an integer out of range or with a fraction)."""
    if kind[0] == "f":
        ok = _fits_float32(values) if kind == "f4" else np.isfinite(values)
        return values.astype(kind) if ok.all() else None
    low, high = _INTEGER_RANGES[kind]
    if values.size and (values.min() < low or values.max() > high):
        return None
    if (values != np.floor(values)).any():
        return None
    return values.astype(kind)


def _fits_float32(values: np.ndarray) -> np.ndarray:
    """Finite float64 values that stay finite when rounded to float32."""
    with np.errstate(over="ignore"):
        return np.isfinite(values.astype(np.float32))


def _ascii_value(token: str, kind: str) -> int | float:
    """One ascii token parsed exactly as the PLY type ``kind`` (raises TokenError)."""
    if kind[0] == "f":
        value = _text.parse_finite_float(token)
        if kind == "f4" and not _fits_float32(np.asarray([value])).all():
            raise _text.TokenError(f"{token!r} overflows the type float")
        return value
    low, high = _INTEGER_RANGES[kind]
    return _text.parse_integer(token, low, high, f"an integer of type {_TYPE_NAMES[kind]}")


def _ascii_columns_by_line(
    path: str, element: PlyElement, block: list[str], numbers: Sequence[int]
) -> Columns:
    """One line at a time, every token checked exactly: the error names the offending line."""
    props = element.properties
    width = "more values" if any(p.is_list for p in props) else f"{len(props)} values"
    columns: dict[str, list] = {p.name: [] for p in props}
    for line, number in zip(block, numbers, strict=True):
        tokens = line.split()
        pos = 0
        try:
            for p in props:
                if pos >= len(tokens):
                    if p.is_list:
                        raise _text.TokenError(f"list '{p.name}': missing its length")
                    raise _text.TokenError(f"expected {width}, got {len(tokens)} values")
                if not p.is_list:
                    columns[p.name].append(_ascii_value(tokens[pos], p.dtype))
                    pos += 1
                    continue
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


# ----------------------------------------------------------------------------------- binary

_STRUCT_CODES = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I"}


def _read_binary(
    path: str, body: bytes, order: str, elements: Sequence[PlyElement], wanted: set[str]
) -> dict[str, Columns]:
    out: dict[str, Columns] = {}
    offset = 0
    for index, element in enumerate(elements):
        if not (wanted & {e.name for e in elements[index:]}):
            break  # nothing requested from here on (a Stanford scan's range grid)
        keep = element.name in wanted
        if any(p.is_list for p in element.properties):
            offset, columns = _binary_lists(path, body, offset, order, element, keep)
        else:
            record = np.dtype([(p.name, order + p.dtype) for p in element.properties])
            size = record.itemsize * element.count
            if offset + size > len(body):
                got = (len(body) - offset) // max(record.itemsize, 1)
                raise _error(
                    path,
                    f"element '{element.name}': truncated binary data, expected "
                    f"{element.count} instances of {record.itemsize} bytes, found {got}",
                )
            table = np.frombuffer(body, record, element.count if keep else 0, offset)
            columns = {p.name: table[p.name].astype(p.dtype) for p in element.properties}
            offset += size
        if keep:
            _check_finite(path, element, columns)
            out[element.name] = columns
        if index == len(elements) - 1 and offset != len(body):
            raise _error(
                path,
                f"{len(body) - offset} byte(s) of data beyond the declared elements (the last, "
                f"'{element.name}', ends at byte {offset} of the body)",
            )
    return out


def _binary_lists(
    path: str, body: bytes, offset: int, order: str, element: PlyElement, keep: bool
) -> tuple[int, Columns]:
    """An element with list properties: one pass over the instances finds where each value
    starts (sequential, as the list lengths vary), then every property is gathered at once.
    Returns the offset after the element and (with ``keep``) its columns."""
    props = element.properties
    steps = [
        (
            struct.Struct(order + _STRUCT_CODES[p.count_dtype]) if p.is_list else None,
            np.dtype(p.dtype).itemsize,
        )
        for p in props
    ]
    starts: list[list[int]] = [[] for _ in props]  # byte offset of each instance's value(s)
    lengths: list[list[int]] = [[] for _ in props]  # list lengths (list properties)
    instance = 0
    try:
        for instance in range(element.count):
            for k, (counter, itemsize) in enumerate(steps):
                if counter is None:
                    starts[k].append(offset)
                    offset += itemsize
                    continue
                n = counter.unpack_from(body, offset)[0]
                if n < 0:
                    raise _error(
                        path,
                        f"element '{element.name}', instance {instance}: list "
                        f"'{props[k].name}' has a negative length {n}",
                    )
                offset += counter.size
                starts[k].append(offset)
                lengths[k].append(n)
                offset += n * itemsize
            if offset > len(body):
                raise struct.error("truncated")
    except struct.error:
        raise _error(
            path,
            f"element '{element.name}': truncated binary data at instance {instance} "
            f"of {element.count}",
        ) from None
    if not keep:
        return offset, {}
    data = np.frombuffer(body, np.uint8)
    out: Columns = {}
    for p, (counter, itemsize), first, n in zip(props, steps, starts, lengths, strict=True):
        dtype = np.dtype(order + p.dtype)
        if counter is None:
            out[p.name] = _gather(data, np.array(first, dtype=np.int64), dtype).astype(p.dtype)
            continue
        sizes = np.array(n, dtype=np.int64)
        within, bounds = _ranges(np.zeros_like(sizes), sizes)  # value j of each list: j
        byte_positions = np.repeat(np.array(first, dtype=np.int64), sizes) + within * itemsize
        values = _gather(data, byte_positions, dtype).astype(p.dtype)
        if p.dtype[0] == "f" and not np.isfinite(values).all():
            bad = int(np.searchsorted(bounds, np.argmin(np.isfinite(values)), side="right")) - 1
            raise _error(
                path,
                f"element '{element.name}', instance {bad}: list '{p.name}' holds a "
                "non-finite value",
            )
        out[p.name] = _split(values, bounds)
    return offset, out


def _gather(data: np.ndarray, positions: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """The values of ``dtype`` that start at the byte ``positions`` of ``data`` (uint8)."""
    raw = data[positions[:, None] + np.arange(dtype.itemsize)]
    return raw.view(dtype).reshape(-1)


def _check_finite(path: str, element: PlyElement, columns: Columns) -> None:
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


# ----------------------------------------------------------------------------------- public


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
    if not raw:
        raise _error(path, "the file is empty (0 bytes)")
    fmt, declared, comments, obj_info, body_start = _read_header(path, raw)
    names = [e.name for e in declared]
    wanted = set(names) if elements is None else set(elements)
    missing = wanted - set(names)
    if missing:
        raise _error(
            path,
            f"requested element(s) {sorted(missing)} not declared; the file declares {names}",
        )
    body = raw[body_start:]
    if fmt == "ascii":
        first_line = raw.count(b"\n", 0, body_start) + 1  # the 1-based line after 'end_header'
        data = _read_ascii(path, body, first_line, declared, wanted)
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        data = _read_binary(path, body, order, declared, wanted)
    return PlyData(fmt, declared, data, comments, obj_info)


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
        comments: header comment lines (ASCII, no newlines).

    Raises:
        ValueError: wrong shapes, non-finite points (or points that overflow ``float``), colours
            outside 0..255, comments with newlines or non-ASCII text, an unknown format.
        TypeError: points that are not real numbers, comments that are not str.
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
    comments = list(comments) if not isinstance(comments, str) else [comments]
    for comment in comments:
        if not isinstance(comment, str):
            raise TypeError(
                f"write_ply: argument 'comments' must hold str, got {_checks.describe(comment)}"
            )
        if "\n" in comment or "\r" in comment:
            raise ValueError("write_ply: comments must not contain newlines")
        if not comment.isascii():
            raise ValueError(f"write_ply: comments must be ASCII text, got {comment[:40]!r}")
    coord = "f8" if coordinate_type == "double" else "f4"
    if coord == "f4" and not _fits_float32(pts.astype(np.float64)).all():
        raise ValueError("write_ply: argument 'points' overflows coordinate_type 'float'")
    fields = [(k, coord) for k in ("x", "y", "z")]
    if rgb is not None:
        fields += [(k, "u1") for k in ("red", "green", "blue")]
    table = np.empty(pts.shape[0], dtype=np.dtype(fields))
    for i, k in enumerate(("x", "y", "z")):
        table[k] = pts[:, i]
    if rgb is not None:
        for i, k in enumerate(("red", "green", "blue")):
            table[k] = rgb[:, i]
    byte_order = {"ascii": "=", "binary_little_endian": "<", "binary_big_endian": ">"}[format]
    vertex = plyfile.PlyElement.describe(table, "vertex")
    ply = plyfile.PlyData([vertex], text=format == "ascii", byte_order=byte_order)
    ply.comments = comments
    if format != "ascii":
        ply.write(path)
        return
    # plyfile writes ascii data one row at a time (1.5 s for 40,000 points): one savetxt here.
    # 17 (9) significant digits make float64 (float32) values exact on a round trip.
    digits = "%.17g" if coordinate_type == "double" else "%.9g"
    columns = [table[name].astype(np.float64) for name in table.dtype.names]
    formats = [digits] * 3 + ["%d"] * (len(columns) - 3)
    with open(path, "wb") as f:
        f.write((ply.header + "\n").encode("ascii"))
        np.savetxt(f, np.stack(columns, axis=-1), fmt=formats, delimiter=" ")
