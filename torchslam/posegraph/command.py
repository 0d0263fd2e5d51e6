"""Deprecated: ``torchslam.posegraph.command`` is now :mod:`torchslam.cli.posegraph` (its figure
:func:`torchslam.cli.plots.plot_trajectories`); removed in the next release.

Reading a name here returns the same object with a ``DeprecationWarning``.
"""

from torchslam import _deprecated

_MOVED = {
    "INITIALIZATIONS": "torchslam.cli.posegraph",
    "PoseGraphOptions": "torchslam.cli.posegraph",
    "add_arguments": "torchslam.cli.posegraph",
    "initial_poses": "torchslam.cli.posegraph",
    "options_from_args": "torchslam.cli.posegraph",
    "run_posegraph": "torchslam.cli.posegraph",
    "plot_trajectories": "torchslam.cli.plots",
}
__all__ = sorted(_MOVED)
__getattr__ = _deprecated.moved(__name__, _MOVED)
