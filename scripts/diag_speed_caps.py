#!/usr/bin/env python3
"""Why SUMO drives a commands-mode vehicle slower than the policy asked: its acceleration limit or a short headway.

    python scripts/diag_speed_caps.py CHECKPOINT NETWORK SECONDS        # e.g. r1sim-nano lane_drop 200

``--control all``, ``--drive commands``, top-5, seed 0. Every controlled vehicle-step's commanded speed is paired with
the speed SUMO reached one step later; a step is capped when SUMO drove more than 0.2 m/s slower. Prints the capped
share and why (commanded beyond the type's acceleration, headway under 1 s, no leader within 100 m), and the commanded
vs realised acceleration [m/s^2] on a free road and when following, by speed band. (Session 11: the same computation
as a scratch script, session-10 nano, at commit d964da4 before plans were retimed: 95% of the caps on lane_drop were
at the acceleration limit and a free-road vehicle commanded +3.5 m/s^2 at 0-10 m/s but realised +0.3.)
"""
import sys

import libsumo
import numpy as np
import torch

from r1sim_sumo.model.checkpoint import load_policy
from r1sim_sumo.resources import network_files
from r1sim_sumo.sim.sumo_controller import SumoController
from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command

torch.set_num_threads(1)
ckpt, net, end = sys.argv[1], sys.argv[2], float(sys.argv[3])
libsumo.start(sumo_command(0, sumocfg=network_files(net)["sumocfg"], end_s=end + 1))
ctrl = SumoController(libsumo, load_policy(ckpt), control="all", sampler="topk:5", seed=0, drive="commands")
rows = []
t = 0.0
while t < end:
    libsumo.simulationStep()
    t += 0.1
    ctrl.step()
    snap = []
    for vid, rec in ctrl.vehicles.items():
        if rec.state != "controlled":
            continue
        cmd = float(ctrl._cmd_speed[rec.slot])
        if not np.isfinite(cmd):
            continue
        v = libsumo.vehicle.getSpeed(vid)
        lead = libsumo.vehicle.getLeader(vid, 200.0)
        gap, vl = (lead[1], libsumo.vehicle.getSpeed(lead[0])) if lead and lead[0] else (np.inf, np.nan)
        snap.append([vid, v, cmd, gap, vl, libsumo.vehicle.getAllowedSpeed(vid), libsumo.vehicle.getAccel(vid)])
    rows.append(snap)
settle_remote_control(libsumo)  # libsumo keeps pending moveToXY past close (r1sim_sumo.sumo_launch)
libsumo.close()
# pair each step's commands with the speed reached at the next step
out = []
for k in range(len(rows) - 1):
    nxt = {r[0]: r[1] for r in rows[k + 1]}
    for vid, v, cmd, gap, vl, allowed, acc in rows[k]:
        if vid in nxt:
            out.append((v, cmd, nxt[vid], gap, vl, allowed, acc, k * 0.1))
o = np.array(out)
v, cmd, vn, gap, vl, allowed, acc, tt = o.T
capped = vn < cmd - 0.2
acc_lim = cmd > v + acc * 0.1 + 0.05
hw = gap / np.maximum(v, 0.1)
print(f"{net} {ckpt}: vehicle-steps {len(o)}, capped {capped.mean():.3f}; of capped: beyond accel limit {np.mean(acc_lim[capped]):.3f}, "
      f"headway<1.0s {np.mean(hw[capped] < 1.0):.3f}, gap>100m or no leader {np.mean(gap[capped] > 100):.3f}")
free = gap > 100
print(f"free road (no leader within 100 m): steps {free.sum()}, mean speed {v[free].mean():.1f}, mean allowed {allowed[free].mean():.1f}, "
      f"commanded accel mean {np.mean((cmd[free]-v[free])/0.1):.2f} m/s^2, share commanding > 0.5 m/s^2 {np.mean((cmd[free]-v[free])/0.1 > 0.5):.2f}")
for lo, hi in ((0, 10), (10, 20), (20, 40)):
    m = free & (v >= lo) & (v < hi)
    if m.any():
        print(f"  free, {lo}-{hi} m/s: steps {m.sum()}, commanded accel {np.mean((cmd[m]-v[m])/0.1):.2f}, realised {np.mean((vn[m]-v[m])/0.1):.2f} m/s^2")
fol = (gap < 100)
print(f"following: steps {fol.sum()}, headway median {np.median(hw[fol]):.2f} s, share < 1 s {np.mean(hw[fol] < 1):.2f}, speed {v[fol].mean():.1f}, leader speed {np.nanmean(vl[fol]):.1f}")
for lo, hi in ((0, 10), (10, 20), (20, 40)):
    m = fol & (v >= lo) & (v < hi)
    if m.any():
        print(f"  following, {lo}-{hi} m/s: steps {m.sum()}, headway median {np.median(hw[m]):.2f} s, commanded accel {np.mean((cmd[m]-v[m])/0.1):.2f}, realised {np.mean((vn[m]-v[m])/0.1):.2f}, leader faster by {np.nanmean(vl[m]-v[m]):.2f}")
