#!/usr/bin/env python3
"""The greedy draw's row maximum: ``max(-1)`` vs :func:`~r1sim_sumo.rollout.samplers.max_blocked` on drop-in-sized
logits (700 agents x 3,720 vehicle tokens, float32), side by side in one process, and whether they agree.

    python benchmarks/probe_greedy_max.py [--rows 700] [--vocab 3720] [--threads 2] [--repeats 200]
"""

from __future__ import annotations

import argparse
import time

# isort: off
import r1sim_sumo  # noqa: F401 - first: it sets the OpenMP wait policy before torch loads, as the drop-in does
import torch
# isort: on

from r1sim_sumo.rollout.samplers import max_blocked


def _ms(fn, repeats: int) -> float:
    fn()
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - t0) / repeats * 1e3


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=700)
    ap.add_argument("--vocab", type=int, default=3720)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=200)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    x = torch.randn(1, a.rows, a.vocab, generator=torch.Generator().manual_seed(0))
    same = torch.equal(max_blocked(x)[1], x.max(-1, keepdim=True)[1])
    rounds = [(_ms(lambda: x.max(-1, keepdim=True), a.repeats), _ms(lambda: max_blocked(x), a.repeats)) for _ in range(3)]
    for i, (plain, blocked) in enumerate(rounds):
        print(f"round {i}: max(-1) {plain:.3f} ms, max_blocked {blocked:.3f} ms ({plain / blocked:.2f}x)")
    print(f"{a.rows} x {a.vocab}, {a.threads} thread(s): same indices: {same}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
