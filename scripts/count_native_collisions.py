"""Collision events of SUMO's own drivers on a bundled network, counted as the drop-in's runs count them.

SUMO drives every vehicle (no policy); each 0.1 s step the events are counted with SUMO's junction check on
(``--collision.check-junctions true --collision.mingap-factor 0``, :data:`r1sim_sumo.sumo_launch.COLLISION_FLAGS`)
and box overlaps of any two vehicles (:class:`r1sim_sumo.sim.collision_events.CollisionCounter`), as in the native rows
of ``docs/simulate/report.md``. Prints one line per (network, seed): events (SUMO-reported / any), arrivals and the
mean speed over vehicle-steps [m/s]; ``--describe N`` lists the first N events with each vehicle's type, lane,
front-bumper position and SUMO angle (degrees clockwise from north).

    python scripts/count_native_collisions.py --networks urban_intersection urban_grid --seeds 0 1 2
    python scripts/count_native_collisions.py --networks urban_grid --net-file old.net.xml --seeds 0   # another build
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from r1sim_sumo._sumo_env import ensure_sumo_home, sumo_binary
from r1sim_sumo.adapters.sumo_state import clear_static_cache, read_vehicle_states
from r1sim_sumo.resources import network_files
from r1sim_sumo.sim.collision_events import CollisionCounter
from r1sim_sumo.sumo_launch import sumo_args


def count(network: str, seed: int, end_s: float, net_file: str | None = None, describe: int = 0) -> dict:
    """One native run of ``network``'s default demand; returns its counts (see the module doc)."""
    import libsumo

    extra = ["--net-file", net_file] if net_file else []
    libsumo.start([sumo_binary("sumo"), *sumo_args(seed, sumocfg=network_files(network)["sumocfg"], end_s=end_s,
                                                    extra=extra)])
    clear_static_cache()
    counter, n_sumo, n_any, arrived, speed_sum, steps, shown = CollisionCounter(), 0, 0, 0, 0.0, 0, []
    try:
        while libsumo.simulation.getTime() < end_s - 1e-6:
            libsumo.simulationStep()
            states = read_vehicle_states(libsumo)
            c = counter.update(libsumo, states)
            n_sumo, n_any = n_sumo + c.sumo, n_any + c.either
            arrived += libsumo.simulation.getArrivedNumber()
            speed_sum, steps = speed_sum + float(states.speed_mps.sum()), steps + len(states.ids)
            for pair in sorted(counter.onsets["sumo"] | counter.onsets["sat"]):
                if len(shown) >= describe:
                    break
                v = libsumo.vehicle
                shown.append({"time_s": round(libsumo.simulation.getTime(), 1),
                              "check": "+".join(k for k in ("sumo", "sat") if pair in counter.onsets[k]),
                              "vehicles": [{"id": i, "type": v.getTypeID(i), "lane": v.getLaneID(i),
                                            "front_bumper_m": [round(a, 2) for a in v.getPosition(i)],
                                            "angle_deg": round(v.getAngle(i), 1), "speed_mps": round(v.getSpeed(i), 2)}
                                           for i in pair]})
    finally:
        libsumo.close()
    return {"network": network, "seed": seed, "end_s": end_s, "net_file": net_file, "events_sumo": n_sumo,
            "events_any": n_any, "arrived": arrived, "mean_speed_mps": round(speed_sum / max(steps, 1), 3),
            "events": shown}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--networks", nargs="+", required=True, help="bundled network names (r1sim_sumo.resources)")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--end", type=float, default=900.0, help="simulated seconds [s]")
    ap.add_argument("--net-file", default=None, help="a .net.xml to run instead of the bundled one (one network)")
    ap.add_argument("--describe", type=int, default=0, help="list the first N events of each run")
    ap.add_argument("--json", default=None, help="write every run's counts to this file")
    args = ap.parse_args(argv)
    if args.net_file and len(args.networks) != 1:
        ap.error("--net-file replaces one network's .net.xml: pass exactly one name to --networks")
    ensure_sumo_home()
    runs = []
    for name in args.networks:
        for seed in args.seeds:
            r = count(name, seed, args.end, args.net_file, args.describe)
            runs.append(r)
            print(f"{name} seed {seed}: events sumo {r['events_sumo']} any {r['events_any']}  arrived {r['arrived']}  "
                  f"mean speed {r['mean_speed_mps']:.2f} m/s", flush=True)
            for e in r["events"]:
                print("   ", e["time_s"], e["check"], " | ".join(
                    f"{x['id']} {x['type']} {x['lane']} fb={x['front_bumper_m']} {x['angle_deg']} deg "
                    f"{x['speed_mps']} m/s" for x in e["vehicles"]))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(runs, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
