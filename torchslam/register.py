"""Deprecated: ``torchslam.register`` was split; it is removed in the next release.

The pipeline is :mod:`torchslam.registration` (``config``, ``pipeline``, ``report``), pose
files are :mod:`torchslam.io.trajectories`, the command and its figure are
:mod:`torchslam.cli.register` and :mod:`torchslam.cli.plots`. A name read from here is the
same object, with a ``DeprecationWarning`` naming its new home.
"""

from torchslam import _deprecated

__getattr__ = _deprecated.moved(
    __name__,
    {
        "torchslam.registration.config": None,
        "torchslam.registration.pipeline": None,
        "torchslam.registration.report": None,
        "torchslam.io.trajectories": None,
        "torchslam.cli.register": None,
        "torchslam.cli.plots": ("merged_cloud", "plot_registration", "scan_colors"),
    },
)

if __name__ == "__main__":
    from torchslam.cli.register import main

    raise SystemExit(main())
