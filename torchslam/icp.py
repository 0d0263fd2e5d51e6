"""Deprecated: ``torchslam.icp`` is now :mod:`torchslam.registration.icp` (removed in the
next release).

Reading a name here returns the same object from :mod:`torchslam.registration.icp` with a
``DeprecationWarning``.
"""

from torchslam import _deprecated
from torchslam.registration import icp as _new

__all__ = list(_new.__all__)
__getattr__ = _deprecated.moved(__name__, "torchslam.registration.icp")
