#!/usr/bin/env python3
"""GRPO checkpoint vs the pretrained one on held-out SUMO test scenes (8 scenes, 16 rollouts, entropy:16,80 or ``--sampler``, 5 seeds).

``--seeds`` / ``--num-scenes`` give replicates: other rollout seeds on the same scenes, or more scenes (the first 8 are
always the default's).

Needs the default dataset (``r1sim dataset build --out data/generated/default``).
Run: ``python scripts/eval_grpo_vs_pretrained.py [--pretrained DIR] [--grpo DIR] [--metric wosac|legacy] [--out FILE.json]``
(``--grpo`` default: the shipped ``r1sim-grpo``; a run's export, e.g. ``runs/grpo_b/final``, compares that fine-tune
with its own start given as ``--pretrained``).

The shipped ``r1sim-grpo`` (session 13) was fine-tuned from today's shipped ``r1sim-nano``, so the comparison of
its card (``docs/eval_grpo_g75_vs_nano.json``) is the default ``--pretrained`` with
``--grpo r1sim-grpo --sampler entropy:16,80 topk:5``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

import r1sim_sumo
from r1sim_sumo.evaluate import evaluate_policy, summarize_runs
from r1sim_sumo.scenario import ScenarioDataset

SAMPLER = "entropy:16,80"
KEYS = ["realism/rmm", "realism/collision_rate", "realism/offroad_rate"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pretrained", default=None, help="pretrained checkpoint folder (default: the shipped r1sim-nano)")
    ap.add_argument("--grpo", default="r1sim-grpo", help="GRPO checkpoint folder or bundled name (default: r1sim-grpo)")
    ap.add_argument("--metric", choices=["wosac", "legacy"], default="wosac", help="realism computation")
    ap.add_argument("--out", default="eval_grpo_vs_pretrained.json")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--sampler", nargs="+", default=[SAMPLER],
                    help=f"samplers to compare under (default {SAMPLER}, the one GRPO trains with; e.g. also topk:5, the model card's)")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(5)),
                    help="rollout seeds (default 0-4; other seeds are an independent replicate on the same scenes)")
    ap.add_argument("--num-scenes", type=int, default=8,
                    help="held-out SUMO scenes (default 8: the first 8 of the fixed draw; more add scenes after them)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    ds = ScenarioDataset("data/generated/default/test")
    idx = np.random.default_rng(1).choice(len(ds), 80, replace=False)  # the default's draw, kept as the prefix
    if args.num_scenes > 8:  # then the rest of the split in a fixed order
        rest = np.setdiff1d(np.arange(len(ds)), idx)
        idx = np.concatenate([idx, np.random.default_rng(2).permutation(rest)])
    scenes = []
    for i in idx:
        s = ds[int(i)]
        if s.metadata.get("source") == "sumo":
            scenes.append(s)
            if len(scenes) == args.num_scenes:
                break
    out = {}
    for name, ck in [(f"pretrained ({args.pretrained or 'r1sim-nano'})", args.pretrained), (args.grpo, args.grpo)]:
        pol = r1sim_sumo.load_policy(ck)
        for sampler in args.sampler:
            runs = [evaluate_policy(pol, scenes, sampler, 16, seed, batch_scenes=2, progress=False, metric=args.metric)
                    for seed in args.seeds]
            s = summarize_runs(runs)
            out[f"{name} / {sampler}"] = s
            print(name, sampler, {k.split("/")[1]: f"{s[k]:.4f} +- {s[k + '/std']:.4f}" for k in KEYS}, flush=True)
    Path(args.out).write_text(json.dumps({"metric": args.metric, "pretrained": args.pretrained or "r1sim-nano", "grpo": args.grpo,
                                          "seeds": args.seeds,
                                          "scenes": [str(s.metadata) for s in scenes], "results": out}, indent=1, default=str))


if __name__ == "__main__":
    main()
