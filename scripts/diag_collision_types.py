#!/usr/bin/env python3
"""What kind of collisions the policy has in closed loop, per network.

    python scripts/diag_collision_types.py [CHECKPOINT]

The learning curve's 25 held-out scenes (5 per SUMO network), 8 rollouts, top-5, the engine's default decoding. For
every policy-driven agent its first box overlap with another agent (states 1..80 at 10 Hz) is classified by the
other agent's pose in the agent's frame at that state:

- ``angle``: headings more than 30 deg apart (crossing at a junction, entering a roundabout);
- ``side``: headings within 30 deg, the other's centre more than 0.6 x the mean width to the side (lane changes,
  merges, drifting into the next lane);
- ``rear_end_into_leader``: the other is ahead (the agent ran into it); ``struck_from_behind``: the other is behind.

Both agents of a pair count, each from its own side. Prints counts per network, the share of agent-rollouts per
kind and the median speed at the overlap [m/s].
"""

import collections
import sys

import numpy as np
import torch

import r1sim_sumo
from r1sim_sumo.evaluate import batch_generator, sumo_scenes_by_network
from r1sim_sumo.geometry import boxes_overlap
from r1sim_sumo.rollout.engine import rollout
from r1sim_sumo.rollout.samplers import parse_sampler
from r1sim_sumo.scenario import ScenarioDataset
from r1sim_sumo.tokens.batch import collate, tokenize_scenario

KINDS = ("angle", "side", "rear_end_into_leader", "struck_from_behind")


def classify(d_xy: np.ndarray, yaw_a: float, yaw_o: float, width_a: float, width_o: float) -> str:
    """The kind of an overlap of agent ``a`` with agent ``o`` whose centre is ``d_xy`` [m] from ``a``'s centre."""
    fwd = d_xy @ np.array([np.cos(yaw_a), np.sin(yaw_a)])
    lat = d_xy @ np.array([-np.sin(yaw_a), np.cos(yaw_a)])
    dh = abs((yaw_o - yaw_a + np.pi) % (2 * np.pi) - np.pi)
    if dh > np.radians(30):
        return "angle"
    if abs(lat) > 0.6 * 0.5 * (width_a + width_o):
        return "side"
    return "rear_end_into_leader" if fwd > 0 else "struck_from_behind"


def first_overlaps(xy: np.ndarray, yaw: np.ndarray, valid: np.ndarray, length: np.ndarray, width: np.ndarray):
    """``(agent, state, other)`` of each agent's first overlap in one rollout: ``xy [A, T, 2]``, ``yaw / valid [A, T]``."""
    x, y, h = xy[..., 0].T, xy[..., 1].T, yaw.T  # [T, A]
    ov = boxes_overlap(x[:, :, None], y[:, :, None], h[:, :, None], length[None, :, None], width[None, :, None],
                       x[:, None, :], y[:, None, :], h[:, None, :], length[None, None, :], width[None, None, :])
    ok = valid.T
    ov &= ok[:, :, None] & ok[:, None, :]
    n = len(length)
    ov[:, np.arange(n), np.arange(n)] = False
    for a in range(n):
        ts = np.flatnonzero(ov[:, a].any(1))
        if len(ts):
            yield a, int(ts[0]), int(np.flatnonzero(ov[ts[0], a])[0])


def main() -> None:
    torch.set_num_threads(1)
    pol = r1sim_sumo.load_policy(sys.argv[1] if len(sys.argv) > 1 else None)
    by = sumo_scenes_by_network(ScenarioDataset("data/generated/default/test"), 5)
    total, per, speeds = collections.Counter(), collections.defaultdict(collections.Counter), collections.defaultdict(list)
    agent_rollouts = 0
    for net, scs in sorted(by.items()):
        for i, sc in enumerate(scs):
            b = collate([tokenize_scenario(sc, pol.vocab)])
            r = rollout(pol.model.eval(), pol.vocab, b, num_rollouts=8, sampler=parse_sampler("topk:5"),
                        generator=batch_generator(0, 1000 * len(net) + i))
            xy, yaw = r.xy_10hz[:, 0, :, 1:].double().numpy(), r.yaw_10hz[:, 0, :, 1:].double().numpy()  # [G, A, 80(, 2)]
            valid = r.valid_10hz()[:, 0, :, 1:].numpy()
            sim = r.sim_mask[0].numpy()
            length, width = b.agent_size[0, :, 0].double().numpy(), b.agent_size[0, :, 1].double().numpy()
            agent_rollouts += len(xy) * int(sim.sum())
            for g in range(len(xy)):
                for a, t, o in first_overlaps(xy[g], yaw[g], valid[g], length, width):
                    if not sim[a]:
                        continue
                    kind = classify(xy[g, o, t] - xy[g, a, t], yaw[g, a, t], yaw[g, o, t], width[a], width[o])
                    total[kind] += 1
                    per[net][kind] += 1
                    if t + 1 < xy.shape[2]:
                        speeds[kind].append(float(np.linalg.norm(xy[g, a, t + 1] - xy[g, a, t]) / 0.1))
        print(net, {k: per[net][k] for k in KINDS}, flush=True)
    print(f"agent-rollouts {agent_rollouts}, colliding {sum(total.values())} "
          f"({sum(total.values()) / max(agent_rollouts, 1):.4f})")
    print("share of agent-rollouts:", {k: round(total[k] / max(agent_rollouts, 1), 4) for k in KINDS})
    print("median speed at the overlap [m/s]:", {k: round(float(np.median(speeds[k])), 1) if speeds[k] else None for k in KINDS})


if __name__ == "__main__":
    main()
