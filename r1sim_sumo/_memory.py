"""Memory of this process: current and peak resident set size [MB], from ``/proc/self/status`` (Linux).

``resource.getrusage(...).ru_maxrss`` is not used for peaks: Linux carries it over ``fork`` and ``exec``, so a worker
started from a large parent reports the parent's peak. ``VmHWM`` is the peak of this process image only.
"""

from __future__ import annotations

from pathlib import Path


def _status_mb(key: str) -> float:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def rss_mb() -> float:
    """Resident set size now [MB] (``VmRSS``; nan where /proc is not available)."""
    return _status_mb("VmRSS")


def peak_rss_mb() -> float:
    """Peak resident set size of this process image [MB] (``VmHWM``; nan where /proc is not available)."""
    return _status_mb("VmHWM")


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc mallopt parameters


def keep_freed_memory(threshold_bytes: int = 1 << 30) -> bool:
    """Make glibc serve large allocations from the heap and keep freed memory for reuse (``mallopt``).

    A training step allocates and frees hundreds of MB of temporaries; by default glibc maps each block above
    its mmap threshold fresh and unmaps it on free, so every step zero-fills the same pages again (~150k minor
    page faults per step in the training-throughput study). Raising the mmap and trim thresholds to
    ``threshold_bytes`` lets freed blocks be reused. Returns False where glibc is not available (no change)."""
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        libc = ctypes.CDLL(name)
        return bool(libc.mallopt(_M_MMAP_THRESHOLD, int(threshold_bytes))) and bool(libc.mallopt(_M_TRIM_THRESHOLD, 2 * int(threshold_bytes)))
    except (OSError, AttributeError):
        return False
