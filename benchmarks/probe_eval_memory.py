"""Peak memory and time of pretraining's held-out evaluation on a CPU, with and without the reach crop.

Each setting runs in its own process (peak RSS is per process): ``batches`` evaluation batches of ``batch`` scenes of the
compact val split, the shipped policy, fp32, as `r1sim pretrain` evaluates every ``eval_every`` steps.

    python benchmarks/probe_eval_memory.py --tokens data/tokens/ext --batch 32 --batches 2

Session 34: a GPU config (batch 32) resumed on the CPU trained fine but took ~22 GB during its evaluation, whose scenes
kept their whole maps; training batches were already cropped to the receptive field.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time


def child(tokens: str, batch: int, batches: int, crop: bool, threads: int) -> dict:
    import torch

    import r1sim_sumo
    from r1sim_sumo.model.packed import reach_radius_m
    from r1sim_sumo.tokens.batch import collate
    from r1sim_sumo.tokens.compact import CompactTokenDataset
    from r1sim_sumo.train.pretrain import evaluate_nll

    torch.set_num_threads(threads)
    policy = r1sim_sumo.load_policy()
    ds = CompactTokenDataset(tokens, "val")
    reach = reach_radius_m(policy.model.config) + 1.0 if crop else None
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    ev = evaluate_nll(policy.model, ds, collate, batch, batches, reach_m=reach)
    return {"crop": crop, "batch": batch, "batches": batches, "nll": ev["nll"], "tokens": ev["tokens"],
            "wall_s": time.perf_counter() - t0, "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,
            "rss_before_gb": base / 1e6}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tokens", default="data/tokens/ext")
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--batches", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--child", choices=["crop", "full"], default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        print(json.dumps(child(a.tokens, a.batch, a.batches, a.child == "crop", a.threads)))
        return 0
    rows = []
    for mode in ("crop", "full"):
        out = subprocess.run([sys.executable, __file__, "--tokens", a.tokens, "--batch", str(a.batch), "--batches",
                              str(a.batches), "--threads", str(a.threads), "--child", mode],
                             capture_output=True, text=True, check=True).stdout
        rows.append(json.loads(out.strip().splitlines()[-1]))
    print("| map tokens | scenes per batch | batches | peak RSS [GB] | wall [s] | NLL | tokens |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {'reach crop' if r['crop'] else 'whole maps'} | {r['batch']} | {r['batches']} | {r['peak_rss_gb']:.2f} "
              f"| {r['wall_s']:.1f} | {r['nll']:.5f} | {r['tokens']} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
