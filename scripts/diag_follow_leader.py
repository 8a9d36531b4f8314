#!/usr/bin/env python3
"""How much does the policy react to a slower vehicle ahead, and does it accelerate towards the speed limit?

    python scripts/diag_follow_leader.py [CHECKPOINT]

Straight 3-lane motorway of the bundled ``motorway_merge`` network (limit 33.3 m/s), 1.1 s of constant-speed history,
one teacher-forced policy step (as the drop-in controller's stateless driver does). Prints, for a follower at 32 m/s,
the expected speed over the next 0.5 s (probability-weighted over the whole vocabulary) and the three most likely
tokens' speeds, alone and with a 20 m/s (or standing) leader at several gaps; then at 25 m/s as close as 3 m behind a
leader at the same speed, and at 20 m/s behind a faster leader; then a lone vehicle at several speeds.
A traffic model should slow down for close leaders and speed up towards the limit when alone.
"""

from __future__ import annotations

import sys

import numpy as np
import torch

import r1sim_sumo
from r1sim_sumo.adapters.sumo_map import read_sumo_map
from r1sim_sumo.resources import network_files
from r1sim_sumo.scenario import N_HISTORY_10HZ, N_WINDOW_10HZ, AgentTracks
from r1sim_sumo.sim.policy_driver import PolicyDriver
from r1sim_sumo.tokens.batch import TokenizedScene, collate
from r1sim_sumo.tokens.matching import match_agents

LANE_Y_M = -5.6  # centre of lane 1 of edge main_in [m]
LIMIT_MPS = 33.33  # speed limit of main_in [m/s]: every probe vehicle's desired speed (policies with that input)


def next_speed(policy, driver, cars) -> tuple[float, list[float]]:
    """cars: (id, x [m], speed [m/s]) heading east on lane 1; returns the first car's expected next speed [m/s] and
    the speeds of its 3 most likely tokens."""
    A = len(cars)
    win = AgentTracks.empty(A, N_WINDOW_10HZ)
    win.ids = np.array([c[0] for c in cars])
    win.agent_type[:], win.length_m[:], win.width_m[:] = 0, 5.0, 1.8
    win.desired_speed_mps = np.full(A, LIMIT_MPS, np.float32)  # what the drop-in gives: lane limit x speedFactor 1
    t = np.arange(N_HISTORY_10HZ) * 0.1 - 1.0
    for i, (_, x0, v) in enumerate(cars):
        win.x_m[i, :N_HISTORY_10HZ] = x0 + v * t
        win.y_m[i, :N_HISTORY_10HZ] = LANE_Y_M
        win.yaw_rad[i, :N_HISTORY_10HZ] = 0.0
        win.speed_mps[i, :N_HISTORY_10HZ] = v
        win.vx_mps[i, :N_HISTORY_10HZ] = v
        win.valid[i, :N_HISTORY_10HZ] = True
    b = collate([TokenizedScene(match_agents(win, policy.vocab), driver._no_map, win.ids.astype(str), np.arange(A), "diag")])
    b = b._replace(agent_token=b.agent_token[:, :, :3], agent_token_valid=b.agent_token_valid[:, :, :3])
    with torch.no_grad():
        logits = policy.model(b, map_ctx=driver._map_ctx, last_step_only=True)[0, 0, -1].float()
    p = torch.softmax(logits, -1)
    dx = torch.as_tensor(policy.vocab.traj[0])[:, -1, 0]  # [V] forward displacement over 0.5 s [m]
    expected = float((p[: len(dx)] * dx).sum()) / 0.5
    top = torch.topk(p[: len(dx)], 3).indices
    return expected, [round(float(dx[i]) / 0.5, 1) for i in top]


def main() -> None:
    torch.set_num_threads(1)
    policy = r1sim_sumo.load_policy(sys.argv[1] if len(sys.argv) > 1 else None)
    driver = PolicyDriver(policy, read_sumo_map(network_files("motorway_merge")["net"]).polylines)
    rows = [("alone", [("f", 300, 32)])]
    rows += [(f"leader at 20 m/s, gap {g} m", [("f", 300, 32), ("l", 305 + g, 20)]) for g in (40, 25, 15, 8)]
    rows += [("standing leader, gap 20 m", [("f", 300, 32), ("l", 325, 0)])]
    print("follower at 32 m/s           expected next speed   top-3 token speeds [m/s]")
    for name, cars in rows:
        e, top = next_speed(policy, driver, cars)
        print(f"{name:28s} {e:8.1f}              {top}")
    # close behind a leader at its own speed (headway well under SUMO's 1 s: the close-up data's situation) and far
    # behind a faster leader (a follower should close up); gaps are bumper to bumper (cars 5 m long)
    rows = [(f"both at 25 m/s, gap {g} m ({g / 25:.2f} s)", [("f", 300, 25), ("l", 305 + g, 25)]) for g in (30, 12, 6, 3)]
    rows += [(f"at 20 m/s, leader at 28 m/s {g} m ahead", [("f", 300, 20), ("l", 305 + g, 28)]) for g in (60, 30)]
    print("\nfollower and leader               expected next speed   top-3 token speeds [m/s]")
    for name, cars in rows:
        e, top = next_speed(policy, driver, cars)
        print(f"{name:34s} {e:8.1f}              {top}")
    print("\nlone vehicle at v0 [m/s]     expected next speed   top-3 token speeds [m/s]")
    for v0 in (0.5, 3, 8, 15, 22, 28, 32):
        e, top = next_speed(policy, driver, [("f", 300, v0)])
        print(f"{v0:<28g} {e:8.1f}              {top}")


if __name__ == "__main__":
    main()
