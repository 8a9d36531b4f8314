#!/usr/bin/env python3
"""Where and why vehicles stand in a drop-in run: standing vehicle-seconds by lane, controller state and cause.

    python scripts/diag_standing.py [--network roundabout] [--drive position] [--end 300] [--seed 0] [--top 15]

Runs ``r1sim simulate``'s loop (libsumo, the shipped r1sim-nano, ``--sampler`` (greedy), the default safety layer) and once per
simulated second records every vehicle slower than 0.1 m/s: its lane, who drives it (``controlled`` by the policy,
``handed_back`` to SUMO with the hand-back reason, or ``sumo``), and what holds it: the rule stop the safety layer
found at the last decision (``red`` / ``yield`` / ``blocked``, position drive), a leader within 10 m (``leader``), or
nothing the controller knows of (``none``). Prints the lanes with most standing vehicle-seconds and, per lane, the
split by state and cause; the first vehicles of standing queues (no leader within 10 m) are the ones to look at.

For standing policy-driven vehicles it also says which vehicle the safety filter's corridor found ahead at the last
step (``filter:``): SUMO's own leader of the vehicle (``sumo-leader``), a vehicle crossing or merging at more than 45
degrees to it (``crossing``, e.g. one waiting at a roundabout entry beside the ring), another one (``other``), or none
(``none``) -- a filter leader SUMO does not see ahead is a stop SUMO's drivers would not make.
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
    ap.add_argument("--sampler", default="median:0.1", help="token sampler (default median:0.1, the drop-in's since session 47; greedy in sessions 32-46; "
                    "earlier outputs were measured with topk:5)")
    ap.add_argument("--top", type=int, default=15)
    a = ap.parse_args(argv)

    import libsumo as conn
    import numpy as np
    import torch

    from r1sim_sumo._sumo_env import ensure_sumo_home
    from r1sim_sumo.model.checkpoint import load_policy
    from r1sim_sumo.resources import network_files
    from r1sim_sumo.sim.sumo_controller import SumoController
    from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command

    torch.set_num_threads(1)
    ensure_sumo_home()
    cfg = network_files(a.network)["sumocfg"]
    conn.start(sumo_command(a.seed, sumocfg=cfg, end_s=a.end + 1.0))
    ctrl = SumoController(conn, load_policy(), control="all", sampler=a.sampler, seed=a.seed, safety="krauss",
                          drive=a.drive, standstill_handoff_s=5.0)
    filter_lead: dict[str, tuple[str, float]] = {}  # ego -> (filter leader, heading difference [rad]) at the last step
    inner = ctrl.safety

    class RecordingFilter:  # the controller's safety filter, recording each ego's corridor leader
        def __getattr__(self, name):
            return getattr(inner, name)

        def leader_gap(self, ego, x, y, yaw, length, width, speed, kappa=None):
            gap, v_lead, lead = inner.leader_gap(ego, x, y, yaw, length, width, speed, kappa)
            ids = state_ids  # the rows of the states the controller passed (recorded by allowed_speeds below)
            filter_lead.clear()
            for e, j in zip(np.asarray(ego), lead, strict=True):
                if j >= 0 and e < len(ids) and j < len(ids):
                    d = float(np.angle(np.exp(1j * (yaw[j] - yaw[e]))))
                    filter_lead[ids[e]] = (ids[j], d)
            return gap, v_lead, lead

    ctrl.safety = RecordingFilter()
    state_ids: list[str] = []
    allowed_speeds = ctrl._allowed_speeds

    def recording_allowed_speeds(states, vids, slots):
        state_ids[:] = [str(v) for v in states.ids]
        return allowed_speeds(states, vids, slots)

    ctrl._allowed_speeds = recording_allowed_speeds
    filter_causes: Counter = Counter()  # (lane, filter cause) of standing controlled vehicles
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
                if rec is not None and rec.state == "controlled":
                    fl = filter_lead.get(vid)
                    sumo_lead = conn.vehicle.getLeader(vid, 50.0)
                    kind = ("none" if fl is None else "sumo-leader" if sumo_lead and sumo_lead[0] == fl[0]
                            else "crossing" if abs(fl[1]) > np.pi / 4 else "other")
                    filter_causes[(lane, kind)] += 1
                if cause != "leader":
                    heads[(lane, state, cause)] += 1
    finally:
        settle_remote_control(conn)  # libsumo keeps pending moveToXY past close (r1sim_sumo.sumo_launch)
        conn.close()
    total = sum(sum(c.values()) for c in stand.values())
    print(f"{a.network} {a.drive} {a.end:.0f} s seed {a.seed}: {total} standing vehicle-seconds; "
          f"arrived {ctrl.stats.arrived}, rule stops {dict(ctrl.stats.rule_stops)}")
    for lane, c in sorted(stand.items(), key=lambda kv: -sum(kv[1].values()))[: a.top]:
        parts = ", ".join(f"{s}/{cause} {n}" for (s, cause), n in c.most_common(5))
        print(f"  {lane:24s} {sum(c.values()):6d}  {parts}")
    print("standing policy-driven vehicles by the safety filter's corridor leader, vehicle-seconds:")
    for kind in ("sumo-leader", "crossing", "other", "none"):
        n = sum(v for (_, k), v in filter_causes.items() if k == kind)
        lanes = ", ".join([f"{ln} {v}" for (ln, k), v in filter_causes.most_common() if k == kind][:5])
        print(f"  filter:{kind:12s} {n:6d}  {lanes}")
    print("queue heads (standing with no leader within 10 m), vehicle-seconds:")
    for (lane, s, cause), n in heads.most_common(a.top):
        print(f"  {lane:24s} {s:28s} {cause:12s} {n}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
