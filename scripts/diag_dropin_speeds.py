"""Where the drop-in's traffic slows down: mean speed [m/s] (and vehicle count) by position along x every 10 s of a
``--control all`` run of a bundled network, optionally with every vehicle's desired speed forced (issue 19, session 9).

    python scripts/diag_dropin_speeds.py CHECKPOINT lane_drop 120             # SUMO's desired speeds
    python scripts/diag_dropin_speeds.py CHECKPOINT lane_drop 80 nan          # no desired speed given
    python scripts/diag_dropin_speeds.py CHECKPOINT lane_drop 80 40           # 40 m/s for every vehicle

Positions are SUMO's x of the front bumper [m] (the bundled motorways run along x); ``--drive commands``, top-5, seed 0.
"""

import sys

import libsumo
import numpy as np
import torch

from r1sim_sumo.model.checkpoint import load_policy
from r1sim_sumo.resources import network_files
from r1sim_sumo.sim.sumo_controller import SumoController
from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command

BINS_M = ((0, 300), (300, 700), (700, 1100), (1100, 1600))


def main(ckpt: str, network: str, end_s: float, desired: str = "sumo") -> None:
    torch.set_num_threads(1)
    libsumo.start(sumo_command(0, sumocfg=network_files(network)["sumocfg"], end_s=end_s + 1))
    ctrl = SumoController(libsumo, load_policy(ckpt), control="all", sampler="topk:5", seed=0, drive="commands")
    if desired != "sumo":
        ctrl._desired_speeds = lambda ids: np.full(len(ids), float(desired), np.float32)  # noqa: SLF001
    try:
        for k in range(int(end_s * 10)):
            libsumo.simulationStep()
            ctrl.step()
            if k % 100 != 99:
                continue
            ids = libsumo.vehicle.getIDList()
            x = np.array([libsumo.vehicle.getPosition(v)[0] for v in ids])
            v = np.array([libsumo.vehicle.getSpeed(v) for v in ids])
            cells = []
            for a, b in BINS_M:
                m = (x >= a) & (x < b)
                cells.append(f"{a}-{b} m: {v[m].mean():5.1f} ({m.sum():2d})" if m.any() else f"{a}-{b} m:   -  ")
            print(f"t={(k + 1) / 10:5.0f} s  vehicles {len(ids):3d}  " + "  ".join(cells), flush=True)
    finally:
        settle_remote_control(libsumo)  # libsumo keeps pending moveToXY past close (r1sim_sumo.sumo_launch)
        libsumo.close()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], float(sys.argv[3]), *(sys.argv[4:5]))
