"""Trace the first exits from the bundled roundabout's ring under the position drive (seed 0, every default), every 0.1 s:
SUMO's lane, front bumper, angle, the controller's box centre and heading, SUMO's speed, the speed moved at, the plan's
curvature [1/m] (+ = left) and whether the junction snap holds it.

    python docs/simulate/junction_turns_s60/tools/trace_exit.py SECONDS N_EXITS [sumo|policy]

``policy``: ``junction_turns="policy"`` (the controller before session 60). Add ``R1SIM_EXP=route_path_exits`` with this
folder first on PYTHONPATH for that experiment (see sitecustomize.py)."""
import sys
from collections import defaultdict

import libsumo as conn
import numpy as np
import torch

from r1sim_sumo._sumo_env import ensure_sumo_home
from r1sim_sumo.model.checkpoint import load_policy
from r1sim_sumo.resources import network_files
from r1sim_sumo.sim.sumo_controller import N_HISTORY_10HZ, SumoController
from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command

torch.set_num_threads(1); ensure_sumo_home()
conn.start(sumo_command(0, sumocfg=network_files("roundabout")["sumocfg"], end_s=200))
ctrl = SumoController(conn, load_policy(None), control="all", sampler="median:0.1", seed=0, safety="krauss", drive="position", standstill_handoff_s=5.0,
                      junction_turns=sys.argv[3] if len(sys.argv) > 3 else "sumo")
log = defaultdict(list); exits = []
for k in range(int(sys.argv[1])*10):
    conn.simulationStep(); ctrl.step()
    t = conn.simulation.getTime()
    for v in conn.vehicle.getIDList():
        r = ctrl.vehicles.get(v)
        if r is None: continue
        lane = conn.vehicle.getLaneID(v); sl = r.slot
        col = ctrl._k % N_HISTORY_10HZ
        h = ctrl._hist[sl, col]
        log[v].append(f"{t:.1f} {r.state[:4]} lane={lane or conn.vehicle.getRoadID(v)+'(road)'} front={np.round(conn.vehicle.getPosition(v),1)} ang={conn.vehicle.getAngle(v):.0f} centre=({h[0]:.1f},{h[1]:.1f}) yaw={np.degrees(h[2]):.0f} v={conn.vehicle.getSpeed(v):.1f} moved={ctrl._moved_speed[sl]:.1f} kappa={ctrl.follower.kappa[sl]:.3f} snap={int(r.snap_in_junction)}")
        if lane.startswith(":ring") and v not in exits and r.state == "controlled":
            ro, i = conn.vehicle.getRoute(v), conn.vehicle.getRouteIndex(v)
            if i + 1 < len(ro) and ro[i + 1].endswith("_out"): exits.append(v)
settle_remote_control(conn); conn.close()
for v in exits[: int(sys.argv[2])]:
    print("=====", v)
    # the 2.5 s before its first step on the exit arm and 0.8 s after
    idx = [j for j, s in enumerate(log[v]) if "_out" in s.split()[2]]
    first_out = idx[0] if idx else len(log[v])
    for s in log[v][max(0, first_out - 25): first_out + 8]: print(s)
