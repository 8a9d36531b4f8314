#!/usr/bin/env python3
"""Why the position drive's safety layer held policy vehicles below their plans, by lane group: which leader, stop line
or vehicle-type limit.

    python scripts/diag_safety_holds.py [--network roundabout] [--end 300] [--seed 0] [--checkpoint r1sim-nano]
        [--group in=_in_ --group out=_out_ --group ring=ring] [--without oncoming] [--without junction-snap]

Runs ``r1sim simulate``'s loop (libsumo, top-5, ``--drive position`` with the default safety layer, standstill hand-off
after 5 s). Every 0.1 s, for each policy-driven vehicle whose allowed speed is more than 0.5 m/s below its plan's, it
names the cause: the corridor leader (its lane group, ``along`` / ``crossing`` / ``oncoming`` by heading difference
< 45 / < 135 / >= 135 degrees, and who drives it), a ``stop line`` (red / yellow signal, yield, blocked exit) nearer
than the leader, or the vehicle type's max speed / acceleration (``type limits``). A lane belongs to the first
group whose pattern is in its lane id (``junction`` for internal lanes, ``other`` else). ``--without`` switches a
session-31 rule off for comparison (``oncoming``: oncoming vehicles beside the ego count as leaders again;
``junction-snap``: vehicles left on no lane inside a junction are not snapped back onto their route's lane).
"""

from __future__ import annotations

import argparse
from collections import Counter

HELD_BELOW_PLAN_MPS = 0.5


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--network", default="roundabout")
    ap.add_argument("--end", type=float, default=300.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sampler", default="median:0.1", help="token sampler (default median:0.1, the drop-in's since session 47; greedy in sessions 32-46; "
                    "earlier outputs were measured with topk:5)")
    ap.add_argument("--checkpoint", default=None, help="policy (default: the shipped r1sim-nano)")
    ap.add_argument("--group", action="append", default=[], metavar="NAME=PATTERN",
                    help="lane group: lanes whose id contains PATTERN (default: the roundabout's in / out / ring)")
    ap.add_argument("--without", action="append", default=[], choices=("junction-snap", "oncoming"))
    a = ap.parse_args(argv)
    groups = [g.split("=", 1) for g in (a.group or ["in=_in_", "out=_out_", "ring=ring"])]
    for g in groups:
        if len(g) != 2 or not g[1]:
            ap.error(f"--group {'='.join(g)}: expected NAME=PATTERN, e.g. ring=ring")

    import libsumo as conn
    import numpy as np
    import torch

    import r1sim_sumo.sim.safety_filter as safety_filter
    from r1sim_sumo._sumo_env import ensure_sumo_home
    from r1sim_sumo.model.checkpoint import load_policy
    from r1sim_sumo.resources import network_files
    from r1sim_sumo.sim.sumo_controller import STEP_LENGTH_S, SumoController
    from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command

    if "oncoming" in a.without:
        safety_filter.ONCOMING_RAD = np.pi  # no heading difference is "oncoming": the corridor test alone decides
    if "junction-snap" in a.without:
        SumoController._junction_snaps = lambda self, todo, keep: keep

    def group_of(lane: str) -> str:
        if lane.startswith(":"):
            return "junction"
        return next((name for name, pat in groups if pat in lane), "other")

    torch.set_num_threads(1)
    ensure_sumo_home()
    conn.start(sumo_command(a.seed, sumocfg=network_files(a.network)["sumocfg"], end_s=a.end + 1.0))
    ctrl = SumoController(conn, load_policy(a.checkpoint), control="all", sampler=a.sampler, seed=a.seed,
                          safety="krauss", drive="position", standstill_handoff_s=5.0)
    seen: dict = {}
    leader_gap = ctrl.safety.leader_gap

    def recording_leader_gap(rows, *args, **kw):
        out = leader_gap(rows, *args, **kw)
        seen["leaders"] = (np.asarray(rows), out)
        return out

    object.__setattr__(ctrl.safety, "leader_gap", recording_leader_gap)  # a frozen dataclass: wrap its method
    allowed_speeds = ctrl._allowed_speeds

    def recording_allowed_speeds(states, vids, slots):
        seen["states"], seen["vids"] = states, list(vids)
        return allowed_speeds(states, vids, slots)

    ctrl._allowed_speeds = recording_allowed_speeds
    follow = ctrl._follow
    steps: Counter = Counter()
    causes: dict[str, Counter] = {}

    def recording_follow(slots, v_allowed, v_floor=None):
        if v_allowed is None or "states" not in seen:
            return follow(slots, v_allowed, v_floor)
        v_plan = ctrl.follower.plan_speed(slots, STEP_LENGTH_S)
        st = seen["states"]
        ids = [str(v) for v in st.ids]
        row_of = {v: i for i, v in enumerate(ids)}
        rows, (gap, _v_lead, lead) = seen["leaders"]
        pos_of = {int(r): n for n, r in enumerate(rows.tolist())}
        for i, vid in enumerate(seen["vids"]):
            g = group_of(conn.vehicle.getLaneID(vid))
            steps[g] += 1
            if v_allowed[i] >= v_plan[i] - HELD_BELOW_PLAN_MPS:
                continue
            r = row_of.get(vid)
            n = pos_of.get(r, -1)
            slot = ctrl.vehicles[vid].slot
            stop_m = ctrl._stop_m[slot] - ctrl.follower.prog_m[slot]
            if n >= 0 and lead[n] >= 0 and not (np.isfinite(stop_m) and stop_m < gap[n]):
                other = ids[lead[n]]
                d = abs((np.degrees(st.yaw_rad[lead[n]] - st.yaw_rad[r]) + 180.0) % 360.0 - 180.0)
                how = "along" if d < 45.0 else "crossing" if d < 135.0 else "oncoming"
                rec = ctrl.vehicles.get(other)
                cause = f"leader {group_of(conn.vehicle.getLaneID(other))} {how} {'sumo' if rec is None else rec.state}"
            elif np.isfinite(stop_m):
                cause = "stop line"
            else:
                cause = "type limits"
            causes.setdefault(g, Counter())[cause] += 1
        return follow(slots, v_allowed, v_floor)

    ctrl._follow = recording_follow
    arrived = 0
    try:
        for _ in range(int(round(a.end / STEP_LENGTH_S))):
            conn.simulationStep()
            ctrl.step()
            arrived += conn.simulation.getArrivedNumber()
    finally:
        settle_remote_control(conn)  # libsumo keeps pending moveToXY past close (r1sim_sumo.sumo_launch)
        conn.close()
    print(f"{a.network} position {a.end:.0f} s seed {a.seed} without {a.without or 'nothing'}: arrived {arrived}")
    for g, n in sorted(steps.items()):
        c = causes.get(g, Counter())
        print(f"  {g}: {n} policy-driven vehicle-steps, held > {HELD_BELOW_PLAN_MPS} m/s below the plan on "
              f"{sum(c.values())} ({sum(c.values()) / max(n, 1):.0%})")
        for cause, k in c.most_common(8):
            print(f"    {k:6d}  {cause}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
