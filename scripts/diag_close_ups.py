#!/usr/bin/env python3
"""What the close-up events (``r1sim_sumo.data.close_ups``) add to SUMO reference traffic.

    python scripts/diag_close_ups.py [--network motorway_merge] [--rates 0 60 120] [--seconds 400]

One SUMO run per rate (libsumo, bundled demand, 120 s warm-up, then ``--seconds`` recorded), the same seed for all.
Over the recorded vehicle-steps it prints the share of vehicles above 10 m/s whose time headway (gap from the front
bumper to the leader's rear / own speed) is under 0.6 s and 0.8 s, the share of steps braking harder than 2 and
3.5 m/s^2 and accelerating harder than 1.5 m/s^2, the mean speed [m/s] and SUMO's collision count.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np


def measure(network: str, rate: float, seconds: float, seed: int) -> dict:
    import libsumo

    from r1sim_sumo.data.close_ups import CloseUpInjector, CloseUpSettings
    from r1sim_sumo.data.sumo_reference import (
        SumoGenConfig,
        demand_factor,
        generation_command,
        resolve_network,
        write_scaled_demand,
    )

    cfg = SumoGenConfig(network=network, seed=seed, duration_s=seconds, warmup_s=120.0)
    src = resolve_network(network)
    inj = CloseUpInjector(CloseUpSettings(rate), seed, 0.1)
    n_warm, n_rec = int(cfg.warmup_s * 10), int(seconds * 10)
    headway, accel, speed, collisions = [], [], [], 0
    prev: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        routes = write_scaled_demand(src.route_file, Path(tmp) / "demand.rou.xml", demand_factor(cfg),
                                     cfg.warmup_s + seconds + 1.0, None, None, None)
        libsumo.start(generation_command(src, routes, cfg))
        try:
            for k in range(n_warm + n_rec):
                inj.before_step(libsumo)
                libsumo.simulationStep()
                if k < n_warm:
                    continue
                collisions += libsumo.simulation.getCollidingVehiclesNumber()
                for v in libsumo.vehicle.getIDList():
                    s = libsumo.vehicle.getSpeed(v)
                    if v in prev:
                        accel.append((s - prev[v]) / 0.1)
                    prev[v] = s
                    speed.append(s)
                    if s > 10.0:
                        lead = libsumo.vehicle.getLeader(v, 100.0)
                        if lead and lead[0]:
                            headway.append(lead[1] / s)
        finally:
            libsumo.close()
    hw, acc = np.asarray(headway), np.asarray(accel)
    return {"rate_per_vehicle_hour": rate, "events": inj.events, "vehicle_steps": len(speed),
            "mean_speed_mps": float(np.mean(speed)), "headway_under_0.6s": float(np.mean(hw < 0.6)),
            "headway_under_0.8s": float(np.mean(hw < 0.8)), "braking_over_2": float(np.mean(acc < -2.0)),
            "braking_over_3.5": float(np.mean(acc < -3.5)), "accelerating_over_1.5": float(np.mean(acc > 1.5)),
            "collisions": collisions}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--network", default="motorway_merge")
    ap.add_argument("--rates", type=float, nargs="+", default=[0.0, 60.0, 120.0], help="events per vehicle-hour")
    ap.add_argument("--seconds", type=float, default=400.0, help="recorded simulated seconds per rate")
    ap.add_argument("--seed", type=int, default=7)
    a = ap.parse_args()
    rows = [measure(a.network, r, a.seconds, a.seed) for r in a.rates]
    keys = list(rows[0])
    print(f"{a.network}, seed {a.seed}, {a.seconds:.0f} s recorded after 120 s warm-up")
    print("| " + " | ".join(keys) + " |\n|" + "---|" * len(keys))
    for r in rows:
        print("| " + " | ".join(f"{v:.4f}" if isinstance(v, float) else str(v) for v in r.values()) + " |")


if __name__ == "__main__":
    main()
