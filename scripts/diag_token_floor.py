#!/usr/bin/env python3
"""The vocabulary's offroad / collision floor per SUMO network on the learning curve's held-out scenes: each logged
future rebuilt from its own rolling-matched tokens (``evaluate.matched_reference_sim``), scored like a rollout.

A policy trained on these tokens imitates these paths, so a network whose floor is above a target (issue 19:
offroad over the log window <= 0.05) cannot be expected to meet it without a finer vocabulary or matching.

    python scripts/diag_token_floor.py [--per-network 5] [--checkpoint r1sim-nano]
"""

from __future__ import annotations

import argparse
import collections

import numpy as np
import torch

import r1sim_sumo
from r1sim_sumo.evaluate import matched_reference_sim, sumo_scenes_by_network
from r1sim_sumo.metrics import compute_realism
from r1sim_sumo.metrics.realism import metric_config
from r1sim_sumo.scenario import ScenarioDataset

KEYS = ("offroad_rate", "offroad_rate_log_window", "collision_rate")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="data/generated/default/test")
    ap.add_argument("--per-network", type=int, default=5, help="scenes per network (the learning curve uses 5)")
    ap.add_argument("--checkpoint", default=None, help="whose vocabulary (default: the shipped policy's)")
    a = ap.parse_args()
    torch.set_num_threads(1)
    vocab = r1sim_sumo.load_policy(a.checkpoint).vocab
    cfg = metric_config("wosac")
    print("| network | scenes | " + " | ".join(KEYS) + " |\n|---|---|" + "---|" * len(KEYS))
    for net, scs in sorted(sumo_scenes_by_network(ScenarioDataset(a.data), a.per_network).items()):
        got = collections.defaultdict(list)
        for sc in scs:
            r = compute_realism(sc, matched_reference_sim(sc, vocab), config=cfg)
            for k in KEYS:
                got[k].append(getattr(r, k) if hasattr(r, k) else r.extra[k])
        print(f"| {net} | {len(scs)} | " + " | ".join(f"{np.nanmean(got[k]):.3f}" for k in KEYS) + " |", flush=True)


if __name__ == "__main__":
    main()
