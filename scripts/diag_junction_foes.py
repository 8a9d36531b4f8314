#!/usr/bin/env python3
"""Does SUMO's junction model see policy-placed (moveToXY) vehicles as foes? Position drive, control=fraction=0.5:
every 1 s, for every SUMO-driven vehicle, vehicle.getJunctionFoes(vid, 60) lists the foes approaching its next
junction; count how often a controlled vs a SUMO-driven vehicle appears, against how many of each are on the
network's incoming lanes within 60 m of a junction.

    python scripts/diag_junction_foes.py [NETWORK] [END_S]     # default urban_intersection 200
"""
import sys
from collections import Counter

# isort: off
import r1sim_sumo  # noqa: F401 - first: it sets the OpenMP wait policy before torch loads, as `r1sim simulate`
import libsumo as conn
import torch
# isort: on

from r1sim_sumo._sumo_env import ensure_sumo_home
from r1sim_sumo.model.checkpoint import load_policy
from r1sim_sumo.resources import network_files
from r1sim_sumo.sim.sumo_controller import SumoController
from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command

torch.set_num_threads(1)
net = sys.argv[1] if len(sys.argv) > 1 else "urban_intersection"
end = float(sys.argv[2]) if len(sys.argv) > 2 else 200.0
ensure_sumo_home()
conn.start(sumo_command(0, sumocfg=network_files(net)["sumocfg"], end_s=end + 1.0))
ctrl = SumoController(conn, load_policy(), control="fraction=0.5", sampler="greedy", seed=0, safety="krauss", drive="position")
foes: Counter = Counter()
near: Counter = Counter()
for k in range(int(end * 10)):
    conn.simulationStep()
    ctrl.step()
    if k % 10 or k < 200:
        continue
    ids = conn.vehicle.getIDList()
    who = {v: ("controlled" if (r := ctrl.vehicles.get(v)) is not None and r.state == "controlled" else "sumo") for v in ids}
    for v in ids:
        lane = conn.vehicle.getLaneID(v)
        if lane and not lane.startswith(":"):
            left = conn.lane.getLength(lane) - conn.vehicle.getLanePosition(v)
            if left < 60:
                near[who[v]] += 1
    for v in ids:
        if who[v] != "sumo":
            continue
        for f in conn.vehicle.getJunctionFoes(v, 60.0):
            fid = f[0] if isinstance(f, tuple) else getattr(f, "foeId", None)
            if fid in who:
                foes[who[fid]] += 1
settle_remote_control(conn)  # libsumo keeps pending moveToXY past close (r1sim_sumo.sumo_launch)
conn.close()
print(net, "vehicle-samples within 60 m of a junction:", dict(near))
print(net, "appearances as junction foes of SUMO-driven vehicles:", dict(foes))
for g in near:
    print(f"  {g}: {foes[g] / max(near[g], 1):.3f} foe appearances per near-junction vehicle-sample")
