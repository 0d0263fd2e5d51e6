"""Shared strict parsing for the text readers (g2o, Stanford ``.conf``, pose files, PLY ascii).

Every helper raises :class:`TokenError`, a ``ValueError`` without file or line; the reader adds
both. Numbers are parsed exactly: ``float()`` alone would accept ``nan``, ``inf``, ``1_000``
and non-ASCII digits, and ``int()`` would accept ``+1_0`` or ``١``.
"""

from __future__ import annotations

import math
import os
import re

__all__ = [
    "TokenError",
    "decode_lines",
    "parse_finite_float",
    "parse_integer",
    "unit_quaternion",
]

# A decimal floating-point literal (no nan/inf, no underscores, ASCII digits only).
_FLOAT = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_INTEGER = re.compile(r"[+-]?[0-9]+")
# An integer literal with more digits than this cannot fit any of our integer types; checking
# the length first also keeps int() away from its 4300-digit limit.
_MAX_DIGITS = 40


class TokenError(ValueError):
    """A malformed token or line; the reader adds the file name and the line number."""


def decode_lines(data: bytes, path: str | os.PathLike, fn: str, kind: str) -> list[str]:
    """Split ``data`` at ``\\n`` (a trailing ``\\r`` is dropped) and decode each line as UTF-8.

    Line numbers of the result are the file's (``str.splitlines`` would also split at form
    feeds and other separators, shifting them).

    Raises:
        ValueError: ``"{fn}: {path}: line L: not a {kind} (…)"`` for a byte sequence that is
            not UTF-8 (a binary file, a Latin-1 accent) or a NUL byte.
    """
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        text = None
    if text is not None and "\x00" not in text:  # the common case: one decode, one split
        lines = text.split("\n")
        if lines and lines[-1] == "":
            lines.pop()
        return [line[:-1] if line.endswith("\r") else line for line in lines]
    # Find the offending line (and column) for the message.
    for number, raw in enumerate(data.split(b"\n"), start=1):
        try:
            line = raw.decode("utf-8")
        except UnicodeDecodeError as error:
            problem = f"byte 0x{raw[error.start]:02x} at column {error.start + 1} is not UTF-8"
        else:
            if "\x00" not in line:
                continue
            problem = f"NUL byte at column {line.index(chr(0)) + 1}"
        raise ValueError(f"{fn}: {os.fspath(path)}: line {number}: not a {kind} ({problem})")
    raise AssertionError("unreachable: the data failed to decode as a whole")


def parse_finite_float(token: str) -> float:
    """``float(token)`` for a decimal literal whose value is finite in float64."""
    if not _FLOAT.fullmatch(token):
        if token.lstrip("+-").lower() in ("nan", "inf", "infinity"):
            raise TokenError(f"expected a finite number, got {token!r}")
        raise TokenError(f"expected a number, got {_shorten(token)!r}")
    value = float(token)
    if not math.isfinite(value):
        raise TokenError(f"expected a finite number, got {_shorten(token)!r} (overflows float64)")
    return value


def parse_integer(token: str, low: int, high: int, what: str = "an integer") -> int:
    """``int(token)`` for a decimal integer literal in [low, high]."""
    if not _INTEGER.fullmatch(token):
        raise TokenError(f"expected {what}, got {_shorten(token)!r}")
    if len(token.lstrip("+-")) > _MAX_DIGITS:
        raise TokenError(f"expected {what} in [{low}, {high}], got {_shorten(token)!r}")
    value = int(token)
    if not low <= value <= high:
        raise TokenError(f"expected {what} in [{low}, {high}], got {value}")
    return value


def unit_quaternion(q: list[float], what: str = "quaternion") -> list[float]:
    """Normalize a finite 4-vector robustly: divided by its largest magnitude first.

    ``q / ‖q‖`` over- or underflows for entries near 1e±200 (‖q‖² leaves float64): (1e200,
    1e200, 0, 0) would become a NaN or zero and (1e-200, 0, 0, 0) a NaN. The scaled vector has
    largest entry 1, so its norm lies in [1, 2].

    Raises:
        TokenError: all entries zero.
    """
    scale = max(abs(x) for x in q)
    if scale == 0:
        raise TokenError(f"the {what} is zero")
    scaled = [x / scale for x in q]
    norm = math.sqrt(math.fsum(x * x for x in scaled))
    return [x / norm for x in scaled]


def _shorten(token: str, limit: int = 40) -> str:
    return token if len(token) <= limit else token[:limit] + "…"
