#!/usr/bin/env python3
"""The greedy draw's row maximum: ``max(-1)`` vs :func:`~r1sim_sumo.rollout.samplers.max_blocked` on drop-in-sized
logits (700 agents x 3,720 vehicle tokens, float32), side by side in one process, and whether they agree; with
``--samplers``, one drop-in decision's whole draw per sampler instead (``Sampler.token_inputs`` + ``Sampler.draw``
over the shipped vocabulary, vehicles; ``median`` also with its travel order sorted per row instead of the per-type
order cached with the vocabulary).

    python benchmarks/probe_greedy_max.py [--rows 700] [--vocab 3720] [--threads 2] [--repeats 200]
    python benchmarks/probe_greedy_max.py --samplers greedy median:0.1 --threads 1 --repeats 20
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
    ap.add_argument("--samplers", nargs="*", default=None, help="time these samplers' draws instead (e.g. greedy median:0.1)")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    if a.samplers:
        return _sampler_draws(a)
    x = torch.randn(1, a.rows, a.vocab, generator=torch.Generator().manual_seed(0))
    same = torch.equal(max_blocked(x)[1], x.max(-1, keepdim=True)[1])
    rounds = [(_ms(lambda: x.max(-1, keepdim=True), a.repeats), _ms(lambda: max_blocked(x), a.repeats)) for _ in range(3)]
    for i, (plain, blocked) in enumerate(rounds):
        print(f"round {i}: max(-1) {plain:.3f} ms, max_blocked {blocked:.3f} ms ({plain / blocked:.2f}x)")
    print(f"{a.rows} x {a.vocab}, {a.threads} thread(s): same indices: {same}")
    return 0


def _sampler_draws(a) -> int:
    from r1sim_sumo.rollout.samplers import parse_sampler

    vocab = r1sim_sumo.load_policy().vocab
    at = torch.zeros(1, a.rows, dtype=torch.long)  # vehicles
    x = torch.randn(1, a.rows, vocab.max_size, generator=torch.Generator().manual_seed(0)) * 3
    for spec in a.samplers:
        s = parse_sampler(spec)
        ms = _ms(lambda s=s: s.draw(x, torch.Generator().manual_seed(0), **s.token_inputs(vocab, at)), a.repeats)
        print(f"{spec}: {ms:.1f} ms per decision")
        if s.kind == "median":
            fwd = s.token_inputs(vocab, at)["token_forward"]
            print(f"{spec}, each row sorted: {_ms(lambda s=s: s.draw(x, token_forward=fwd), a.repeats):.1f} ms per decision")
    print(f"{a.rows} vehicles x {vocab.max_size} tokens, {a.threads} thread(s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
