#!/usr/bin/env python3
"""Log futures next to closed-loop policy rollouts on test scenes of one SUMO network (a picture of how rollouts
fail, e.g. vehicles leaving a roundabout's ring tangentially).

    python scripts/plot_network_rollouts.py roundabout --out docs/img/roundabout_rollouts.png [--checkpoint DIR]

Scenes: the first ``--scenes`` of every 7th scene of ``data/generated/default/test`` on that network; 4 rollouts each.
"""

from __future__ import annotations

import argparse

import matplotlib
import numpy as np
import torch

import r1sim_sumo
from r1sim_sumo.evaluate import rollouts_to_sim, sumo_scenes_by_network
from r1sim_sumo.rollout.engine import rollout
from r1sim_sumo.rollout.samplers import parse_sampler
from r1sim_sumo.scenario import ScenarioDataset
from r1sim_sumo.tokens.batch import collate, tokenize_scenario
from r1sim_sumo.viz import plot_scenario


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("network")
    ap.add_argument("--out", required=True)
    ap.add_argument("--data", default="data/generated/default/test")
    ap.add_argument("--checkpoint", default=None)
    ap.add_argument("--scenes", type=int, default=2)
    ap.add_argument("--sampler", default="topk:5")
    a = ap.parse_args()
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    torch.set_num_threads(2)
    pol = r1sim_sumo.load_policy(a.checkpoint)
    ds = ScenarioDataset(a.data)
    scs = sumo_scenes_by_network(ds, a.scenes).get(a.network, [])
    if not scs:
        raise SystemExit(f"{a.data}: no scene of network '{a.network}'")
    fig, axs = plt.subplots(len(scs), 2, figsize=(14, 6.5 * len(scs)), squeeze=False)
    for r, sc in enumerate(scs):
        scene = tokenize_scenario(sc, pol.vocab)
        res = rollout(pol.model, pol.vocab, collate([scene]), 4, parse_sampler(a.sampler),
                      generator=torch.Generator().manual_seed(0))
        sim = rollouts_to_sim(res.xy_10hz[:, 0], res.yaw_10hz[:, 0], res.valid_10hz()[:, 0], scene.agent_index, sc)
        xy = np.stack([sim.x_m, sim.y_m], -1)  # [4, A, 80, 2]
        xy[~sim.valid] = np.nan
        ci = sc.current_index
        log = np.stack([sc.agents.x_m[:, ci:], sc.agents.y_m[:, ci:]], -1)
        log[~sc.agents.valid[:, ci:]] = np.nan
        plot_scenario(sc, axs[r, 0], rollouts=log)
        axs[r, 0].set_title(f"{a.network}: logged 8 s futures", fontsize=9)
        plot_scenario(sc, axs[r, 1], rollouts=xy)
        axs[r, 1].set_title(f"{a.network}: 4 closed-loop rollouts ({a.sampler})", fontsize=9)
    fig.tight_layout()
    fig.savefig(a.out, dpi=70)
    print(a.out)


if __name__ == "__main__":
    main()
