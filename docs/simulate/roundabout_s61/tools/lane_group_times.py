"""Where the bundled roundabout's vehicles spend their time: vehicle-seconds and mean speed per lane group (``in`` arms
and their first / last 30 m, the ``ring``, junction lanes, ``out`` arms), every vehicle, native SUMO or the position drive
with every default (seed 0, sampled every 0.1 s).

    python docs/simulate/roundabout_s61/tools/lane_group_times.py SECONDS native|policy"""
import sys
from collections import defaultdict

from _roundabout import close, start_roundabout

native = sys.argv[2] == "native"
end_s = float(sys.argv[1])
conn, ctrl = start_roundabout(end_s, native)
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
close(conn)
print(f"roundabout {'native' if native else 'position'} {end_s:.0f} s seed 0")
for g in sorted(steps):
    print(f"  {g:14s} {steps[g] / 10:9.0f} vehicle-s   mean speed {speed[g] / steps[g]:5.2f} m/s")
