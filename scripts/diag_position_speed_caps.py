#!/usr/bin/env python3
"""Why the position drive's vehicles drive below their plans, by lane group: the speed SUMO reports for a moved vehicle
vs the speed it was moved at, and which cap of the safety layer held it.

    python scripts/diag_position_speed_caps.py [--network roundabout] [--scale 0.15] [--end 250] [--seed 0]
        [--speed-carry gains] [--sumo-speed]

Runs the position drive (libsumo, the drop-in's defaults, ``--control all``, standstill hand-off after 5 s) with the
network's demand scaled by ``--scale`` and, every 0.1 s step and policy-driven vehicle, records its lane group (``in`` /
``out`` / ``ring`` / ``junction`` / ``other`` by lane id), the plan's speed over the step, the safety layer's allowed
speed, the speed it was moved at, and SUMO's ``getSpeed`` before and after the step [m/s]. Where the allowed speed is
more than 0.1 m/s below the plan's it names the binding cap: the Krauss leader gap (``leader``), a stop line
(``stop``), the type's max speed (``vmax``) or acceleration (``acc``), with the mean shortfall [m/s]; and the mean of
the ego speed the caps start from minus SUMO's reading.

``--sumo-speed`` restores what the controller did before session 59: the history's speed of a moved vehicle (the next
plan's start speed) is SUMO's reading, and the acceleration cap starts from the vehicle's last 0.1 s displacement.
(Session 59, docs/simulate/moved_speed_s59: at 15% of the roundabout's demand the acceleration cap held ring vehicles
on 33% of their steps by 1.2 m/s with SUMO's reading, which is clipped to the lane's limit x speedFactor and drops to
0.8-4 m/s where a vehicle enters a junction's internal lane.)
"""

from __future__ import annotations

