"""CPU threads for small tensor work: a few dozen rows run faster on one thread than on several.

At ~20 agent rows a matmul or a softmax takes microseconds, less than waking OpenMP worker threads
(with ``OMP_WAIT_POLICY=PASSIVE`` and a short ``GOMP_SPINCOUNT``, which ``r1sim_sumo`` sets because workers
spinning without bound were 10-30x slower on a shared CPU). :func:`few_threads` runs such work on one thread and restores the caller's thread count.
"""

from __future__ import annotations

from contextlib import contextmanager

import torch

SMALL_ROWS = 64  # work over at most this many agent rows runs on one CPU thread
# 256 while OpenMP workers only slept (PASSIVE alone); with the short spin (r1sim_sumo/__init__.py) two threads are
# faster from ~100 rows on: drop-in decisions, 2 threads on an idle 2-core Intel Xeon (session 26, `python
# benchmarks/compare_revisions.py --base d386812 --only sumo_controller --rounds 2 --threads 2`, threshold 32 vs 256,
# benchmarks/reports/compare_s26_small_rows): motorway_merge 100 agents 17.1 -> 14.6 ms per decision, 200 agents
# 28.0 -> 21.3 ms, city grid 100 agents 19.9 -> 17.2 ms; 50 agents 11.6 -> 12.0 ms (so 50 stays on one thread).


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
