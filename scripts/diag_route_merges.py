#!/usr/bin/env python3
"""How vehicles that must change lanes to stay on their route (an acceleration lane, a dropped lane) get out of it.

    python scripts/diag_route_merges.py [--network lane_drop] [--drive position] [--end 600] [--seed 0]
        [--checkpoint r1sim-nano] [--merge-cooperation on|off]

Runs ``r1sim simulate``'s loop (libsumo, the drop-in defaults: greedy tokens, the safety layer, standstill hand-off
after 5 s). Once per simulated 0.5 s, every vehicle on a lane that does not lead on along its route (SUMO's best-lane
offset is not 0) is recorded: who drives it (``controlled`` by the policy, ``handed_back`` with the reason, ``sumo``),
its speed [m/s] and whether it stands (< 0.1 m/s). For each such vehicle that is standing and handed to SUMO, SUMO's
own lane-change state toward its target lane says what blocks the change (leader / follower on the target lane), and
who drives that blocker. Prints per lane: vehicle-seconds by driver and speed band, standing vehicle-seconds by
blocker, and how vehicles left the lane (changed while the policy drove them / while SUMO drove them).
"""

from __future__ import annotations

import argparse
from collections import Counter, defaultdict

# SUMO lane-change state bits (traci.constants.LCA_*)
BLOCKED_BITS = {"left_leader": 512, "left_follower": 1024, "right_leader": 2048, "right_follower": 4096}
NEIGHBOUR_MODES = {"left_follower": 4, "left_leader": 6, "right_follower": 5, "right_leader": 7}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--network", default="lane_drop")
    ap.add_argument("--drive", default="position", choices=("position", "commands"))
    ap.add_argument("--end", type=float, default=600.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--checkpoint", default=None, help="policy (default: the shipped r1sim-nano)")
    ap.add_argument("--sampler", default="greedy")
    ap.add_argument("--merge-cooperation", default=None, choices=("on", "off"),
                    help="SumoController(merge_cooperation=...): the commands drive's yields (default: the controller's)")
    ap.add_argument("--wrong-lane-ahead-s", type=float, default=None,
                    help="override the controller's WRONG_LANE_AHEAD_S [s] (hand-back to SUMO before a lane's end)")
    a = ap.parse_args(argv)

    import libsumo as conn
    import torch

    from r1sim_sumo._sumo_env import ensure_sumo_home
    from r1sim_sumo.model.checkpoint import load_policy
    from r1sim_sumo.resources import network_files
    from r1sim_sumo.sim.sumo_controller import SumoController
    from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command

    torch.set_num_threads(1)
    if a.wrong_lane_ahead_s is not None:
        import r1sim_sumo.sim.sumo_controller as sc

        sc.WRONG_LANE_AHEAD_S = a.wrong_lane_ahead_s
    ensure_sumo_home()
    cfg = network_files(a.network)["sumocfg"]
    conn.start(sumo_command(a.seed, sumocfg=cfg, end_s=a.end + 1.0))
    kw = {} if a.merge_cooperation is None else {"merge_cooperation": a.merge_cooperation == "on"}
    ctrl = SumoController(conn, load_policy(a.checkpoint) if a.checkpoint else load_policy(), control="all",
                          sampler=a.sampler, seed=a.seed, safety="krauss", drive=a.drive, standstill_handoff_s=5.0, **kw)

    def driver(vid: str) -> str:
        rec = ctrl.vehicles.get(vid)
        if rec is None:
            return "sumo"
        return rec.state if rec.state != "handed_back" else f"handed_back:{rec.reason}"

    time_on: dict[str, Counter] = defaultdict(Counter)  # lane -> (driver, speed band) -> vehicle-seconds
    blockers: dict[str, Counter] = defaultdict(Counter)  # lane -> (blocker side, its driver) -> standing veh-s
    last: dict[str, tuple[str, str]] = {}  # vehicle -> (must-change lane, driver) at the last sample
    left: dict[str, Counter] = defaultdict(Counter)  # lane -> how vehicles left it
    try:
        for k in range(int(round(a.end / 0.1))):
            conn.simulationStep()
            ctrl.step()
            if k % 5:
                continue
            now: dict[str, tuple[str, str]] = {}
            for vid in conn.vehicle.getIDList():
                lane = conn.vehicle.getLaneID(vid)
                if not lane or lane.startswith(":"):
                    continue
                offset = next((int(o) for ln, _l, _o, o, _a, _n in conn.vehicle.getBestLanes(vid) if ln == lane), 0)
                if offset == 0:
                    continue
                who = driver(vid)
                v = conn.vehicle.getSpeed(vid)
                band = "stand" if v < 0.1 else "<10" if v < 10 else "<20" if v < 20 else ">=20"
                time_on[lane][(who.split(":")[0] if who != "handed_back:wrong_lane" else who, band)] += 0.5
                now[vid] = (lane, who)
                if band == "stand" and not who.startswith("controlled"):
                    side = 1 if offset > 0 else -1
                    state = conn.vehicle.getLaneChangeState(vid, side)[0]
                    names = [n for n, bit in BLOCKED_BITS.items() if state & bit and n.startswith("left" if side > 0 else "right")]
                    if not names:
                        blockers[lane][("not blocked", "-")] += 0.5
                    for n in names:
                        nb = conn.vehicle.getNeighbors(vid, NEIGHBOUR_MODES[n])
                        blockers[lane][(n, driver(nb[0][0]) if nb else "?")] += 0.5
            for vid, (lane, who) in last.items():
                if vid not in now or now[vid][0] != lane:
                    gone = vid not in conn.vehicle.getIDList()
                    left[lane]["arrived/removed" if gone else f"changed while {who.split(':')[0]}"] += 1
            last = now
    finally:
        settle_remote_control(conn)  # libsumo keeps pending moveToXY past close (r1sim_sumo.sumo_launch)
        conn.close()
    print(f"{a.network} {a.drive} {a.end:.0f} s seed {a.seed} ({a.checkpoint or 'r1sim-nano'}): arrived "
          f"{ctrl.stats.arrived}, handbacks {dict(ctrl.stats.handbacks)}, merge yields "
          f"{getattr(ctrl.stats, 'merge_yields', 0)}")
    for lane in sorted(time_on, key=lambda ln: -sum(time_on[ln].values())):
        c = time_on[lane]
        print(f"lane {lane}: {sum(c.values()):.0f} vehicle-s on it; left it: {dict(left[lane])}")
        print("   " + ", ".join(f"{w}/{b} {n:.0f}" for (w, b), n in c.most_common(8)))
        if blockers[lane]:
            print("   standing (SUMO-driven) by blocker: " + ", ".join(f"{s}={w} {n:.0f}" for (s, w), n in blockers[lane].most_common(8)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
