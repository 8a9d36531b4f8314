"""How often SUMO's own drivers hold a steady speed below their desired one with their lane free ahead.

Runs a bundled network's default demand in libsumo (step 0.1 s, seed 400000) for ``--end`` simulated seconds and,
every 2 s after ``--warmup``, looks at each vehicle at >= 15 m/s, at least 3 m/s below its desired speed (the lane's
limit x its speedFactor, capped by its type's maxSpeed: ``getAllowedSpeed``) and with no leader within 100 m on its
route: "free below-allowed" vehicle-states. Of those it counts the ones whose speed changed by less than 0.3 m/s over
the last 2 s ("held"). Prints both, the mean speed of all vehicles and the arrivals. ``--overtake-right`` runs SUMO with
``--lanechange.overtake-right true``: with SUMO's default (LC2013 keeps a vehicle behind a slower one in the lane to its
left) many free vehicles are held; the recipe ``configs/dataset_overtake_right.yaml`` records traffic without that rule.

    python scripts/free_lane_holds.py lane_drop [--overtake-right] [--end 600]
"""

from __future__ import annotations

import argparse
import collections


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("network", help="bundled network name (lane_drop, motorway_merge, ...)")
    ap.add_argument("--overtake-right", action="store_true", help="SUMO's --lanechange.overtake-right true")
    ap.add_argument("--end", type=float, default=600.0, help="simulated seconds [s]")
    ap.add_argument("--warmup", type=float, default=120.0, help="seconds [s] before vehicles are looked at")
    ap.add_argument("--examples", type=int, default=0,
                    help="print this many held vehicles with the nearest vehicle ahead in the lane to their left")
    a = ap.parse_args(argv)

    from r1sim_sumo._sumo_env import ensure_sumo_home, sumo_binary
    from r1sim_sumo.resources import network_files

    ensure_sumo_home()
    import libsumo as c

    extra = ["--lanechange.overtake-right", "true"] if a.overtake_right else []
    c.start([sumo_binary("sumo"), "-c", str(network_files(a.network)["sumocfg"]), "--step-length", "0.1", "--seed",
             "400000", "--no-warnings", "true", "--no-step-log", "true", *extra])
    speeds: dict[str, collections.deque] = {}
    free = held = seen = arrived = shown = 0
    speed_sum = 0.0
    try:
        for k in range(int(round(a.end / 0.1))):
            c.simulationStep()
            arrived += c.simulation.getArrivedNumber()
            for v in c.vehicle.getIDList():
                speeds.setdefault(v, collections.deque(maxlen=21)).append(c.vehicle.getSpeed(v))
            if k * 0.1 < a.warmup or k % 20:
                continue
            for v in c.vehicle.getIDList():
                h = speeds[v]
                sp = h[-1]
                seen += 1
                speed_sum += sp
                if len(h) < 21 or sp < 15.0:
                    continue
                allowed = min(c.vehicle.getAllowedSpeed(v), c.vehicle.getMaxSpeed(v))
                lead = c.vehicle.getLeader(v, 100.0)
                if allowed - sp < 3.0 or (lead and lead[0]):
                    continue
                free += 1
                if abs(h[-1] - h[0]) < 0.3:
                    held += 1
                    if shown < a.examples:
                        shown += 1
                        left = c.vehicle.getLeftLeaders(v)
                        lv = f"{left[0][0]} {left[0][1]:.1f} m ahead at {c.vehicle.getSpeed(left[0][0]):.1f} m/s" if left else "none"
                        print(f"t={k * 0.1:.0f} s {v} on {c.vehicle.getLaneID(v)}: {sp:.1f} m/s, desired {allowed:.1f}; "
                              f"left lane's leader: {lv}")
    finally:
        c.close()
    rule = "passing on the right allowed" if a.overtake_right else "SUMO's default (no passing on the right)"
    print(f"{a.network}, {rule}: free below-allowed vehicle-states {free}, held steady over 2 s {held} "
          f"({held / max(free, 1):.0%}); mean speed {speed_sum / max(seen, 1):.2f} m/s; arrivals {arrived}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
