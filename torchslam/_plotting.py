"""matplotlib, imported lazily, for the figures of the command line.

matplotlib is an optional dependency: ``pip install 'torchslam[plot]'`` (the ``dev`` extra
includes it). The library never needs it; only the figures of ``torchslam demo``, ``bench``,
``posegraph --plot`` and ``register`` do, and they import it through :func:`require_pyplot`.
"""

from __future__ import annotations

from types import ModuleType

__all__ = ["INSTALL_HINT", "MatplotlibMissingError", "require_matplotlib", "require_pyplot"]

INSTALL_HINT = "pip install 'torchslam[plot]'"


class MatplotlibMissingError(ImportError):
    """matplotlib is not installed (or cannot be imported); the message says how to fix it."""


def require_matplotlib() -> ModuleType:
    """The ``matplotlib`` module with the non-interactive Agg backend selected.

    Raises:
        MatplotlibMissingError: matplotlib is not installed or cannot be imported.
    """
    try:
        import matplotlib
    except ImportError as error:
        missing = isinstance(error, ModuleNotFoundError) and error.name == "matplotlib"
        problem = "is not installed" if missing else f"cannot be imported ({error})"
        raise MatplotlibMissingError(f"matplotlib {problem}; {INSTALL_HINT}") from None
    matplotlib.use("Agg")  # figures are written to files; no display needed
    return matplotlib


def require_pyplot() -> ModuleType:
    """``matplotlib.pyplot`` with the Agg backend (:func:`require_matplotlib`).

    Raises:
        MatplotlibMissingError: matplotlib is not installed or cannot be imported.
    """
    require_matplotlib()
    try:
        import matplotlib.pyplot as plt
    except ImportError as error:
        raise MatplotlibMissingError(
            f"matplotlib.pyplot cannot be imported ({error}); {INSTALL_HINT}"
        ) from None
    return plt
