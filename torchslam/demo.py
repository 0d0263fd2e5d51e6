"""Deprecated alias of :mod:`torchslam.cli.demo` (``torchslam demo``), removed in the next
release; its names warn when read."""

from torchslam import _deprecated

__getattr__ = _deprecated.moved(__name__, {"torchslam.cli.demo": None})
