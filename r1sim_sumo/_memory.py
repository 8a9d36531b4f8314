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
    page faults per step in the training-throughput study). A drop-in decision does the same at a smaller scale every
    0.5 s (edge features ``[A, 22, 64]``, the rollout cache, logits ``[A, V]``: on the 700-car city grid 99k-209k faults
    in 30 decisions, a 3.9 MB ReLU taking 2.9 ms; every :class:`~r1sim_sumo.sim.policy_driver.PolicyDriver` calls this).
    Raising the mmap and trim thresholds to ``threshold_bytes`` lets freed blocks be reused; peak memory is unchanged,
    but memory freed after a peak stays with the process. ``R1SIM_MALLOC_TUNING=0`` leaves the allocator as it is.
    Returns False where glibc is not available or the tuning is turned off (no change)."""
    import ctypes
    import ctypes.util
    import os

    if os.environ.get("R1SIM_MALLOC_TUNING", "1") == "0":
        return False
    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        libc = ctypes.CDLL(name)
        return bool(libc.mallopt(_M_MMAP_THRESHOLD, int(threshold_bytes))) and bool(libc.mallopt(_M_TRIM_THRESHOLD, 2 * int(threshold_bytes)))
    except (OSError, AttributeError):
        return False
