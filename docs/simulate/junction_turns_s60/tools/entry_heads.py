"""Who waits at the bundled roundabout's yield lines: every second, each arm's head vehicle within 5 m of its yield line,
by driver (SUMO, policy, handed back and why) and whether it stands; for the standing ones, whether SUMO reports a foe
approaching its link and the link open (seed 0).

    python docs/simulate/junction_turns_s60/tools/entry_heads.py SECONDS native|policy"""
import sys
from collections import Counter

import libsumo as conn
import torch

from r1sim_sumo._sumo_env import ensure_sumo_home
from r1sim_sumo.model.checkpoint import load_policy
from r1sim_sumo.resources import network_files
from r1sim_sumo.sim.sumo_controller import SumoController
from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command

torch.set_num_threads(1); ensure_sumo_home()
native = sys.argv[2] == "native"
conn.start(sumo_command(0, sumocfg=network_files("roundabout")["sumocfg"], end_s=float(sys.argv[1]) + 1))
ctrl = None if native else SumoController(conn, load_policy(None), control="all", seed=0, safety="krauss", drive="position", standstill_handoff_s=5.0)
heads = Counter(); foes = Counter(); nsec = 0
for k in range(int(float(sys.argv[1]) * 10)):
    conn.simulationStep()
    if ctrl: ctrl.step()
    if k % 10: continue
    for arm in ("east", "north", "west", "south"):
        lane = f"{arm}_in_0"; L = conn.lane.getLength(lane)
        ids = conn.lane.getLastStepVehicleIDs(lane)
        if not ids: continue
        h = max(ids, key=lambda v: conn.vehicle.getLanePosition(v))
        if L - conn.vehicle.getLanePosition(h) > 5.0: continue
        nsec += 1
        st = "sumo" if ctrl is None else (ctrl.vehicles[h].state + ("/" + ctrl.vehicles[h].reason if ctrl.vehicles[h].state == "handed_back" else ""))
        standing = conn.vehicle.getSpeed(h) < 0.3
        links = conn.vehicle.getNextLinks(h)
        lk = links[0] if links else None
        heads[(st, "standing" if standing else "moving")] += 1
        if standing and lk:
            foes[(st, "foe" if lk[3] else "-", "open" if lk[2] else "closed")] += 1
settle_remote_control(conn); conn.close()
print("arm-seconds with a head within 5 m of the yield line:", nsec)
for k, v in heads.most_common(): print("  ", k, v)
print("standing heads: (driver, foe approaching, link open)")
for k, v in foes.most_common(): print("  ", k, v)
