"""Start-up lag in the bundled roundabout's approach queues: for each vehicle standing behind a standing leader on an
``*_in`` arm, the time from its leader moving off (above 1 m/s) to its own moving off (above 1 m/s), by who drives
the follower (SUMO, the policy, or SUMO after a hand-back), native SUMO or the position drive with every default
(seed 0). Also the mean acceleration over the first 2 s after moving off.

    python docs/simulate/roundabout_s61/tools/queue_startup.py SECONDS native|policy"""
import sys
from collections import defaultdict

import numpy as np
from _roundabout import close, start_roundabout

native = sys.argv[2] == "native"
end_s = float(sys.argv[1])
conn, ctrl = start_roundabout(end_s, native)
GO = 1.0
waiting = {}  # follower -> (leader, time the leader moved off or None)
lags = defaultdict(list)
accel = defaultdict(list)
started = {}  # vid -> (t, speed at t, driver)
for _ in range(int(end_s * 10)):
    conn.simulationStep()
    if ctrl:
        ctrl.step()
    t = conn.simulation.getTime()
    for v in conn.vehicle.getIDList():
        lane = conn.vehicle.getLaneID(v)
        sp = conn.vehicle.getSpeed(v)
        if v in started and t - started[v][0] >= 2.0 - 1e-6:
            t0, s0, drv = started.pop(v)
            accel[drv].append((sp - s0) / (t - t0))
        if "_in_" not in lane:
            waiting.pop(v, None)
            continue
        drv = "sumo" if ctrl is None else ctrl.vehicles[v].state + ("/" + ctrl.vehicles[v].reason if ctrl.vehicles[v].state == "handed_back" else "") if v in ctrl.vehicles else "sumo"
        if sp < 0.3:
            lead = conn.vehicle.getLeader(v, 30.0)
            if lead and lead[0] and v not in waiting and conn.vehicle.getSpeed(lead[0]) < 0.3:
                waiting[v] = [lead[0], None]
        w = waiting.get(v)
        if w is None:
            continue
        if w[1] is None:
            try:
                if conn.vehicle.getSpeed(w[0]) > GO:
                    w[1] = t
            except Exception:
                w[1] = t
        if sp > GO:
            if w[1] is not None:
                lags[drv].append(t - w[1])
                started[v] = (t, sp, drv)
            del waiting[v]
close(conn)
print(f"roundabout {'native' if native else 'position'} {end_s:.0f} s seed 0: start-up lag behind a leader moving off (> {GO} m/s)")
for d, x in sorted(lags.items()):
    x = np.asarray(x)
    a = np.asarray(accel[d]) if accel[d] else np.zeros(1)
    print(f"  {d:26s} n={len(x):5d}  lag mean {x.mean():4.2f} s  median {np.median(x):4.2f} s  p90 {np.quantile(x, 0.9):4.2f} s"
          f"   mean accel over 2 s after {a.mean():4.2f} m/s^2")
