#!/usr/bin/env python3
"""Offroad and collision rates of the shipped policy vs constant velocity per SUMO network, counted over the whole 8 s
rollout and over the logged agent's lifetime only (``*_log_window``: an agent whose log ends where it leaves the finite
network keeps driving in simulation, off the map). "matched reference (floor)" is the logged future rebuilt from its
rolling-matched tokens: what the vocabulary alone costs.

    python scripts/diag_offroad_log_window.py [--per-network 6] [--rollouts 8] [--sampler topk:5] [--metric wosac legacy]
    python scripts/diag_offroad_log_window.py --per-network 5 --floor-only   # the floor alone, on the learning curve's scenes

``--metric``: the realism computation(s) scored on the same rollouts (wosac = the official one, legacy = before issue 16);
one table per metric.

Scenes: every 7th scene of ``data/generated/default/test`` up to ``--per-network`` per network.
"""

from __future__ import annotations

import argparse
import collections

import numpy as np
import torch

import r1sim_sumo
from r1sim_sumo.evaluate import (
    constant_velocity_sim,
    matched_reference_sim,
    rollouts_to_sim,
    sumo_scenes_by_network,
)
from r1sim_sumo.metrics import compute_realism
from r1sim_sumo.metrics.realism import metric_config
from r1sim_sumo.rollout.engine import rollout
from r1sim_sumo.rollout.samplers import parse_sampler
from r1sim_sumo.scenario import ScenarioDataset
from r1sim_sumo.tokens.batch import collate, tokenize_scenario


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="data/generated/default/test")
    ap.add_argument("--per-network", type=int, default=6)
    ap.add_argument("--rollouts", type=int, default=8)
    ap.add_argument("--sampler", default="topk:5")
    ap.add_argument("--checkpoint", default=None, help="checkpoint folder (default: the shipped policy)")
    ap.add_argument("--metric", nargs="+", choices=["wosac", "legacy"], default=["wosac"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--floor-only", action="store_true",
                    help="only the matched reference (the vocabulary's floor; no policy rollouts, seconds per network)")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    configs = {m: metric_config(m) for m in a.metric}
    pol = r1sim_sumo.load_policy(a.checkpoint)
    ds = ScenarioDataset(a.data)
    scenes = sumo_scenes_by_network(ds, a.per_network)
    keys = ("offroad_rate", "offroad_rate_log_window", "collision_rate", "collision_rate_log_window")
    tables = {m: [f"| network | model | {' | '.join(keys)} |", "|---|---|" + "---|" * len(keys)] for m in a.metric}
    for net, scs in sorted(scenes.items()):
        res = collections.defaultdict(list)
        for sc in scs:
            scene = tokenize_scenario(sc, pol.vocab)
            sims = {"matched reference (floor)": matched_reference_sim(sc, pol.vocab, scene)}
            if not a.floor_only:
                r = rollout(pol.model, pol.vocab, collate([scene]), a.rollouts, parse_sampler(a.sampler),
                            generator=torch.Generator().manual_seed(0))
                sims = {"policy": rollouts_to_sim(r.xy_10hz[:, 0], r.yaw_10hz[:, 0], r.valid_10hz()[:, 0], scene.agent_index, sc),
                        "constant velocity": constant_velocity_sim(sc), **sims}
            for name, sim in sims.items():
                for metric, cfg in configs.items():
                    d = compute_realism(sc, sim, config=cfg).to_dict()
                    res[metric, name].append([d[f"realism/{k}"] for k in keys])
        for (metric, name), rows in res.items():
            m = np.mean(rows, 0)
            tables[metric].append(f"| {net} ({len(scs)} scenes) | {name} | " + " | ".join(f"{v:.3f}" for v in m) + " |")
    for metric, lines in tables.items():
        print(f"\nmetric: {metric}\n" + "\n".join(lines), flush=True)


if __name__ == "__main__":
    main()
