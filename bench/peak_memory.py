"""A process's own peak resident memory, for the benches' memory columns."""

from __future__ import annotations

import resource
import sys
from pathlib import Path

PROC_STATUS = Path("/proc/self/status")


def peak_rss_mb() -> float:
    """This process's peak resident set size in MB.

    On Linux it is VmHWM, the high-water mark of the process's own memory: ru_maxrss carries
    the forking parent's peak across exec, so a bench's child started from a large bench
    process would report the bench's memory instead of its own. Elsewhere, ru_maxrss.
    """
    if PROC_STATUS.is_file():
        for line in PROC_STATUS.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024  # kB
    maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return maxrss / 2**20 if sys.platform == "darwin" else maxrss / 1024  # bytes / kB