import argparse
from collections import defaultdict


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--network", default="roundabout")
    ap.add_argument("--scale", type=float, default=0.15, help="demand factor (SUMO --scale; default 0.15)")
    ap.add_argument("--end", type=float, default=250.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--speed-carry", default="gains", choices=["off", "gains", "free", "both"])
    ap.add_argument("--sumo-speed", action="store_true", help="plans start from SUMO's reading (before session 59)")
    a = ap.parse_args(argv)

    import libsumo as conn
    import numpy as np
    import torch

    from r1sim_sumo._sumo_env import ensure_sumo_home
    from r1sim_sumo.model.checkpoint import load_policy
    from r1sim_sumo.resources import network_files
    from r1sim_sumo.sim import sumo_controller as sc
    from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command

    torch.set_num_threads(1)
    ensure_sumo_home()
    conn.start(sumo_command(a.seed, sumocfg=network_files(a.network)["sumocfg"], end_s=a.end + 1.0,
                            extra=("--scale", f"{a.scale:g}")))
    ctrl = sc.SumoController(conn, load_policy(), control="all", seed=a.seed, drive="position",
                             standstill_handoff_s=5.0, speed_carry=a.speed_carry)
    if a.sumo_speed:
        ctrl._speed_as_moved = lambda row, slots: None
        plain_allowed = ctrl._allowed_speeds

        def allowed_from_displacement(states, vids, slots):  # no vehicle counts as moved: its displacement starts the cap
            at = ctrl._moved_at.copy()
            ctrl._moved_at[:] = -2
            try:
                return plain_allowed(states, vids, slots)
            finally:
                ctrl._moved_at[:] = at

        ctrl._allowed_speeds = allowed_from_displacement

    def group(vid: str) -> str:
        lane = conn.vehicle.getLaneID(vid)
        return ("ring" if "ring" in lane else "in" if "_in_" in lane else "out" if "_out_" in lane
                else "junction" if lane.startswith(":") else "other")

    causes: dict[str, dict[str, float]] = defaultdict(lambda: defaultdict(float))
    orig_allowed, orig_follow = ctrl._allowed_speeds, ctrl._follow

    def allowed_speeds(states, vids, slots):
        allowed, floor = orig_allowed(states, vids, slots)
        rows = ctrl._row_of_slot[slots]
        v_plan = ctrl.follower.plan_speed(slots, sc.STEP_LENGTH_S)
        known = rows >= 0
        gap, v_lead, lead = ctrl.safety.leader_gap(rows[known], states.x_m, states.y_m, states.yaw_rad, states.length_m,
                                                   states.width_m, states.speed_mps, ctrl.follower.kappa[slots[known]])
        gap = sc._break_mutual_blocks(rows[known], lead, gap, states)
        lim = ctrl._limits[slots]
        vmax = np.where(np.isnan(lim[:, 0]), np.inf, lim[:, 0])
        acc = np.where(np.isnan(lim[:, 1]), np.inf, lim[:, 1])
        dec = np.where(np.isnan(lim[:, 2]), ctrl.safety.decel_mps2, lim[:, 2])
        col, prev = ctrl._k % sc.N_HISTORY_10HZ, (ctrl._k - 1) % sc.N_HISTORY_10HZ
        moved = np.hypot(*(ctrl._hist[slots, col, :2] - ctrl._hist[slots, prev, :2]).T) / sc.STEP_LENGTH_S
        v_now = np.where(ctrl._hist_valid[slots, col] & ctrl._hist_valid[slots, prev], moved, v_plan)
        if not a.sumo_speed:
            v_now = np.where(ctrl._moved_at[slots] == ctrl._k - 1, ctrl._moved_speed[slots], v_now)
        caps = {"leader": np.full(len(slots), np.inf), "stop": np.full(len(slots), np.inf), "vmax": vmax,
                "acc": v_now + acc * sc.STEP_LENGTH_S}
        caps["leader"][known] = ctrl.safety.safe_speed(v_now[known], gap, v_lead, dec[known])
        stop = ctrl._stop_m[slots] - ctrl.follower.prog_m[slots]
        ahead = np.isfinite(stop)
        if ahead.any():
            caps["stop"][ahead] = ctrl.safety.safe_speed(v_now[ahead], np.maximum(stop[ahead], 0.0),
                                                         np.zeros(int(ahead.sum())), dec[ahead],
                                                         min_gap_m=sc.STOP_LINE_MARGIN_M)
        for i, vid in enumerate(vids):
            c = causes[group(vid)]
            c["steps"] += 1
            c["v_plan"] += v_plan[i]
            c["v_allowed"] += min(allowed[i], v_plan[i] + 5.0)
            c["ego_minus_sumo"] += (v_now[i] - states.speed_mps[rows[i]]) if rows[i] >= 0 else 0.0
            if allowed[i] < v_plan[i] - 0.1:
                why = min(caps, key=lambda k: caps[k][i])
                c[why] += 1
                c["short_" + why] += v_plan[i] - allowed[i]
        return allowed, floor

    def follow(slots, v_allowed, *rest):
        out = orig_follow(slots, v_allowed, *rest)
        ids = {r.slot: v for v, r in ctrl.vehicles.items() if r.state == "controlled"}
        for i, s in enumerate(slots.tolist()):
            if s in ids:
                c = causes[group(ids[s])]
                c["v_moved"] += out.speed[i]
                c["sumo_before"] += conn.vehicle.getSpeed(ids[s])
        return out

    ctrl._allowed_speeds, ctrl._follow = allowed_speeds, follow
    try:
        for _ in range(int(round(a.end / sc.STEP_LENGTH_S))):
            conn.simulationStep()
            ctrl.step()
    finally:
        settle_remote_control(conn)
        conn.close()
    print(f"{a.network} x{a.scale:g} demand, {a.end:.0f} s, seed {a.seed}, position drive, speed carry {a.speed_carry}, "
          f"{'SUMO speed (before session 59)' if a.sumo_speed else 'moved speed'}")
    print(f"  {'group':9s} {'steps':>6s} {'plan':>5s} {'allowed':>7s} {'moved':>5s} {'SUMO':>5s} {'ego-SUMO':>8s}  "
          "held by (share of steps, mean shortfall m/s)")
    for g, c in sorted(causes.items()):
        n = max(c["steps"], 1.0)
        held = ", ".join(f"{k} {c[k] / n:.2f} ({c['short_' + k] / max(c[k], 1):.2f})"
                         for k in ("acc", "leader", "stop", "vmax") if c[k])
        print(f"  {g:9s} {int(n):6d} {c['v_plan'] / n:5.2f} {c['v_allowed'] / n:7.2f} {c['v_moved'] / n:5.2f} "
              f"{c['sumo_before'] / n:5.2f} {c['ego_minus_sumo'] / n:8.2f}  {held}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
