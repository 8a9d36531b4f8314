#!/usr/bin/env python3
"""How far is the training estimate of a driver's desired speed from SUMO's own? (issue 19, session 17)

    python scripts/desired_vs_hindsight.py [--networks motorway_merge lane_drop urban_grid] [--seed 300000] [--duration 300]

Until session 17 no SUMO window recorded desired speeds, so training fed the policy the *hindsight* estimate
(:func:`r1sim_sumo.tokens.matching.hindsight_speed`: the highest speed a car reaches between 0.5 s boundary poses of its
9 s window), while the drop-in controller hands it SUMO's (lane limit x speedFactor, capped by maxSpeed). This records
fresh SUMO runs (which now carry SUMO's value) and prints, per network, SUMO's minus the hindsight estimate over the
cars of every window (one window per 5 s): mean [m/s] and the share above 3 m/s, for all cars and for those below 20 m/s
at the current step.
"""

from __future__ import annotations

import argparse

import numpy as np

from r1sim_sumo.data.sumo_reference import SumoGenConfig, iter_sumo_scenarios
from r1sim_sumo.tokens.matching import hindsight_speed

BOUNDARIES = np.arange(0, 91, 5)  # 10 Hz steps of the token boundary poses of a window


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--networks", nargs="+", default=["motorway_merge", "lane_drop", "urban_grid"])
    ap.add_argument("--seed", type=int, default=300000, help="SUMO seed (not one of the training recipes')")
    ap.add_argument("--duration", type=float, default=300.0, help="recorded seconds after a 120 s warm-up")
    a = ap.parse_args(argv)
    print("| network | cars | SUMO - hindsight, mean [m/s] | > 3 m/s | cars < 20 m/s | their mean | their > 3 m/s |")
    print("|---|---|---|---|---|---|---|")
    for net in a.networks:
        cfg = SumoGenConfig(network=net, seed=a.seed, duration_s=a.duration, warmup_s=120.0, stride_steps=50)
        all_d, slow_d = [], []
        for sc in iter_sumo_scenarios(cfg):
            ag, b = sc.agents, BOUNDARIES
            est = hindsight_speed(ag.x_m[:, b], ag.y_m[:, b], ag.valid[:, b], 0.5)
            sumo = np.asarray(ag.desired_speed_mps, np.float64)
            ok = np.isfinite(est) & np.isfinite(sumo) & (ag.agent_type == 0)
            slow = ok & (ag.speed_mps[:, sc.current_index] < 20.0)
            all_d.append((sumo - est)[ok])
            slow_d.append((sumo - est)[slow])
        x, y = np.concatenate(all_d), np.concatenate(slow_d)
        print(f"| {net} | {len(x)} | {x.mean():+.1f} | {np.mean(x > 3):.1%} | {len(y)} | "
              f"{y.mean() if len(y) else float('nan'):+.1f} | {np.mean(y > 3) if len(y) else float('nan'):.1%} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
