#!/usr/bin/env python3
"""Does the policy predict the braking its log shows, and does top-K sampling keep it?

    python scripts/diag_braking_truncation.py [CHECKPOINT] [--data data/generated/closeups/val] [--cases 30] [--k 5]

Real windows of the motorway networks (every 3rd scene) where an agent at >= 8 m/s with a vehicle ahead in its lane
brakes by more than 1 m/s over the next 0.5 s in its log (one agent per window, first ``--cases``). One teacher-forced
policy step from the logged history (1.1 s, as the drop-in decides), with the leader and with the leader removed.
Prints the log's speed change over the next 0.5 s next to the policy's: the expectation over the whole vocabulary,
the most likely token's, and the expectation under top-K sampling (the K most likely tokens, renormalised), plus the
probability mass top-K keeps and the mass on tokens more than 1 m/s slower than the most likely one.
Speeds in m/s; a token's speed is its forward displacement over 0.5 s.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

import r1sim_sumo
from r1sim_sumo.scenario import CURRENT_INDEX, N_HISTORY_10HZ, N_WINDOW_10HZ, AgentTracks, ScenarioDataset
from r1sim_sumo.sim.policy_driver import PolicyDriver
from r1sim_sumo.tokens.batch import TokenizedScene, collate
from r1sim_sumo.tokens.matching import match_agents

NETWORKS = ("motorway_merge", "lane_drop")


class Probe:
    def __init__(self, policy, k: int):
        self.policy, self.k, self.drivers = policy, k, {}
        self.speed = torch.as_tensor(policy.vocab.traj[0])[:, -1, 0] / 0.5  # [V] vehicle token speeds [m/s]

    def step(self, sc, keep: np.ndarray) -> dict:
        """Next-speed statistics of agent ``keep[0]`` with only the agents ``keep`` in the scene."""
        a, A = sc.agents.select(keep), len(keep)
        win = AgentTracks.empty(A, N_WINDOW_10HZ)
        for f in ("ids", "agent_type", "length_m", "width_m"):
            setattr(win, f, getattr(a, f))
        for f in (*AgentTracks.PER_STEP, "valid"):
            getattr(win, f)[:, :N_HISTORY_10HZ] = getattr(a, f)[:, :N_HISTORY_10HZ]
        win.desired_speed_mps = np.full(A, np.nan, np.float32)  # unknown: estimated from the history, no future
        net = sc.metadata["network"]
        drv = self.drivers.setdefault(net, PolicyDriver(self.policy, sc.map))
        b = collate([TokenizedScene(match_agents(win, self.policy.vocab), drv._no_map, np.asarray(win.ids).astype(str),
                                    np.arange(A), "diag")])
        b = b._replace(agent_token=b.agent_token[:, :, :3], agent_token_valid=b.agent_token_valid[:, :, :3])
        with torch.no_grad():
            logits = self.policy.model(b, map_ctx=drv._map_ctx, last_step_only=True)[0, 0, -1].float()
        p = torch.softmax(logits, -1)[: len(self.speed)]
        top = torch.topk(p, self.k)
        mode = float(self.speed[int(p.argmax())])
        return {"expected": float((p * self.speed).sum()), "mode": mode,
                "topk": float((top.values * self.speed[top.indices]).sum() / top.values.sum()),
                "topk_mass": float(top.values.sum()), "slower_mass": float(p[self.speed < mode - 1.0].sum())}


def cases(ds, n: int):
    """(scene, agent, leader) of logged braking behind a leader in the motorway networks."""
    c = CURRENT_INDEX
    for i in range(0, len(ds), 3):
        sc = ds[i]
        if sc.metadata.get("network") not in NETWORKS:
            continue
        a = sc.agents
        for j in range(a.num_agents):
            if not a.valid[j, c - 10:c + 6].all() or a.speed_mps[j, c] < 8.0 or a.speed_mps[j, c + 5] - a.speed_mps[j, c] > -1.0:
                continue
            h = a.yaw_rad[j, c]
            rx, ry = a.x_m[:, c] - a.x_m[j, c], a.y_m[:, c] - a.y_m[j, c]
            lon, lat = rx * np.cos(h) + ry * np.sin(h), -rx * np.sin(h) + ry * np.cos(h)
            ahead = np.flatnonzero(a.valid[:, c] & (lon > 0) & (np.abs(lat) < 2.0) & (np.arange(a.num_agents) != j))
            if len(ahead):
                yield sc, j, int(ahead[np.argmin(lon[ahead])]), float(lon[ahead].min())
                n -= 1
                break
        if n <= 0:
            return


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", nargs="?", default=None)
    ap.add_argument("--data", default="data/generated/closeups/val")
    ap.add_argument("--cases", type=int, default=30)
    ap.add_argument("--k", type=int, default=5)
    a = ap.parse_args()
    torch.set_num_threads(1)
    probe = Probe(r1sim_sumo.load_policy(a.checkpoint), a.k)
    rows = []
    for sc, j, lead, gap in cases(ScenarioDataset(a.data), a.cases):
        ag = sc.agents
        others = [k for k in range(ag.num_agents) if k != j and ag.valid[k, :N_HISTORY_10HZ].any()]
        w = probe.step(sc, np.array([j, *others]))
        wo = probe.step(sc, np.array([j, *[k for k in others if k != lead]]))
        v0 = float(ag.speed_mps[j, CURRENT_INDEX])
        rows.append({"v": v0, "log": float(ag.speed_mps[j, CURRENT_INDEX + 5]) - v0, "gap": gap,
                     **{f"{k}_with": w[k] - (v0 if k in ("expected", "mode", "topk") else 0) for k in w},
                     **{f"{k}_without": wo[k] - (v0 if k in ("expected", "mode", "topk") else 0) for k in wo}})
    m = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
    print(f"{len(rows)} logged braking cases ({a.data}); mean speed {m['v']:.1f} m/s, centre distance to the leader {m['gap']:.1f} m")
    print(f"| speed change over 0.5 s [m/s] | log | policy expectation | most likely token | top-{a.k} sampling |")
    print("|---|---|---|---|---|")
    for side in ("with", "without"):
        print(f"| leader {side} | {m['log']:+.2f} | {m['expected_' + side]:+.2f} | {m['mode_' + side]:+.2f} | {m['topk_' + side]:+.2f} |")
    print(f"top-{a.k} keeps {m['topk_mass_with']:.2f} of the probability; tokens > 1 m/s slower than the most likely "
          f"one hold {m['slower_mass_with']:.2f}")


if __name__ == "__main__":
    main()
