"""Old module paths kept for one release: names that moved, forwarded with a warning.

A shim module (``torchslam/icp.py`` and the like) holds no code of its own. It sets its
module-level ``__getattr__`` to :func:`moved`, so that reading a moved name from it returns the
object at its new home (the very same object) and emits a ``DeprecationWarning`` that names the
new location. Importing a shim warns about nothing; reading a name does, at the caller's line.
docs/reference.md lists the old and the new paths ("Deprecated names").

:func:`callable_tensor` does the same for a method that became a property: the tensor it
returns may still be called, once, with a warning.
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable, Mapping, Sequence

import torch

__all__ = ["callable_tensor", "moved"]


def moved(old: str, new: str | Mapping[str, Sequence[str] | None]) -> Callable[[str], object]:
    """A module ``__getattr__`` forwarding names of module ``old`` to where they live now.

    Args:
        old: the deprecated module path, e.g. ``"torchslam.icp"``.
        new: the module every name moved to (``"torchslam.registration.icp"``), or a mapping
            new module → the names that went there (None: the names of its ``__all__``).

    Returns:
        ``__getattr__(name)``: the object, with a ``DeprecationWarning`` naming
        ``<module>.<name>``; AttributeError for a name that did not move.
    """
    homes: dict[str, str] = {}

    def home(name: str) -> str | None:
        if isinstance(new, str):
            return new
        if not homes:  # first use: the new modules are imported only now
            for module, names in new.items():
                for moved_name in (
                    importlib.import_module(module).__all__ if names is None else names
                ):
                    homes.setdefault(moved_name, module)
        return homes.get(name)

    def __getattr__(name: str) -> object:
        target = None if name.startswith("__") else home(name)
        module = None if target is None else importlib.import_module(target)
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


class _CallableTensor(torch.Tensor):
    """A tensor that can still be called like the method it replaces (see callable_tensor).

    Its ``__torch_function__`` is torch's disabled one: every operation on it returns a
    plain tensor, so the subclass never spreads beyond the attribute read."""

    __torch_function__ = torch._C._disabled_torch_function_impl
    _deprecation: str

    def __call__(self) -> torch.Tensor:
        warnings.warn(self._deprecation, DeprecationWarning, stacklevel=2)
        return self.as_subclass(torch.Tensor)


def callable_tensor(value: torch.Tensor, owner: str, name: str) -> torch.Tensor:
    """``value`` (autograd history kept) for the property ``owner.name`` that was a method:
    calling it, ``owner.name()``, returns the plain tensor with a ``DeprecationWarning``."""
    wrapped = value.as_subclass(_CallableTensor)
    wrapped._deprecation = (
        f"{owner}.{name}() is deprecated: {name} is a property now (a tensor, as "
        f"SolveResult.{name} is); drop the parentheses (the call is removed in the next release)"
    )
    return wrapped
