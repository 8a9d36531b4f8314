#!/usr/bin/env python3
"""Where and why vehicles stand in a drop-in run: standing vehicle-seconds by lane, controller state and cause.

    python scripts/diag_standing.py [--network roundabout] [--drive position] [--end 300] [--seed 0] [--top 15]

Runs ``r1sim simulate``'s loop (libsumo, the shipped r1sim-nano, top-5, the default safety layer) and once per
simulated second records every vehicle slower than 0.1 m/s: its lane, who drives it (``controlled`` by the policy,
``handed_back`` to SUMO with the hand-back reason, or ``sumo``), and what holds it: the rule stop the safety layer
found at the last decision (``red`` / ``yield`` / ``blocked``, position drive), a leader within 10 m (``leader``), or
nothing the controller knows of (``none``). Prints the lanes with most standing vehicle-seconds and, per lane, the
split by state and cause; the first vehicles of standing queues (no leader within 10 m) are the ones to look at.
"""

from __future__ import annotations

import argparse
from collections import Counter, defaultdict


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--network", default="roundabout")
    ap.add_argument("--drive", default="position", choices=("position", "commands"))
    ap.add_argument("--end", type=float, default=300.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--top", type=int, default=15)
    a = ap.parse_args(argv)

    import libsumo as conn
    import numpy as np
    import torch

    from r1sim_sumo._sumo_env import ensure_sumo_home
    from r1sim_sumo.model.checkpoint import load_policy
    from r1sim_sumo.resources import network_files
    from r1sim_sumo.sim.sumo_controller import SumoController
    from r1sim_sumo.sumo_launch import sumo_command

    torch.set_num_threads(1)
    ensure_sumo_home()
    cfg = network_files(a.network)["sumocfg"]
    conn.start(sumo_command(a.seed, sumocfg=cfg, end_s=a.end + 1.0))
    ctrl = SumoController(conn, load_policy(), control="all", sampler="topk:5", seed=a.seed, safety="krauss",
                          drive=a.drive, standstill_handoff_s=5.0)
    stand: dict[str, Counter] = defaultdict(Counter)  # lane -> (state, cause) -> vehicle-seconds
    heads: Counter = Counter()  # (lane, state, cause) of queue heads
    try:
        for k in range(int(round(a.end / 0.1))):
            conn.simulationStep()
            ctrl.step()
            if k % 10:
                continue
            for vid in conn.vehicle.getIDList():
                if conn.vehicle.getSpeed(vid) >= 0.1:
                    continue
                lane = conn.vehicle.getLaneID(vid)
                rec = ctrl.vehicles.get(vid)
                state = "sumo" if rec is None else rec.state
                if state == "handed_back":
                    state += f":{rec.reason}"
                lead = conn.vehicle.getLeader(vid, 10.0)
                cause = "leader" if lead and lead[0] else "none"
                if rec is not None and rec.state == "controlled" and np.isfinite(ctrl._stop_m[rec.slot]):
                    cause = f"rule<{ctrl._stop_m[rec.slot]:.0f}m" if cause == "none" else cause
                stand[lane][(state, cause)] += 1
                if cause != "leader":
                    heads[(lane, state, cause)] += 1
    finally:
        conn.close()
    total = sum(sum(c.values()) for c in stand.values())
    print(f"{a.network} {a.drive} {a.end:.0f} s seed {a.seed}: {total} standing vehicle-seconds; "
          f"arrived {ctrl.stats.arrived}, rule stops {dict(ctrl.stats.rule_stops)}")
    for lane, c in sorted(stand.items(), key=lambda kv: -sum(kv[1].values()))[: a.top]:
        parts = ", ".join(f"{s}/{cause} {n}" for (s, cause), n in c.most_common(5))
        print(f"  {lane:24s} {sum(c.values()):6d}  {parts}")
    print("queue heads (standing with no leader within 10 m), vehicle-seconds:")
    for (lane, s, cause), n in heads.most_common(a.top):
        print(f"  {lane:24s} {s:28s} {cause:12s} {n}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
