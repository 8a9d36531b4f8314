"""Who stands where, second by second: the position drive of the shipped policy (every default) on a bundled network,
and from T0 to T1 [s] the first six vehicles of each named lane (front first) as ``id@position:speed:driver``
(``cont`` = the policy, ``hand/<reason>`` = SUMO after a hand-back), with the signal state ahead of the lane's first.

    python docs/simulate/wrong_lane_s62/tools/lane_trace.py NETWORK SEED T0 T1 LANE[,LANE...]

e.g. ``urban_grid 0 585 660 J21_J20_0,J21_J20_1,J22_J21_0`` (the queue of session 62's README)."""
import sys

import libsumo as conn
import torch

from r1sim_sumo._sumo_env import ensure_sumo_home
from r1sim_sumo.model.checkpoint import load_policy
from r1sim_sumo.resources import network_files
from r1sim_sumo.sim.sumo_controller import SumoController
from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command

torch.set_num_threads(1)
ensure_sumo_home()
net, seed, t0, t1 = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4])
lanes = sys.argv[5].split(",")
conn.start(sumo_command(seed, sumocfg=network_files(net)["sumocfg"], end_s=t1 + 1))
ctrl = SumoController(conn, load_policy(None), control="all", seed=seed, safety="krauss", drive="position")
for _ in range(int(t1 * 10)):
    conn.simulationStep()
    ctrl.step()
    t = conn.simulation.getTime()
    if t < t0 or abs(t % 1) > 1e-6:
        continue
    out = []
    for ln in lanes:
        ids = sorted(conn.lane.getLastStepVehicleIDs(ln), key=conn.vehicle.getLanePosition, reverse=True)
        cells = []
        for v in ids[:6]:
            r = ctrl.vehicles.get(v)
            who = "?" if r is None else (r.state[:4] + ("/" + r.reason[:6] if r.state == "handed_back" else ""))
            cells.append(f"{v}@{conn.vehicle.getLanePosition(v):.0f}:{conn.vehicle.getSpeed(v):.1f}:{who}")
        nxt = conn.vehicle.getNextTLS(ids[0]) if ids else ()
        out.append(f"{ln}[{len(ids)} {nxt[0][3] if nxt else ''}] " + " ".join(cells))
    print(f"t={t:.0f} " + " | ".join(out), flush=True)
settle_remote_control(conn)
conn.close()
