"""Peak memory and CPU time of the processes of a build (as the kernel counts them)."""

from __future__ import annotations

import ctypes
import gc
import resource
import sys

__all__ = ["peak_rss_mb", "rss_mb", "cpu_seconds", "trim_memory"]


def peak_rss_mb() -> float:
    """Peak resident set size of this process since it started [MB]."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0  # bytes on macOS, kB on Linux


def rss_mb() -> float:
    """Resident set size of this process now [MB] (Linux ``/proc``; else the peak)."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return peak_rss_mb()
    return pages * resource.getpagesize() / (1024.0 * 1024.0)


def cpu_seconds() -> float:
    """CPU time of this process so far, user + system [s] (on a loaded machine, wall time is not
    what a build costs: this is)."""
    use = resource.getrusage(resource.RUSAGE_SELF)
    return float(use.ru_utime + use.ru_stime)


def trim_memory() -> bool:
    """Collect garbage and give the heap's free pages back to the OS (glibc ``malloc_trim(0)``,
    which also releases free pages inside the heap, not only at its top); False where there is no
    glibc. A worker's freed memory (the adjustment's parts, an earlier tile) otherwise stays in
    its RSS under the next task's."""
    gc.collect()
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    libc.malloc_trim(0)
    return True
