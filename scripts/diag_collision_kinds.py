#!/usr/bin/env python3
"""What kind of collisions a drop-in run has: who drove each vehicle and where SUMO had it (lane, junction, no lane).

    python scripts/diag_collision_kinds.py [--network roundabout] [--drive position] [--end 900] [--seed 0]
        [--checkpoint r1sim-nano] [--without junction-snap] [--without oncoming] [--list 20]

Runs ``r1sim simulate``'s loop (libsumo, top-5, the default safety layer, standstill hand-off after 5 s) and after
every 0.1 s step finds the vehicle pairs whose boxes overlap (the separating-axis test of the report's
``collisions_boxes``; a pair touching again within 3 s is the same event). Per event it records each vehicle's
driver (``controlled`` by the policy, ``handed_back`` to SUMO, ``sumo``), where SUMO has it (``lane``, ``internal``:
a junction's internal lane, ``none``: no lane, e.g. placed off the internal lanes inside a junction) and the heading
difference [degrees]. ``--without`` switches a session-31 safety-layer rule off for comparison (``junction-snap``:
vehicles left on no lane inside a junction are not snapped back onto their route's lane; ``oncoming``: oncoming
vehicles on the other lane count as leaders again).
"""

from __future__ import annotations

import argparse
from collections import Counter

COLLISION_EVENT_GAP_STEPS = 30  # 3 s at 0.1 s: as r1sim_sumo.sim.collision_events


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--network", default="roundabout")
    ap.add_argument("--drive", default="position", choices=("position", "commands"))
    ap.add_argument("--end", type=float, default=900.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sampler", default="median:0.1", help="token sampler (default median:0.1, the drop-in's since session 47; greedy in sessions 32-46; "
                    "earlier outputs were measured with topk:5)")
    ap.add_argument("--checkpoint", default=None, help="policy (default: the shipped r1sim-nano)")
    ap.add_argument("--without", action="append", default=[], choices=("junction-snap", "oncoming"))
    ap.add_argument("--list", type=int, default=20, help="print the first N events")
    a = ap.parse_args(argv)

    import libsumo as conn
    import numpy as np
    import torch

    import r1sim_sumo.sim.safety_filter as safety_filter
    from r1sim_sumo._sumo_env import ensure_sumo_home
    from r1sim_sumo.adapters.sumo_state import read_vehicle_states
    from r1sim_sumo.geometry import boxes_overlap
    from r1sim_sumo.model.checkpoint import load_policy
    from r1sim_sumo.resources import network_files
    from r1sim_sumo.sim.sumo_controller import STEP_LENGTH_S, SumoController
    from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command

    if "oncoming" in a.without:
        safety_filter.ONCOMING_RAD = np.pi  # no heading difference is "oncoming": the corridor test alone decides
    if "junction-snap" in a.without:
        SumoController._junction_snaps = lambda self, todo, keep: keep
    torch.set_num_threads(1)
    ensure_sumo_home()
    conn.start(sumo_command(a.seed, sumocfg=network_files(a.network)["sumocfg"], end_s=a.end + 1.0))
    ctrl = SumoController(conn, load_policy(a.checkpoint), control="all", sampler=a.sampler, seed=a.seed,
                          safety="krauss", drive=a.drive, standstill_handoff_s=5.0)

    def where(vid: str) -> str:
        lane = conn.vehicle.getLaneID(vid)
        return "none" if not lane else "internal" if lane.startswith(":") else "lane"

    def driver(vid: str) -> str:
        rec = ctrl.vehicles.get(vid)
        return "sumo" if rec is None else rec.state

    last: dict[tuple[str, str], int] = {}
    events = []
    try:
        for k in range(int(round(a.end / STEP_LENGTH_S))):
            conn.simulationStep()
            ctrl.step()
            s = read_vehicle_states(conn)
            if len(s) < 2:
                continue
            ov = boxes_overlap(s.x_m[:, None], s.y_m[:, None], s.yaw_rad[:, None], s.length_m[:, None], s.width_m[:, None],
                               s.x_m[None], s.y_m[None], s.yaw_rad[None], s.length_m[None], s.width_m[None])
            for i, j in np.argwhere(np.triu(ov, 1)):
                pair = (str(s.ids[i]), str(s.ids[j]))
                if k - last.get(pair, -10**9) > COLLISION_EVENT_GAP_STEPS:
                    d = (np.degrees(s.yaw_rad[j] - s.yaw_rad[i]) + 180.0) % 360.0 - 180.0
                    events.append((k * STEP_LENGTH_S, *(f"{v}:{driver(v)}@{where(v)}" for v in pair), abs(float(d))))
                last[pair] = k
    finally:
        settle_remote_control(conn)  # libsumo keeps pending moveToXY past close (r1sim_sumo.sumo_launch)
        conn.close()
    print(f"{a.network} {a.drive} {a.end:.0f} s seed {a.seed} without {a.without or 'nothing'}: {len(events)} box-overlap events")
    kinds = Counter(" + ".join(sorted(e.split(":", 1)[1] for e in ev[1:3])) for ev in events)
    print("  by driver@where (both vehicles):")
    for kind, n in kinds.most_common():
        print(f"    {n:5d}  {kind}")
    angles = Counter(int(min(ev[3], 180.0) // 45) * 45 for ev in events)
    print("  by heading difference [deg]: " + ", ".join(f"{lo}-{lo + 45}: {n}" for lo, n in sorted(angles.items())))
    for ev in events[: a.list]:
        print(f"    t={ev[0]:6.1f} s  {ev[1]}  x  {ev[2]}  dpsi {ev[3]:5.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
