#!/usr/bin/env python3
"""Session 59: one position-drive car on the roundabout ring at 15% demand, every 0.1 s: SUMO's speed reading, its
displacement, the history's speed, the plan's speed, the safety layer's allowed speed and the speed it was moved at.

    python docs/simulate/moved_speed_s59/tools/trace_ring_vehicle.py
"""
import sys, numpy as np, torch, libsumo as conn
from r1sim_sumo._sumo_env import ensure_sumo_home
from r1sim_sumo.model.checkpoint import load_policy
from r1sim_sumo.resources import network_files
from r1sim_sumo.sim.sumo_controller import SumoController
from r1sim_sumo.sim import sumo_controller as sc
from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command
torch.set_num_threads(1); ensure_sumo_home()
conn.start(sumo_command(0, sumocfg=network_files("roundabout")["sumocfg"], end_s=200, extra=("--scale", "0.15")))
ctrl = SumoController(conn, load_policy(), control="all", sampler="median:0.1", seed=0, drive="position", standstill_handoff_s=5.0)
follow = ctrl._follow
watch = None; lines = []
def rec_follow(slots, v_allowed, *rest):
    global watch
    out = follow(slots, v_allowed, *rest)
    vid_of = {r.slot: v for v, r in ctrl.vehicles.items() if r.state == "controlled"}
    for i, s in enumerate(slots.tolist()):
        vid = vid_of.get(s)
        if vid is None: continue
        lane = conn.vehicle.getLaneID(vid)
        if watch is None and "ring" in lane and conn.vehicle.getSpeed(vid) > 3: watch = vid
        if vid == watch:
            col = ctrl._k % sc.N_HISTORY_10HZ; prev = (col - 1) % sc.N_HISTORY_10HZ
            moved = np.hypot(*(ctrl._hist[s, col, :2] - ctrl._hist[s, prev, :2])) / 0.1
            lines.append(f"k={ctrl._k} lane={lane:14s} getSpeed={conn.vehicle.getSpeed(vid):5.2f} disp={moved:5.2f} histspeed={ctrl._hist[s, col, 3]:5.2f} plan={out.v_plan[i]:5.2f} allowed={(v_allowed[i] if v_allowed is not None else np.inf):5.2f} out={out.speed[i]:5.2f} clock={ctrl.follower.clock_s[s]:.1f} planstep={ctrl.vehicles[vid].plan_step}")
    return out
ctrl._follow = rec_follow
try:
    for k in range(1900):
        conn.simulationStep(); ctrl.step()
        if len(lines) > 80: break
finally:
    settle_remote_control(conn); conn.close()
print("\n".join(lines))
