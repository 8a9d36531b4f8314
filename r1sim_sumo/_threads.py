"""CPU threads for small tensor work: a few hundred rows run faster on one thread than on several.

At ~100 agent rows a matmul or a softmax takes tens of microseconds, less than waking OpenMP worker threads
(with ``OMP_WAIT_POLICY=PASSIVE`` and a short ``GOMP_SPINCOUNT``, which ``r1sim_sumo`` sets because workers
spinning without bound were 10-30x slower on a shared CPU). :func:`few_threads` runs such work on one thread and restores the caller's thread count.
"""

from __future__ import annotations

from contextlib import contextmanager

import torch

SMALL_ROWS = 256  # work over at most this many agent rows runs on one CPU thread


@contextmanager
def few_threads(rows: int, device: str | torch.device = "cpu"):
    """Run the block on one CPU thread when ``rows <= SMALL_ROWS`` (CPU only); the thread count is restored."""
    n = torch.get_num_threads()
    if rows > SMALL_ROWS or n <= 1 or torch.device(device).type != "cpu":
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)
