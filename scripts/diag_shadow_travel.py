#!/usr/bin/env python3
"""How far the policy plans to go in 0.5 s on a free ring, against how far SUMO's drivers do go (box centres).

    python scripts/diag_shadow_travel.py [--network training/ring_five] [--scale 0.3] [--sampler greedy]
        [--checkpoint CKPT] [--end 400]

SUMO's drivers drive every vehicle (the shadow drive of ``scripts/diag_roundabout_entry.py``: the controller's
commands are dropped) while the controller plans every vehicle every 0.5 s from SUMO's own motion. For each vehicle on
a ring lane (lane id containing ``ring``, SUMO's ``getLeader`` finding no one within 30 m) at a decision, it prints the
mean of:

- the plan's box-centre travel over 0.5 s [m] and SUMO's actual box-centre travel over the next 0.5 s [m];
- the plan's speed per 0.1 s step as the commands drive would command it (lane speeds since session 48), SUMO's speed
  at the decision and 0.5 s later [m/s].

Equal travels with a lower commanded speed mean a units error, not a slow policy (session 48,
``docs/simulate/lane_speed_s48``).
"""

from __future__ import annotations

import argparse

import numpy as np

FREE_M = 30.0  # [m] no leader within this distance: a free ring


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--network", default="training/ring_five")
    ap.add_argument("--scale", type=float, default=0.3, help="demand factor (SUMO --scale)")
    ap.add_argument("--sampler", default="greedy")
    ap.add_argument("--checkpoint", default=None, help="policy (default: the shipped r1sim-nano)")
    ap.add_argument("--end", type=float, default=400.0, help="simulated seconds")
    a = ap.parse_args(argv)

    import torch

    from r1sim_sumo._sumo_env import ensure_sumo_home

    ensure_sumo_home()
    import libsumo as conn

    from r1sim_sumo.adapters.sumo_state import read_vehicle_states
    from r1sim_sumo.model.checkpoint import load_policy
    from r1sim_sumo.resources import network_files
    from r1sim_sumo.sim.sumo_controller import SumoController
    from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command

    torch.set_num_threads(1)
    conn.start(sumo_command(0, sumocfg=network_files(a.network)["sumocfg"], end_s=a.end + 1.0,
                            extra=("--scale", f"{a.scale:g}")))
    policy = load_policy(a.checkpoint) if a.checkpoint else load_policy()
    ctrl = SumoController(conn, policy, control="all", sampler=a.sampler, seed=0, drive="commands",
                          standstill_handoff_s=5.0)
    for name in ("setSpeed", "slowDown", "changeLane", "changeSublane", "moveToXY", "setSpeedMode", "setLaneChangeMode"):
        setattr(conn.vehicle, name, lambda *args, **kwargs: None)  # SUMO's drivers drive

    def centre(v):
        s = read_vehicle_states(conn, [v])
        return np.array([s.x_m[0], s.y_m[0]])

    pending: dict[str, tuple] = {}  # vehicle -> (step due, centre now, planned travel, commanded speeds, speed now)
    rows, profiles, seen = [], [], None
    try:
        for k in range(int(round(a.end / 0.1))):
            conn.simulationStep()
            ctrl.step()
            ids = set(conn.vehicle.getIDList())
            for v, (due, xy0, travel, cmd, v0) in list(pending.items()):
                if k >= due:
                    if v in ids:
                        rows.append((travel, float(np.linalg.norm(centre(v) - xy0)), v0, conn.vehicle.getSpeed(v)))
                        profiles.append(cmd)
                    del pending[v]
            if ctrl.last_plan is None or ctrl.last_plan[1] is seen:
                continue
            seen_ids, plan = ctrl.last_plan
            seen = plan
            for i, v in enumerate(seen_ids):
                rec = ctrl.vehicles.get(v)
                if v not in ids or v in pending or rec is None or not plan.ok[i] or "ring" not in conn.vehicle.getLaneID(v):
                    continue
                lead = conn.vehicle.getLeader(v, FREE_M)
                if lead and lead[0] and lead[1] < FREE_M:
                    continue
                travel = float(np.linalg.norm(plan.xy_m[i, -1] - plan.xy_m[i, 0]))
                pending[v] = (k + 5, centre(v), travel, ctrl._plan_speed[rec.slot].copy(), conn.vehicle.getSpeed(v))
    finally:
        settle_remote_control(conn)  # libsumo keeps pending moveToXY past close (r1sim_sumo.sumo_launch)
        conn.close()
    if not rows:
        print("no free ring vehicle at a decision")
        return 1
    r = np.array(rows)
    print(f"{a.network} x{a.scale:g}, shadow drive, {a.checkpoint or 'r1sim-nano'}, {a.sampler}: {len(r)} free-ring decisions")
    print(f"  box-centre travel over 0.5 s: planned {r[:, 0].mean():.3f} m, SUMO's drivers {r[:, 1].mean():.3f} m")
    print(f"  SUMO's speed at the decision {r[:, 2].mean():.2f} m/s, 0.5 s later {r[:, 3].mean():.2f} m/s; "
          f"commanded per 0.1 s step {np.round(np.mean(profiles, 0), 2).tolist()} m/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
