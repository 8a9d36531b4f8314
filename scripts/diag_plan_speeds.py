#!/usr/bin/env python3
"""How fast vehicles drive where, and whether the policy plans slow or is held slow: speeds by lane group and driver.

    python scripts/diag_plan_speeds.py [--network roundabout] [--drive native|position|commands] [--end 300]
        [--group in=_in_ --group out=_out_ --group ring=ring] [--seed 0] [--checkpoint r1sim-nano]

Runs ``r1sim simulate``'s loop (libsumo, top-5, the default safety layer, standstill hand-off after 5 s) and once per
simulated second records each vehicle's speed [m/s] by lane group (a lane belongs to the first group whose pattern is
in its lane id; ``other`` else) and by who drives it (``controlled`` by the policy, ``handed_back`` to SUMO, ``sumo``).
For the position drive it also records, every 0.1 s and per policy-driven vehicle, the speed of its plan over the
step, whether the safety layer held it below that (``held``: allowed speed more than 0.1 m/s below the plan's), and
the speed SUMO's driver would want on its lane (``desired``: the lane's limit x speedFactor, capped by the type's max
speed) -- a plan far below ``desired`` with nothing holding it is the policy's own choice.
"""

from __future__ import annotations

import argparse
from collections import defaultdict


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--network", default="roundabout")
    ap.add_argument("--drive", default="position", choices=("native", "position", "commands"))
    ap.add_argument("--end", type=float, default=300.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--checkpoint", default=None, help="policy (default: the shipped r1sim-nano)")
    ap.add_argument("--sampler", default="median:0.1", help="token sampler (default median:0.1, the drop-in's since session 47; greedy in sessions 32-46; "
                    "the outputs of sessions 30-31 were measured with topk:5)")
    ap.add_argument("--group", action="append", default=[], metavar="NAME=PATTERN",
                    help="lane group: lanes whose id contains PATTERN (default: the roundabout's in / out / ring)")
    a = ap.parse_args(argv)
    groups = [g.split("=", 1) for g in (a.group or ["in=_in_", "out=_out_", "ring=ring"])]
    for g in groups:
        if len(g) != 2 or not g[1]:
            ap.error(f"--group {'='.join(g)}: expected NAME=PATTERN, e.g. ring=ring")

    import libsumo as conn
    import numpy as np
    import torch

    from r1sim_sumo._sumo_env import ensure_sumo_home
    from r1sim_sumo.adapters.sumo_state import read_desired_speeds
    from r1sim_sumo.model.checkpoint import load_policy
    from r1sim_sumo.resources import network_files
    from r1sim_sumo.sim.sumo_controller import STEP_LENGTH_S, SumoController
    from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command

    def group_of(lane: str) -> str:
        return next((name for name, pat in groups if pat in lane), "other")

    torch.set_num_threads(1)
    ensure_sumo_home()
    conn.start(sumo_command(a.seed, sumocfg=network_files(a.network)["sumocfg"], end_s=a.end + 1.0))
    ctrl = None
    if a.drive != "native":
        ctrl = SumoController(conn, load_policy(a.checkpoint), control="all", sampler=a.sampler, seed=a.seed,
                              safety="krauss", drive=a.drive, standstill_handoff_s=5.0)
    speeds: dict[tuple[str, str], list[float]] = defaultdict(list)  # (group, driver) -> speeds once per second
    plans: dict[str, list[tuple[float, bool, float]]] = defaultdict(list)  # group -> (plan, held, desired) per step
    if ctrl is not None and a.drive == "position":
        follow = ctrl._follow

        def recording_follow(slots, v_allowed, *rest):
            v_plan = ctrl.follower.plan_speed(slots, STEP_LENGTH_S)
            vid_of = {r.slot: v for v, r in ctrl.vehicles.items() if r.state == "controlled"}
            rows = [(i, vid_of[s]) for i, s in enumerate(slots.tolist()) if s in vid_of]
            desired = read_desired_speeds(conn, [vid for _, vid in rows])  # what the drop-in gives the policy
            for (i, vid), want in zip(rows, desired.tolist(), strict=True):
                held = v_allowed is not None and bool(v_allowed[i] < v_plan[i] - 0.1)
                plans[group_of(conn.vehicle.getLaneID(vid))].append((float(v_plan[i]), held, float(want)))
            return follow(slots, v_allowed, *rest)

        ctrl._follow = recording_follow
    arrived = 0
    try:
        for k in range(int(round(a.end / STEP_LENGTH_S))):
            conn.simulationStep()
            if ctrl is not None:
                ctrl.step()
            arrived += conn.simulation.getArrivedNumber()
            if k % 10:
                continue
            for vid in conn.vehicle.getIDList():
                rec = None if ctrl is None else ctrl.vehicles.get(vid)
                driver = "sumo" if rec is None else rec.state
                speeds[(group_of(conn.vehicle.getLaneID(vid)), driver)].append(conn.vehicle.getSpeed(vid))
    finally:
        settle_remote_control(conn)  # libsumo keeps pending moveToXY past close (r1sim_sumo.sumo_launch)
        conn.close()
    print(f"{a.network} {a.drive} {a.end:.0f} s seed {a.seed}: arrived {arrived}")
    print(f"  {'group':8s} {'driver':12s} {'veh-s':>7s} {'mean v':>7s} {'standing':>8s}")
    for (g, d), v in sorted(speeds.items()):
        v = np.asarray(v)
        print(f"  {g:8s} {d:12s} {len(v):7d} {v.mean():7.2f} {np.mean(v < 0.1):8.2f}")
    if plans:
        print("  policy-driven, every 0.1 s:  plan speed / held below it by the safety layer / desired speed")
        for g, rows in sorted(plans.items()):
            p = np.asarray(rows, np.float64)
            desired = p[:, 2][p[:, 2] >= 0]  # off its lanes SUMO answers a huge negative number (or the query fails: NaN)
            print(f"  {g:8s} {len(p):7d} steps  plan {p[:, 0].mean():5.2f}  held {p[:, 1].mean():4.2f}  "
                  f"desired {desired.mean() if len(desired) else float('nan'):5.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
