"""How often a dataset shows motorway vehicles speeding back up: the share of agent-states (at each window's current
index, every ``--every``-th window of motorway_merge and lane_drop) below 20 m/s, and below 20 m/s while speeding up by
more than 0.8 m/s^2 over the next 2 s.

    python scripts/speed_recovery_share.py data/generated/default/train data/generated/recovery/train
"""

from __future__ import annotations

import argparse

from r1sim_sumo.scenario import ScenarioDataset

MOTORWAYS = ("motorway_merge", "lane_drop")
SLOW_MPS, SPEEDING_UP_MPS2, HORIZON_STEPS = 20.0, 0.8, 20  # 20 steps of 0.1 s = 2 s


def shares(root: str, every: int = 7) -> dict:
    ds = ScenarioDataset(root)
    n_all = n_slow = n_up = 0
    for i in range(0, len(ds), every):
        sc = ds[i]
        if sc.metadata.get("network") not in MOTORWAYS:
            continue
        a, t0 = sc.agents, 10
        ok = a.valid[:, t0] & a.valid[:, t0 + HORIZON_STEPS]
        v0, v1 = a.speed_mps[:, t0], a.speed_mps[:, t0 + HORIZON_STEPS]
        slow = ok & (v0 < SLOW_MPS)
        n_all, n_slow = n_all + int(ok.sum()), n_slow + int(slow.sum())
        n_up += int((slow & ((v1 - v0) / (HORIZON_STEPS * 0.1) > SPEEDING_UP_MPS2)).sum())
    return {"agent_states": n_all, "slow": n_slow / max(n_all, 1), "slow_and_speeding_up": n_up / max(n_all, 1)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("datasets", nargs="+", help="dataset split folders (e.g. data/generated/default/train)")
    ap.add_argument("--every", type=int, default=7, help="look at every n-th window")
    a = ap.parse_args(argv)
    for root in a.datasets:
        s = shares(root, a.every)
        print(f"{root}: {s['agent_states']} motorway agent-states, below {SLOW_MPS:.0f} m/s {s['slow']:.1%}, "
              f"below and speeding up {s['slow_and_speeding_up']:.1%}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
