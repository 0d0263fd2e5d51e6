"""Deprecated: the ``torchslam posegraph`` command moved to :mod:`torchslam.cli.posegraph`, its
figure to :mod:`torchslam.cli.plots`. Names read from here warn; removed in the next release."""

from torchslam import _deprecated

__getattr__ = _deprecated.moved(
    __name__, {"torchslam.cli.posegraph": None, "torchslam.cli.plots": ("plot_trajectories",)}
)
