"""Old module paths kept for one release: names that moved, forwarded with a warning.

A shim module (``torchslam/icp.py`` and the like) holds no code of its own. It sets its
module-level ``__getattr__`` to :func:`moved`, so that reading a moved name from it returns the
object at its new home (the very same object) and emits a ``DeprecationWarning`` that names the
new location. Importing a shim warns about nothing; reading a name does, at the caller's line.
README.md lists the old and the new paths ("Deprecated names").
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable, Mapping

__all__ = ["moved"]


def moved(old: str, new: str | Mapping[str, str]) -> Callable[[str], object]:
    """A module ``__getattr__`` forwarding names of module ``old`` to where they live now.

    Args:
        old: the deprecated module path, e.g. ``"torchslam.icp"``.
        new: the module every name moved to (``"torchslam.registration.icp"``), or a mapping
            name → module for names that went to different modules.

    Returns:
        ``__getattr__(name)``: the object, with a ``DeprecationWarning`` naming
        ``<module>.<name>``; AttributeError for a name that did not move.
    """

    def __getattr__(name: str) -> object:
        target = new if isinstance(new, str) else new.get(name)
        module = None
        if target is not None and not name.startswith("__"):
            module = importlib.import_module(target)
        if module is None or not hasattr(module, name):
            raise AttributeError(f"module {old!r} has no attribute {name!r}")
        warnings.warn(
            f"{old}.{name} is deprecated: use {target}.{name} (the old name is removed in the "
            "next release)",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(module, name)

    return __getattr__
