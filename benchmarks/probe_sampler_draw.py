#!/usr/bin/env python3
"""One drop-in decision's token draw per sampler: ``Sampler.token_inputs`` + ``Sampler.draw`` on drop-in-sized logits
(700 vehicles x the shipped vocabulary's 3,720 vehicle tokens, float32), side by side in one process; ``median``
also with its travel order sorted per row instead of the per-type order cached with the vocabulary.

    python benchmarks/probe_sampler_draw.py [--rows 700] [--threads 1] [--repeats 20] [--samplers greedy median:0.1]
"""

from __future__ import annotations

import argparse
import time

# isort: off
import r1sim_sumo  # noqa: F401 - first: it sets the OpenMP wait policy before torch loads, as the drop-in does
import torch
# isort: on


def _ms(fn, repeats: int) -> float:
    fn()
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - t0) / repeats * 1e3


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=700)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--samplers", nargs="+", default=["greedy", "median:0.1"])
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
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
            ms = _ms(lambda s=s: s.draw(x, token_forward=fwd), a.repeats)
            print(f"{spec}, each row sorted: {ms:.1f} ms per decision")
    print(f"{a.rows} vehicles x {vocab.max_size} tokens, {a.threads} thread(s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
