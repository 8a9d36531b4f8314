"""Where the bundled roundabout's vehicles spend their time: vehicle-seconds and mean speed per lane group (``in`` arms
and their first / last 30 m, the ``ring``, junction lanes, ``out`` arms), every vehicle, native SUMO or the position drive
with every default (seed 0, sampled every 0.1 s).

    python docs/simulate/roundabout_s61/tools/lane_group_times.py SECONDS native|policy"""
import sys
from collections import defaultdict

import libsumo as conn
import torch

from r1sim_sumo._sumo_env import ensure_sumo_home
from r1sim_sumo.model.checkpoint import load_policy
from r1sim_sumo.resources import network_files
from r1sim_sumo.sim.sumo_controller import SumoController
from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command

torch.set_num_threads(1)
ensure_sumo_home()
native = sys.argv[2] == "native"
end_s = float(sys.argv[1])
conn.start(sumo_command(0, sumocfg=network_files("roundabout")["sumocfg"], end_s=end_s + 1))
ctrl = None if native else SumoController(conn, load_policy(None), control="all", seed=0, safety="krauss", drive="position")
steps, speed = defaultdict(int), defaultdict(float)
for _ in range(int(end_s * 10)):
    conn.simulationStep()
    if ctrl:
        ctrl.step()
    for v in conn.vehicle.getIDList():
        lane = conn.vehicle.getLaneID(v)
        if lane.startswith(":"):
            g = "junction"
        elif "_in_" in lane:
            left = conn.lane.getLength(lane) - conn.vehicle.getLanePosition(v)
            g = "in: last 30 m" if left <= 30 else "in: before"
        elif lane.startswith("ring"):
            g = "ring"
        else:
            g = "out"
        steps[g] += 1
        speed[g] += conn.vehicle.getSpeed(v)
arrived = conn.simulation.getArrivedNumber()
settle_remote_control(conn)
conn.close()
print(f"roundabout {'native' if native else 'position'} {end_s:.0f} s seed 0")
for g in sorted(steps):
    print(f"  {g:14s} {steps[g] / 10:9.0f} vehicle-s   mean speed {speed[g] / steps[g]:5.2f} m/s")
