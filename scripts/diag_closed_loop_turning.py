#!/usr/bin/env python3
"""Why closed-loop rollouts leave curved roads: teacher-forced turning vs closed-loop token copying, per SUMO network.

    python scripts/diag_closed_loop_turning.py [--checkpoint DIR] [--per-network 4] [--sampler greedy]

Per network (every 7th test scene, up to ``--per-network``), vehicles only:

* teacher forced: on tokens where the logged vehicle turns (|heading change| > 0.05 rad per 0.5 s), the mean
  |heading change| of the argmax token vs the logged token, and how often their signs agree;
* closed loop (one rollout per scene with ``--sampler``): how often an agent's token repeats its previous token, vs
  the same rate in the logged (matched) token sequences; a policy that copies its last token extrapolates its
  current speed and turn rate (off a roundabout's ring, through a bend);
* closed loop: mean speed [m/s] of the policy over the 8 s vs the log's.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

import r1sim_sumo
from r1sim_sumo.evaluate import sumo_scenes_by_network
from r1sim_sumo.rollout.engine import rollout
from r1sim_sumo.rollout.samplers import parse_sampler
from r1sim_sumo.scenario import ScenarioDataset
from r1sim_sumo.tokens.batch import collate, tokenize_scenario

TURN_RAD = 0.05


def repeat_rate(tok: torch.Tensor) -> tuple[int, int]:
    """(repeats, pairs) over consecutive valid tokens ``[A, F]`` (-1 invalid)."""
    a, b = tok[:, :-1], tok[:, 1:]
    ok = (a >= 0) & (b >= 0)
    return int(((a == b) & ok).sum()), int(ok.sum())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="data/generated/default/test")
    ap.add_argument("--checkpoint", default=None)
    ap.add_argument("--per-network", type=int, default=4)
    ap.add_argument("--sampler", default="greedy")
    a = ap.parse_args()
    torch.set_num_threads(2)
    pol = r1sim_sumo.load_policy(a.checkpoint)
    end = torch.as_tensor(pol.vocab.traj[0])[:, -1]  # [V, 3] end pose of each vehicle token (x, y [m], yaw [rad])
    ds = ScenarioDataset(a.data)
    scenes = sumo_scenes_by_network(ds, a.per_network)
    print("| network | turning tokens | log abs(dyaw) | argmax abs(dyaw) | same sign | log repeat | policy repeat | "
          "log speed [m/s] | policy speed [m/s] |\n|---|---|---|---|---|---|---|---|---|")
    for net, scs in sorted(scenes.items()):
        tf, rep_log, rep_pol, spd_log, spd_pol = [], np.zeros(2), np.zeros(2), [], []
        for sc in scs:
            b = collate([tokenize_scenario(sc, pol.vocab)])
            veh = (b.agent_type[0] == 0) & b.agent_mask[0].bool()
            ok = b.agent_token_valid[0].bool() & veh[:, None]
            with torch.no_grad():
                logits = pol.model(b)[0]  # [A, 18, V] teacher forced
            for k in range(2, b.agent_token.shape[-1]):
                m = ok[:, k]
                g, p = end[b.agent_token[0, m, k], 2], end[logits[m, k].argmax(-1), 2]
                tf.append(torch.stack([g, p], -1))
            gt = torch.where(ok, b.agent_token[0], -1)[:, 2:]
            rep_log += repeat_rate(gt[veh])
            res = rollout(pol.model, pol.vocab, b, 1, parse_sampler(a.sampler), generator=torch.Generator().manual_seed(0))
            pt = res.token[0, 0]  # [A, F]
            rep_pol += repeat_rate(pt[veh & (gt[:, 0] >= 0)])
            for tok, out in ((gt, spd_log), (pt, spd_pol)):
                t = tok[veh]
                out.append(float(end[t[t >= 0], :2].norm(dim=-1).mean() / 0.5))
        r = torch.cat(tf)
        turn = r[:, 0].abs() > TURN_RAD
        g, p = r[turn].T
        print(f"| {net} | {int(turn.sum())} | {g.abs().mean():.3f} | {p.abs().mean():.3f} | "
              f"{(torch.sign(g) == torch.sign(p)).float().mean():.2f} | {rep_log[0] / rep_log[1]:.2f} | "
              f"{rep_pol[0] / rep_pol[1]:.2f} | {np.mean(spd_log):.1f} | {np.mean(spd_pol):.1f} |")


if __name__ == "__main__":
    main()
