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
