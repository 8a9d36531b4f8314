#!/usr/bin/env python3
"""Online planning cost, PolicyDriver stateless vs memory mode, on 90 token-chained agents (untrained nano).

Run: ``python scripts/bench_driver_memory.py 1`` (argument: torch threads). Prints the median ms per ``plan`` of two
alternating rounds of each mode (the first two decisions of a round are warm-up).
"""

from __future__ import annotations

import sys
import time

import numpy as np
import torch

sys.path.insert(0, "tests")

from r1sim_sumo.model.untrained import untrained_policy  # noqa: E402
from r1sim_sumo.sim.policy_driver import PolicyDriver  # noqa: E402

AGENTS = 90


def main(threads: int) -> None:
    import test_policy_driver as helpers  # the token-chained history and road of the driver tests

    torch.set_num_threads(threads)
    pol = untrained_policy(0)
    full = helpers._token_chained_history(pol, A=AGENTS, n_tok=12)
    road = helpers._road()
    res: dict[bool, list[float]] = {}
    for memory in (False, True, False, True):
        driver = PolicyDriver(pol, road, sampler="topk:5", seed=0, memory=memory)
        times = []
        for k in range(10):
            history = full.slice_steps(5 * k, 5 * k + 11)
            t0 = time.perf_counter()
            driver.plan(history)
            times.append(time.perf_counter() - t0)
        res.setdefault(memory, []).append(float(np.median(times[2:])))
    print({("memory" if k else "stateless"): [round(1000 * v, 1) for v in vals] for k, vals in res.items()},
          f"ms per plan, {AGENTS} agents")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 1)
