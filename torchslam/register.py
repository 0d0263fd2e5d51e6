"""Deprecated: ``torchslam.register`` moved; it is removed in the next release.

The pipeline is :mod:`torchslam.registration` (``config``, ``pipeline``, ``report``), pose
files are :mod:`torchslam.io.trajectories`, the command and its figure are
:mod:`torchslam.cli.register` and :mod:`torchslam.cli.plots`. Reading a name here returns the
same object with a ``DeprecationWarning`` naming its new home.
"""

from torchslam import _deprecated

_MOVED = {
    "RegisterConfig": "torchslam.registration.config",
    "default_stages": "torchslam.registration.config",
    "ChainResult": "torchslam.registration.pipeline",
    "Progress": "torchslam.registration.pipeline",
    "RefineResult": "torchslam.registration.pipeline",
    "Registration": "torchslam.registration.pipeline",
    "RoundInfo": "torchslam.registration.pipeline",
    "boundary_mask": "torchslam.registration.pipeline",
    "information_matrices": "torchslam.registration.pipeline",
    "joint_cost": "torchslam.registration.pipeline",
    "load_scans": "torchslam.registration.pipeline",
    "overlapping_pairs": "torchslam.registration.pipeline",
    "refine": "torchslam.registration.pipeline",
    "register": "torchslam.registration.pipeline",
    "register_chain": "torchslam.registration.pipeline",
    "alignment_residual": "torchslam.registration.report",
    "error_table": "torchslam.registration.report",
    "plane_distances": "torchslam.registration.report",
    "read_poses": "torchslam.io.trajectories",
    "write_poses": "torchslam.io.trajectories",
    "add_arguments": "torchslam.cli.register",
    "main": "torchslam.cli.register",
    "run": "torchslam.cli.register",
    "merged_cloud": "torchslam.cli.plots",
    "plot_registration": "torchslam.cli.plots",
    "scan_colors": "torchslam.cli.plots",
}
__all__ = sorted(_MOVED)
__getattr__ = _deprecated.moved(__name__, _MOVED)

if __name__ == "__main__":
    from torchslam.cli.register import main

    raise SystemExit(main())
