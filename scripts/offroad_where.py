"""Where a policy leaves the road: closed-loop rollouts on held-out scenes of one network, offroad tokens located.

Rolls out ``--rollouts`` samples of ``--scenes`` test scenes of ``--network`` (every 7th scene of the split on that
network, as ``token_offroad`` of the GRPO reward sees them: any box corner outside the scene map's drivable area at
one of a token's five 10 Hz states) and prints the offroad token rate, the share of offroad tokens whose end point is
past the end of the map's lanes (``x`` beyond the largest lane-centre ``x``: vehicles that drive off a finite network
before their logged twin leaves it), and the places (25 m cells, world frame [m]) where the offroad tokens inside the
log window (the logged agent exists at the token's end) cluster, with the map's lanes for reference.

    python scripts/offroad_where.py --checkpoint r1sim-grpo --network lane_drop [--scenes 6] [--rollouts 8]
"""

from __future__ import annotations

import argparse
import collections

import numpy as np
import torch


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", default="r1sim-grpo")
    ap.add_argument("--network", default="lane_drop")
    ap.add_argument("--data", default="data/generated/default/test")
    ap.add_argument("--scenes", type=int, default=6)
    ap.add_argument("--rollouts", type=int, default=8)
    ap.add_argument("--sampler", default="topk:5")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    import r1sim_sumo
    from r1sim_sumo.rollout.engine import rollout
    from r1sim_sumo.rollout.samplers import parse_sampler
    from r1sim_sumo.scenario import LANE_CENTRE, ScenarioDataset
    from r1sim_sumo.tokens.batch import TokenizedDataset, collate
    from r1sim_sumo.train.rewards import token_offroad

    pol = r1sim_sumo.load_policy(a.checkpoint)
    sd = ScenarioDataset(a.data)
    idx = [i for i in range(0, len(sd), 7) if sd[i].metadata.get("network") == a.network][: a.scenes]
    if not idx:
        raise SystemExit(f"--network {a.network}: no scene of {a.data} is on it")
    td = TokenizedDataset(sd, pol.vocab)
    batch = collate([td[i] for i in idx])
    maps = [sd[i].map for i in idx]
    with torch.no_grad():
        r = rollout(pol.model, pol.vocab, batch, a.rollouts, parse_sampler(a.sampler),
                    generator=torch.Generator().manual_seed(a.seed), num_steps=16)
    off = token_offroad(r.xy_10hz, r.yaw_10hz, r.valid_10hz(), batch.agent_size, maps)  # [G, B, A, F]
    act = r.sim_mask[None, :, :, None] & (r.token >= 0)
    ev = (off & act).nonzero()
    g, b, ag, f = ev.unbind(-1)
    end = r.pose_xy[g, b, ag, f + 1].numpy()  # [n, 2] token end points [m]
    in_log = batch.pose_valid[b, ag, 3 + f].numpy()  # the logged agent exists at the token's end
    lane_x_max = np.array([max(float(m.polyline(k)[:, 0].max()) for k in range(len(m.kind)) if m.kind[k] == LANE_CENTRE)
                           for m in maps])
    past_end = end[:, 0] > lane_x_max[b.numpy()]
    print(f"{a.checkpoint} on {len(idx)} {a.network} scenes x {a.rollouts} rollouts ({a.sampler}): offroad token rate "
          f"{float((off & act).sum() / act.sum().clamp(min=1)):.4f}; {len(end)} offroad tokens, "
          f"{past_end.mean() if len(end) else 0:.0%} past the map's last lane x; inside the log window {int(in_log.sum())}, "
          f"{past_end[in_log].mean() if in_log.any() else 0:.0%} of them past it")
    cells = collections.Counter((int(round(x / 25) * 25), int(round(y / 5) * 5)) for x, y in end[in_log])
    print("offroad tokens inside the log window by 25 m x 5 m cell (x, y) [m]:", cells.most_common(12))
    m = maps[0]
    print("lanes of the first scene (id, start, end [m]):",
          [(str(m.lane_id[k]), np.round(m.polyline(k)[[0, -1]]).astype(int).tolist())
           for k in range(len(m.kind)) if m.kind[k] == LANE_CENTRE and not str(m.lane_id[k]).startswith(":")])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
