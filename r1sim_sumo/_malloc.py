"""Keep freed heap memory in the process between policy decisions (glibc only).

A drop-in decision over hundreds of agents allocates and frees the same few-MB temporaries every 0.5 s (edge
features ``[A, 22, 64]``, the rollout cache ``[L, 1, A, 11, 64]``, logits ``[A, 3720]``). With glibc's defaults a
freed block above the (dynamic) mmap threshold is unmapped and the top of the heap is trimmed back to the OS, so the
next decision writes to fresh pages and takes a minor page fault for every 4 KiB of them: on the 700-car city grid
about 134k faults in 30 decisions, and a 3.9 MB ReLU took 2.9 ms where 0.3 would do (session 27, torch profiler).
:func:`keep_freed_memory` sets ``mallopt(M_MMAP_THRESHOLD, 32 MiB)`` (glibc's largest) and ``mallopt(M_TRIM_THRESHOLD,
1 GiB)``: blocks up to 32 MiB come from the heap and up to 1 GiB of freed heap stays mapped for reuse. Peak memory is
unchanged; what the process holds after a peak shrinks later (or not at all below 1 GiB of free heap).

Called once per process by every online host (:class:`~r1sim_sumo.sim.policy_driver.PolicyDriver`). Set
``R1SIM_MALLOC_TUNING=0`` to keep the allocator's settings as they are; other C libraries (musl, macOS) are left alone.
"""

from __future__ import annotations

import ctypes
import logging
import os
import platform

LOG = logging.getLogger(__name__)

M_TRIM_THRESHOLD = -1  # glibc's mallopt parameter numbers (malloc.h)
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 32 << 20  # glibc's maximum (HEAP_MAX_SIZE / 2 on 64-bit)
TRIM_THRESHOLD_BYTES = 1 << 30

_state: dict[str, bool] = {}


def keep_freed_memory() -> bool:
    """Apply the settings above once per process; True when they are in force (now or by an earlier call), False
    when turned off (``R1SIM_MALLOC_TUNING=0``), not glibc, or ``mallopt`` refused."""
    if "applied" in _state:
        return _state["applied"]
    ok = False
    if os.environ.get("R1SIM_MALLOC_TUNING", "1") == "0":
        LOG.info("R1SIM_MALLOC_TUNING=0: heap settings left as they are")
    elif platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        LOG.debug("not glibc (%s): heap settings left as they are", platform.libc_ver())
    else:
        try:
            mallopt = ctypes.CDLL(None).mallopt
            mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
            ok = bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
        except (OSError, AttributeError) as exc:
            LOG.debug("mallopt unavailable (%s)", exc)
    _state["applied"] = ok
    return ok
