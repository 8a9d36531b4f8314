"""Session 54: where vehicles stand in the position drive on motorway_merge (seed 0, first 300 s): standing samples (speed < 1 m/s,
every 1 s) counted by lane, 20 m bin and driver. Run: python docs/simulate/position_coop_s54/standing_trace.py"""
import sys; from pathlib import Path; sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "scripts"))
from collections import Counter
from diag_following_headway import start_run
libsumo, ctrl = start_run("motorway_merge", "position", 300, 0, None)
c = Counter(); first = []
try:
    for k in range(3000):
        libsumo.simulationStep(); ctrl.step()
        if k % 10 == 0:
            for v in libsumo.vehicle.getIDList():
                if libsumo.vehicle.getSpeed(v) < 1.0:
                    ln = libsumo.vehicle.getLaneID(v); pos = libsumo.vehicle.getLanePosition(v)
                    rec = ctrl.vehicles.get(v)
                    c[(ln, int(pos // 20) * 20, rec.state if rec else "?")] += 1
                    if len(first) < 15: first.append((k / 10, v, ln, round(pos, 1), rec.state if rec else "?"))
finally:
    ctrl.close()
print("first standing samples:", *first, sep="\n  ")
for key, n in c.most_common(25): print(key, n)
print(ctrl.stats.rule_stops, ctrl.stats.handbacks)
