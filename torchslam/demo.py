"""Deprecated: ``torchslam.demo`` is now :mod:`torchslam.cli.demo`; removed in the next release.

Reading a name here returns the same object with a ``DeprecationWarning``.
"""

from torchslam import _deprecated

_MOVED = {
    "DemoOptions": "torchslam.cli.demo",
    "LIMITS": "torchslam.cli.demo",
    "MAX_SCENE_SIZE": "torchslam.cli.demo",
    "add_arguments": "torchslam.cli.demo",
    "options_from_args": "torchslam.cli.demo",
    "run_demo": "torchslam.cli.demo",
    "validate": "torchslam.cli.demo",
}
__all__ = sorted(_MOVED)
__getattr__ = _deprecated.moved(__name__, _MOVED)
