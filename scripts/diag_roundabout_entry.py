#!/usr/bin/env python3
"""How fast vehicles approach and drive a roundabout when nothing is in their way: SUMO's drivers vs the drop-in.

    python scripts/diag_roundabout_entry.py [--network roundabout] [--scale 0.15]
        [--drive native|commands|position|shadow] [--checkpoint CKPT] [--sampler median:0.1] [--safety krauss|none] [--end 900] [--seed 0] [--all]
        [--drop-road-edges all | PART [PART ...]] [--junction-curbs]

Runs the network's ``.sumocfg`` (a bundled network or a training-only ring, ``training/ring_r19_three``) with its
demand scaled by ``--scale`` (SUMO ``--scale``; low demand = mostly free entries) under ``r1sim simulate``'s loop
(libsumo, the drop-in's defaults: Krauss cap (``--safety``), standstill hand-off 5 s) or SUMO alone (``native``),
and every 0.5 s samples each vehicle the policy drives (every vehicle in ``native``):

- on an approach lane (lane id containing ``_in_``) with no leader within 50 m (``--all``: every vehicle): its speed
  [m/s] (SUMO's ``getSpeed``) and the speed at the end of the policy's latest 0.5 s plan (its last 0.1 s step; the
  plan starts at the speed then, so end minus speed is the intended change), binned by the distance to the approach
  lane's end (the stop line at the ring) [m];
- inside the ring (lane id containing ``ring``) with no leader within 30 m: its speed and the policy's plan end.

In the ``commands`` drive it also prints, per bin, the speed the controller commanded for the 0.1 s step just
simulated (``setSpeed``) and how much SUMO held the vehicle below it (mean of max(0, commanded - speed) [m/s]; SUMO
caps a command by its own checks: safe gap, right of way at the junction, red lights): near zero means the vehicle
drives the policy's plan, so a slow approach is the policy's own.

The bins near the stop line say whether a vehicle rolls into a free ring as SUMO's drivers do or stops first.

``--drop-road-edges`` / ``--junction-curbs``: input ablations (``scripts/policy_map_ablation``, which also does them
for any ``r1sim`` run). The policy's map leaves out road-edge polylines (every one with ``all``, else
those whose SUMO id, ``<edge>#left`` / ``#right``, contains one of the given parts, e.g. ``_in#``), or gains road edges
along each junction's outline (its curbs, mouths left open); SUMO's network and the controller's lane bookkeeping are
unchanged. The model was trained with road edges, so this asks which input a
behaviour comes from, not how the policy should be run.

``--drive shadow``: SUMO's drivers drive every vehicle (the controller's speed, lane-change and placement commands
are dropped), while the controller still plans every vehicle every 0.5 s from SUMO's own motion. It separates what
the policy predicts from a native past from what a closed loop of its own decisions leads to.
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

BIN_M = 10.0  # [m] distance bins to the approach lane's end
MAX_BIN_M = 110.0  # [m] farther samples fall into the last bin
APPROACH_FREE_M = 50.0  # [m] no leader within this distance: a free approach
RING_FREE_M = 30.0  # [m] no leader within this distance: a free ring


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--network", default="roundabout", help="bundled network or training/<ring> (default roundabout)")
    ap.add_argument("--scale", type=float, default=0.15, help="demand factor (SUMO --scale; default 0.15)")
    ap.add_argument("--drive", default="commands", choices=("native", "commands", "position", "shadow"))
    ap.add_argument("--checkpoint", default=None, help="policy (default: the shipped r1sim-nano)")
    ap.add_argument("--sampler", default="median:0.1", help="token sampler (default median:0.1, the drop-in's since session 47; outputs of sessions 32-46 used greedy)")
    ap.add_argument("--end", type=float, default=900.0, help="simulated seconds (default 900)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--safety", default="krauss", choices=("krauss", "none"), help="the drop-in's safety layer (default krauss)")
    ap.add_argument("--all", action="store_true", help="approach samples of every vehicle, not only free ones")
    ap.add_argument("--junction-curbs", action="store_true",
                    help="add road edges around every junction to the policy's map (scripts/policy_map_ablation)")
    ap.add_argument("--drop-road-edges", nargs="+", default=None, metavar="PART",
                    help="leave road edges out of the policy's map: 'all', or those whose id contains a PART (e.g. _in#)")
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
    sys.path.insert(0, str(Path(__file__).resolve().parent / "policy_map_ablation"))
    from sitecustomize import add_junction_curbs_to_policy_map, drop_road_edges_from_policy_map

    if a.junction_curbs:
        add_junction_curbs_to_policy_map()
    if a.drop_road_edges:
        drop_road_edges_from_policy_map(a.drop_road_edges)
    cfg = network_files(a.network)["sumocfg"]
    conn.start(sumo_command(a.seed, sumocfg=cfg, end_s=a.end + 1.0, extra=("--scale", f"{a.scale:g}")))
    ctrl = None
    if a.drive != "native":
        policy = load_policy(a.checkpoint) if a.checkpoint else load_policy()
        ctrl = SumoController(conn, policy, control="all", sampler=a.sampler, seed=a.seed, safety=a.safety,
                              drive="commands" if a.drive == "shadow" else a.drive, standstill_handoff_s=5.0)
        if a.drive == "shadow":  # the policy plans, SUMO's drivers drive: drop every command that moves a vehicle
            for name in ("setSpeed", "slowDown", "changeLane", "changeSublane", "moveToXY", "setSpeedMode",
                         "setLaneChangeMode"):
                setattr(conn.vehicle, name, lambda *args, **kwargs: None)
    n_bins = int(MAX_BIN_M / BIN_M)
    speed: dict[int, list[float]] = defaultdict(list)
    plan_end: dict[int, list[float]] = defaultdict(list)  # [m/s] speed at the end of the latest plan
    ring: list[float] = []
    ring_plan_end: list[float] = []
    commanded: dict[int, list[float]] = defaultdict(list)  # [m/s] commanded speed of the step just simulated
    held: dict[int, list[float]] = defaultdict(list)  # [m/s] max(0, commanded - speed)
    last_cmd: dict[str, float] = {}  # vehicle -> speed commanded by the controller's latest step
    if a.drive == "commands":
        set_speed = conn.vehicle.setSpeed

        def record(vid, v):
            last_cmd[vid] = v
            return set_speed(vid, v)

        conn.vehicle.setSpeed = record
    arrived = 0
    try:
        for k in range(int(round(a.end / 0.1))):
            executed = dict(last_cmd)  # commanded by the previous controller step, driven by this simulation step
            last_cmd.clear()
            conn.simulationStep()
            arrived += conn.simulation.getArrivedNumber()
            if ctrl is not None:
                ctrl.step()
            if k % 5:
                continue
            for vid in conn.vehicle.getIDList():
                rec = ctrl.vehicles.get(vid) if ctrl is not None else None
                if ctrl is not None and (rec is None or rec.state != "controlled"):
                    continue  # only what the policy drives
                lane = conn.vehicle.getLaneID(vid)
                if "_in_" in lane:
                    lead = conn.vehicle.getLeader(vid, APPROACH_FREE_M)
                    if lead and lead[0] and lead[1] < APPROACH_FREE_M and not a.all:
                        continue
                    to_end = conn.lane.getLength(lane) - conn.vehicle.getLanePosition(vid)
                    b = min(int(to_end // BIN_M), n_bins - 1)
                    speed[b].append(conn.vehicle.getSpeed(vid))
                    if rec is not None:
                        plan_end[b].append(float(ctrl._plan_speed[rec.slot, -1]))
                    if executed.get(vid, -1.0) >= 0.0:  # -1: SUMO drives its speed
                        commanded[b].append(executed[vid])
                        held[b].append(max(0.0, executed[vid] - speed[b][-1]))
                elif "ring" in lane:
                    lead = conn.vehicle.getLeader(vid, RING_FREE_M)
                    if not (lead and lead[0] and lead[1] < RING_FREE_M):
                        ring.append(conn.vehicle.getSpeed(vid))
                        if rec is not None:
                            ring_plan_end.append(float(ctrl._plan_speed[rec.slot, -1]))
    finally:
        settle_remote_control(conn)  # libsumo keeps pending moveToXY past close (r1sim_sumo.sumo_launch)
        conn.close()
    who = "native" if ctrl is None else f"{a.drive} ({a.checkpoint or 'r1sim-nano'}, {a.sampler})"
    if a.drop_road_edges and ctrl is not None:
        who += f", policy map without road edges {' '.join(a.drop_road_edges)}"
    if a.junction_curbs and ctrl is not None:
        who += ", policy map with junction curbs"
    print(f"{a.network} x{a.scale:g} demand, {a.end:.0f} s, seed {a.seed}, {who}: arrived {arrived}")
    print(f"  approach lanes ({'every vehicle' if a.all else f'no leader within {APPROACH_FREE_M:.0f} m'}), "
          "by distance to the stop line:")
    cols = "   commanded [m/s]   held by SUMO [m/s]" if commanded else ""
    print("    distance [m]   samples   speed [m/s]   plan end [m/s]" + cols)
    for b in sorted(speed):
        end = f"{np.mean(plan_end[b]):10.2f}" if plan_end[b] else "       n/a"
        extra = (f"   {np.mean(commanded[b]):15.2f}   {np.mean(held[b]):18.2f}" if commanded.get(b) else
                 ("               n/a                  n/a" if commanded else ""))
        print(f"    {b * BIN_M:4.0f}-{(b + 1) * BIN_M:<4.0f}{'+' if b == n_bins - 1 else ' '}  {len(speed[b]):8d}   "
              f"{np.mean(speed[b]):10.2f}   {end}{extra}")
    print(f"  ring (no leader within {RING_FREE_M:.0f} m): {len(ring)} samples, speed "
          f"{np.mean(ring) if ring else float('nan'):.2f} m/s"
          + (f", plan end {np.mean(ring_plan_end):.2f} m/s" if ring_plan_end else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
