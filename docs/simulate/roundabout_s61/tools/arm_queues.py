"""The bundled roundabout's arms and ring every 20 s from 400 s on, position drive with every default (or native SUMO,
``native`` last): vehicles waiting
to be inserted, the ring's vehicles (count, mean speed, standing, who drives them) and per arm (``e n w s``) the vehicles
on its ``*_in`` lane / how many stand, and who drives the head (``cont`` = the policy, ``hand/stand`` = SUMO after the
standstill hand-off).

    python docs/simulate/roundabout_s61/tools/arm_queues.py SEED SECONDS [native]"""
import sys
from collections import Counter

from _roundabout import close, start_roundabout

seed, end_s = int(sys.argv[1]), float(sys.argv[2])
native = sys.argv[3:] == ["native"]
conn, ctrl = start_roundabout(end_s, native=native, seed=seed)
for _ in range(int(end_s * 10)):
    conn.simulationStep()
    if ctrl:
        ctrl.step()
    t = conn.simulation.getTime()
    if t < 400 or abs(t % 20) > 1e-6:
        continue
    arms = []
    for arm in ("east", "north", "west", "south"):
        ids = conn.lane.getLastStepVehicleIDs(f"{arm}_in_0")
        standing = sum(conn.vehicle.getSpeed(v) < 0.3 for v in ids)
        head = max(ids, key=conn.vehicle.getLanePosition) if ids else None
        if head is None:
            who = "-"
        elif ctrl is None:
            who = "sumo"
        else:
            rec = ctrl.vehicles[head]
            who = rec.state[:4] + ("/" + rec.reason[:5] if rec.state == "handed_back" else "")
        arms.append(f"{arm[0]}:{len(ids)}/{standing} {who}")
    ring = [v for v in conn.vehicle.getIDList() if conn.vehicle.getRoadID(v).startswith(("ring", ":ring"))]
    speeds = [conn.vehicle.getSpeed(v) for v in ring]
    drivers = dict(Counter("sumo" if ctrl is None else ctrl.vehicles[v].state[:4] for v in ring))
    print(f"t={t:5.0f} waiting to insert {len(conn.simulation.getPendingVehicles()):3d}  ring n={len(ring)} mean "
          f"{sum(speeds) / max(len(speeds), 1):4.1f} m/s standing {sum(s < 0.3 for s in speeds)} {drivers} | "
          + "  ".join(arms), flush=True)
close(conn)
