#!/usr/bin/env python3
"""How the 10 Hz states between a rollout's token boundaries are decoded changes the kinematic realism.

    python scripts/diag_rollout_decoding.py [CHECKPOINT]

The learning curve's 25 held-out scenes (5 per SUMO network), 8 rollouts, top-5, the official realism metric; the same
rollouts (same tokens and boundary poses) decoded three ways:

- ``tokens``: each token's own 10 Hz frames (its cluster representative's; what the rollout engine does today);
- ``chain``: each token's path retimed at one constant acceleration (``r1sim_sumo.rollout.kernel.retime_plan``) from
  the previous segment's end speed (the first from the logged speed now): an error in the start speed swings back and
  forth from token to token, undamped;
- ``central``: the same retiming, each segment starting at the mean of the previous and the current token's speeds
  (causal: both tokens are chosen by the time the segment is driven).

Prints RMM per network and every metric field per decoding.
"""

from __future__ import annotations

import sys

import numpy as np
import torch

import r1sim_sumo
from r1sim_sumo.evaluate import _row, batch_generator, rollouts_to_sim, sumo_scenes_by_network
from r1sim_sumo.metrics import compute_realism
from r1sim_sumo.metrics.realism import metric_config
from r1sim_sumo.rollout.engine import rollout
from r1sim_sumo.rollout.kernel import retime_plan
from r1sim_sumo.rollout.samplers import parse_sampler
from r1sim_sumo.scenario import CURRENT_INDEX, ScenarioDataset
from r1sim_sumo.tokens.batch import collate, tokenize_scenario

MODES = ("tokens", "chain", "central")
TOKEN_S = 0.5  # [s] one token


def retime_all(xy: np.ndarray, yaw: np.ndarray, v_now: np.ndarray, mode: str):
    """``xy [G, A, 81, 2]``, ``yaw [G, A, 81]`` of a rollout with every 0.5 s segment retimed; ``v_now [A]`` [m/s]."""
    G, A, N, _ = xy.shape
    out_xy, out_yaw = xy.copy(), yaw.copy()
    v0 = np.broadcast_to(v_now[None], (G, A)).reshape(-1).astype(np.float64)
    prev_len = v0 * TOKEN_S
    for k in range((N - 1) // 5):
        seg = slice(5 * k, 5 * k + 6)
        seg_xy, seg_yaw = out_xy[:, :, seg].reshape(G * A, 6, 2), out_yaw[:, :, seg].reshape(G * A, 6)
        length = np.linalg.norm(np.diff(seg_xy, axis=1), axis=-1).sum(1)
        start = v0 if mode == "chain" else (prev_len + length) / (2 * TOKEN_S)
        new_xy, new_yaw, speed = retime_plan(seg_xy, seg_yaw, start, 0.1)
        out_xy[:, :, seg], out_yaw[:, :, seg] = new_xy.reshape(G, A, 6, 2), new_yaw.reshape(G, A, 6)
        v0 = speed[:, -1] + 0.5 * (speed[:, -1] - speed[:, -2])  # end speed: last step's + half a step of acceleration
        prev_len = length
    return out_xy, out_yaw


def main() -> None:
    torch.set_num_threads(1)
    pol = r1sim_sumo.load_policy(sys.argv[1] if len(sys.argv) > 1 else None)
    by = sumo_scenes_by_network(ScenarioDataset("data/generated/default/test"), 5)
    cfg = metric_config("wosac")
    res = {m: [] for m in MODES}
    for net, scs in sorted(by.items()):
        for i, sc in enumerate(scs):
            scene = tokenize_scenario(sc, pol.vocab)
            r = rollout(pol.model.eval(), pol.vocab, collate([scene]), num_rollouts=8, sampler=parse_sampler("topk:5"),
                        generator=batch_generator(0, 1000 * len(net) + i))
            v10 = r.valid_10hz()[:, 0]
            xy, yaw = r.xy_10hz[:, 0].numpy().astype(np.float64), r.yaw_10hz[:, 0].numpy().astype(np.float64)
            v_now = np.asarray(sc.agents.speed_mps)[np.asarray(scene.agent_index), CURRENT_INDEX]
            for m in MODES:
                X, Y = (xy, yaw) if m == "tokens" else retime_all(xy, yaw, v_now, m)
                sim = rollouts_to_sim(torch.as_tensor(X, dtype=torch.float32), torch.as_tensor(Y, dtype=torch.float32),
                                      v10, scene.agent_index, sc)
                res[m].append(_row(net, compute_realism(sc, sim, config=cfg)))
        print(net, "RMM", {m: round(float(np.nanmean([r["realism/rmm"] for r in res[m][-len(scs):]])), 4) for m in MODES},
              flush=True)
    keys = [k for k in res["tokens"][0] if k != "scenario"]
    print(f"{'metric':55s} " + " ".join(f"{m:>8s}" for m in MODES))
    for k in keys:
        print(f"{k:55s} " + " ".join(f"{float(np.nanmean([r[k] for r in res[m]])):8.4f}" for m in MODES))


if __name__ == "__main__":
    main()
