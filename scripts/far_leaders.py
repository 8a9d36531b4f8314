"""Why a car holds a steady speed below its desired one in SUMO's data: where its nearest same-lane leader is, seen from
the policy (whose agent-to-agent attention reaches ``agent_radius_m`` = 60 m in the nano).

At each window's current index on motorway_merge and lane_drop (every ``--every``-th window), cars (vehicles shorter
than 7 m) at 18-27 m/s, steady over the last 1 s (< 0.3 m/s change) and more than 4 m/s below their recorded desired
speed, by their nearest leader within 1.8 m of their lane's axis (< 60 m, 60-200 m, none within 200 m) and by whether any
other agent is within 60 m; for each group the mean speed change over the next 1 s and the share that speeds up by more
than 0.8 m/s^2.

    python scripts/far_leaders.py data/generated/desired/train --every 5
"""

from __future__ import annotations

import argparse

import numpy as np
from steady_below_desired_share import others_in_own_frame  # scripts/ is on the path when run as a script

from r1sim_sumo.scenario import ScenarioDataset

MOTORWAYS = ("motorway_merge", "lane_drop")
SIGHT_M = 60.0  # [m] the nano's agent_radius_m


def nearest_leader_m(a, t0: int, half_width_m: float = 1.8) -> np.ndarray:
    """``[A]`` [m] distance (box centres, along the agent's heading) to the nearest valid agent ahead within
    ``half_width_m`` of its axis at step ``t0``; inf if none."""
    lon, lat, other = others_in_own_frame(a, t0)
    return np.where((lon > 0.5) & (np.abs(lat) < half_width_m) & other, lon, np.inf).min(1)


def nearest_any_m(a, t0: int) -> np.ndarray:
    """``[A]`` [m] distance to the nearest other valid agent at step ``t0`` (inf if none)."""
    lon, lat, other = others_in_own_frame(a, t0)
    return np.where(other, np.hypot(lon, lat), np.inf).min(1)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", help="a scenario dataset split folder (e.g. data/generated/desired/train)")
    ap.add_argument("--every", type=int, default=5, help="look at every n-th window")
    a = ap.parse_args(argv)
    ds = ScenarioDataset(a.dataset)
    groups: dict[str, list[float]] = {}
    for i in range(0, len(ds), a.every):
        sc = ds[i]
        if sc.metadata.get("network") not in MOTORWAYS or sc.agents.desired_speed_mps is None:
            continue
        ag, t0 = sc.agents, 10
        ok = ag.valid[:, t0] & ag.valid[:, t0 - 10] & ag.valid[:, t0 + 10] & (ag.agent_type == 0) & (ag.length_m < 7)
        v0 = ag.speed_mps[:, t0]
        state = (ok & (np.abs(v0 - ag.speed_mps[:, t0 - 10]) < 0.3) & (ag.desired_speed_mps - v0 > 4.0)
                 & (v0 > 18.0) & (v0 < 27.0))
        lead, near = nearest_leader_m(ag, t0), nearest_any_m(ag, t0)
        dv = ag.speed_mps[:, t0 + 10] - v0  # [m/s] over the next 1 s
        for j in np.flatnonzero(state):
            where = (f"leader < {SIGHT_M:.0f} m" if lead[j] < SIGHT_M else
                     f"leader {SIGHT_M:.0f}-200 m" if lead[j] < 200 else "no leader within 200 m")
            seen = f"nobody within {SIGHT_M:.0f} m" if near[j] > SIGHT_M else f"others within {SIGHT_M:.0f} m"
            groups.setdefault(f"{where}, {seen}", []).append(float(dv[j]))
    print(f"{a.dataset}: cars at 18-27 m/s, steady, > 4 m/s below their desired speed")
    for k, v in sorted(groups.items()):
        arr = np.asarray(v)
        print(f"  {k}: {len(arr)} states, mean acceleration over the next 1 s {arr.mean():+.2f} m/s^2, "
              f"share > 0.8 m/s^2 {np.mean(arr > 0.8):.0%}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
