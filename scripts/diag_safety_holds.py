#!/usr/bin/env python3
"""Why the position drive's safety layer held policy vehicles below their plans, by lane group: which leader, stop line
or vehicle-type limit.

    python scripts/diag_safety_holds.py [--network roundabout] [--end 300] [--seed 0] [--checkpoint r1sim-nano]
        [--group in=_in --group out=_out --group ring=ring] [--without oncoming] [--without junction-snap]
        [--junction-turns sumo|policy]

Runs ``r1sim simulate``'s loop (libsumo, top-5, ``--drive position`` with the default safety layer, standstill hand-off
after 5 s). Every 0.1 s, for each policy-driven vehicle whose allowed speed is more than 0.5 m/s below its plan's, it
names the cause: the corridor leader (its lane group, ``along`` / ``crossing`` / ``oncoming`` by heading difference
< 45 / < 135 / >= 135 degrees, and who drives it), a ``stop line`` (red / yellow signal, yield, blocked exit) nearer
than the leader, or the vehicle type's max speed / acceleration (``type limits``). A lane belongs to the first
group whose pattern is in its lane id (``other`` if none); a vehicle on a junction's internal lane to ``junction A>B``
by the groups of the route edges it comes from and goes to. Per group it also prints the mean planned and allowed
speed and the share of steps whose plan is below 2 m/s (the policy's own slowness, held or not). ``--without`` switches a
session-31 rule off for comparison (``oncoming``: oncoming vehicles beside the ego count as leaders again;
``junction-snap``: vehicles left on no lane inside a junction are not snapped back onto their route's lane).
"""

from __future__ import annotations

import argparse
from collections import Counter

HELD_BELOW_PLAN_MPS = 0.5
SLOW_PLAN_MPS = 2.0


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
    ap.add_argument("--junction-turns", default="sumo", choices=("sumo", "policy"),
                    help="who drives a vehicle whose plan leaves its route inside a junction (r1sim simulate "
                         "--junction-turns; policy: as before session 60)")
    a = ap.parse_args(argv)
    groups = [g.split("=", 1) for g in (a.group or ["in=_in", "out=_out", "ring=ring"])]
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

    def group_of_vehicle(vid: str) -> str:
        """The lane group of ``vid``; inside a junction also which way it crosses it, by the groups of its route's
        edges before and after (``junction in>ring``: entering the ring)."""
        lane = conn.vehicle.getLaneID(vid)
        if not lane.startswith(":"):
            return group_of(lane)
        route, i = conn.vehicle.getRoute(vid), conn.vehicle.getRouteIndex(vid)
        if 0 <= i < len(route) - 1:
            return f"junction {group_of(route[i])}>{group_of(route[i + 1])}"
        return "junction"

    torch.set_num_threads(1)
    ensure_sumo_home()
    conn.start(sumo_command(a.seed, sumocfg=network_files(a.network)["sumocfg"], end_s=a.end + 1.0))
    ctrl = SumoController(conn, load_policy(a.checkpoint), control="all", sampler=a.sampler, seed=a.seed,
                          safety="krauss", drive="position", standstill_handoff_s=5.0,
                          junction_turns=a.junction_turns)
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
    plan_sum: Counter = Counter()
    allowed_sum: Counter = Counter()
    slow_plan: Counter = Counter()

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
            g = group_of_vehicle(vid)
            steps[g] += 1
            plan_sum[g] += float(v_plan[i])
            allowed_sum[g] += float(min(v_allowed[i], v_plan[i]))
            slow_plan[g] += bool(v_plan[i] < SLOW_PLAN_MPS)
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
                cause = f"leader {group_of_vehicle(other)} {how} {'sumo' if rec is None else rec.state}"
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
    print(f"{a.network} position {a.end:.0f} s seed {a.seed} without {a.without or 'nothing'}, junction turns "
          f"{a.junction_turns}: arrived {arrived}, hand-backs {dict(ctrl.stats.handbacks)}")
    for g, n in sorted(steps.items()):
        c = causes.get(g, Counter())
        print(f"  {g}: {n} policy-driven vehicle-steps, held > {HELD_BELOW_PLAN_MPS} m/s below the plan on "
              f"{sum(c.values())} ({sum(c.values()) / max(n, 1):.0%}); mean plan {plan_sum[g] / max(n, 1):.2f} m/s, "
              f"allowed {allowed_sum[g] / max(n, 1):.2f} m/s, plan below {SLOW_PLAN_MPS:g} m/s on "
              f"{slow_plan[g] / max(n, 1):.0%}")
        for cause, k in c.most_common(8):
            print(f"    {k:6d}  {cause}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
