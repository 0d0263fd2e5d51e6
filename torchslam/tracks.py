"""Deprecated: ``torchslam.tracks`` is now :mod:`torchslam.registration.tracks` (removed in the
next release).

Reading a name here returns the same object from :mod:`torchslam.registration.tracks` with a
``DeprecationWarning``.
"""

from torchslam import _deprecated
from torchslam.registration import tracks as _new

__all__ = list(_new.__all__)
__getattr__ = _deprecated.moved(__name__, "torchslam.registration.tracks")
