"""Peak resident memory of a block of code, for the experiments (one helper for all of them).

``with PeakMemory() as peak: ...`` then ``peak.extra_mib``: the extra resident memory the block
needed, its outputs included. On Linux ≥ 4.0 the kernel's peak-RSS counter is reset on entry
(writing "5" to /proc/self/clear_refs) and the figure is the peak RSS (VmHWM) at exit minus
the RSS (VmRSS) at entry. Where that is not possible, it is the growth of ``ru_maxrss`` over
the block, a lower bound (zero when the process had a higher peak before). ``peak.method``
says which was used. Measure in a fresh process, the block's first run: afterwards glibc
keeps freed blocks and later runs look cheaper. tracemalloc does not see torch's allocations.

Import it from a script in this folder (``from peak_memory import PeakMemory``): the folder of
the script that runs is on ``sys.path``.
"""

from __future__ import annotations

import math
import re
import resource
from pathlib import Path

__all__ = ["PeakMemory"]


def _status_kib(field: str) -> int | None:
    """A ``kB`` field (VmRSS, VmHWM) of /proc/self/status, or None where there is none."""
    try:
        text = Path("/proc/self/status").read_text()
    except OSError:
        return None
    match = re.search(rf"^{field}:\s+(\d+) kB", text, re.MULTILINE)
    return int(match.group(1)) if match else None


def _reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS counter (VmHWM) of this process; False if not possible."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


class PeakMemory:
    """Context manager: the extra resident memory (MiB) of the block, in ``extra_mib``."""

    def __init__(self) -> None:
        self.extra_mib = math.nan
        self.method = ""

    def __enter__(self) -> PeakMemory:
        self._exact = _reset_peak_rss()
        self._rss_before = _status_kib("VmRSS")
        self._maxrss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB (Linux)
        return self

    def __exit__(self, *exc_info: object) -> None:
        peak = _status_kib("VmHWM")
        if self._exact and self._rss_before is not None and peak is not None:
            extra_kib = peak - self._rss_before
            self.method = "VmHWM after a clear_refs reset, minus VmRSS before the block"
        else:
            maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
            extra_kib = maxrss - self._maxrss_before
            self.method = "ru_maxrss growth over the block (a lower bound)"
        self.extra_mib = extra_kib / 1024
