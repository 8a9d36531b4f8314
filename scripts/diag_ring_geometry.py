#!/usr/bin/env python3
"""Where SUMO puts a vehicle on a ring: front bumper vs box centre, and the speed ratio between them (session 48).

    python scripts/diag_ring_geometry.py [--network roundabout] [--scale 0.3] [--end 250]

SUMO's drivers drive (no policy). Every 1 s, for each vehicle on a ring lane (id containing ``ring``, not inside a
junction) whose whole length lies on that lane, it compares the distance from the ring's centre (a circle fitted to the
ring lanes' shapes) of the front bumper (SUMO's ``getPosition``) and of the box centre
(:func:`r1sim_sumo.adapters.sumo_state.read_vehicle_states`). By vehicle length it prints both radii, their ratio
(the speed ratio of bumper over centre) and ``R / sqrt(R^2 - L^2 / 4)`` (both bumpers on a circle of radius R).
"""

from __future__ import annotations

import argparse
import math

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--network", default="roundabout")
    ap.add_argument("--scale", type=float, default=0.3, help="demand factor (SUMO --scale)")
    ap.add_argument("--end", type=float, default=250.0, help="simulated seconds")
    a = ap.parse_args(argv)

    from r1sim_sumo._sumo_env import ensure_sumo_home

    ensure_sumo_home()
    import libsumo as conn

    from r1sim_sumo.adapters.sumo_state import read_vehicle_states
    from r1sim_sumo.resources import network_files
    from r1sim_sumo.sumo_launch import sumo_command

    conn.start(sumo_command(0, sumocfg=network_files(a.network)["sumocfg"], end_s=a.end + 1.0,
                            extra=("--scale", f"{a.scale:g}")))
    rows = []
    try:
        pts = np.array([p for lane in conn.lane.getIDList() if "ring" in lane and not lane.startswith(":")
                        for p in conn.lane.getShape(lane)])
        sol = np.linalg.lstsq(np.c_[2 * pts, np.ones(len(pts))], (pts ** 2).sum(1), rcond=None)[0]
        centre = sol[:2]
        print(f"{a.network}: ring lanes' radius {np.hypot(*(pts - centre).T).mean():.2f} m")
        for k in range(int(round(a.end / 0.1))):
            conn.simulationStep()
            if k % 10:
                continue
            for v in conn.vehicle.getIDList():
                lane = conn.vehicle.getLaneID(v)
                if "ring" not in lane or lane.startswith(":"):
                    continue
                if conn.vehicle.getLanePosition(v) < conn.vehicle.getLength(v) + 0.5:
                    continue  # its rear is still on the lane before
                st = read_vehicle_states(conn, [v])
                bumper = np.hypot(*(np.array(conn.vehicle.getPosition(v)) - centre))
                box = np.hypot(*(np.array([st.x_m[0], st.y_m[0]]) - centre))
                rows.append((float(st.length_m[0]), bumper, box))
    finally:
        conn.close()
    r = np.array(rows)
    for L in np.unique(r[:, 0]):
        m = r[:, 0] == L
        R = r[m, 1].mean()
        print(f"  length {L:.1f} m: {m.sum()} samples, bumper radius {R:.2f} m, box-centre radius {r[m, 2].mean():.2f} m, "
              f"ratio {np.mean(r[m, 1] / r[m, 2]):.4f} (both bumpers on the circle: {R / math.sqrt(R * R - L * L / 4):.4f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
