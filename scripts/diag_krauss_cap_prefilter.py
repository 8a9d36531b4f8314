#!/usr/bin/env python3
"""Could the commands drive's Krauss cap skip SUMO's ``getLeader`` for vehicles nobody is near enough to cap?

``SumoController._krauss_caps`` asks SUMO for each controlled vehicle's leader every 0.1 s step (4.1 us per call
under cProfile at 700 vehicles, `python benchmarks/profile_sumo_decision.py --vehicles 700 --scene grid --threads 1
--drive commands --profile`). A leader's gap along the route is at least the straight-line distance between the boxes, and the Krauss
safe speed ``v_l + (g - v_l tau) / ((v + v_l) / (2b) + tau)`` is at least ``2 sqrt(2b (g + tau v + 2 b tau^2)) - v -
4 b tau`` for any leader speed, so a vehicle whose nearest other vehicle is farther than the gap that bound needs
(plus half its own and half the longest length and 3 m of minimum gap) cannot be capped and needs no query. This
measures how many vehicles that would skip on the 700-vehicle city grid of ``benchmarks/bench_sumo_controller.py``
(SUMO's own drivers, no policy; 10 samples between 10 and 30 simulated s; command speed = speed + 0.3 m/s).

    python scripts/diag_krauss_cap_prefilter.py

Session 38 (AMD EPYC): 700 vehicles; 3.2% skippable; median nearest other vehicle 5.4 m, median distance a skip
needs 8.4 m. Not built: it would save ~3% of the ``getLeader`` calls.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

TAU_S, DECEL_MPS2, MIN_GAP_M, CMD_UP_MPS = 1.0, 4.5, 3.0, 0.3  # the filter's defaults; a margin over SUMO's minGap


def skippable(x_m, y_m, speed_mps, length_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per vehicle: no other vehicle near enough to cap it (bool), its nearest other vehicle [m] and the distance a
    skip needs [m] (box centres, metres; speeds m/s)."""
    from scipy.spatial import cKDTree

    xy = np.stack([x_m, y_m], 1)
    nearest = cKDTree(xy).query(xy, k=2)[0][:, 1]
    v, b, tau = np.asarray(speed_mps, np.float64), DECEL_MPS2, TAU_S
    v_cmd = v + CMD_UP_MPS
    gap = ((v_cmd + v + 4 * b * tau) / 2) ** 2 / (2 * b) - tau * v - 2 * b * tau**2  # bound >= v_cmd from this gap on
    need = np.maximum(gap, 0.0) + length_m / 2 + length_m.max() / 2 + MIN_GAP_M
    return nearest > need, nearest, need


def main() -> int:
    import bench_sumo_controller as scene

    from r1sim_sumo.adapters.sumo_state import read_vehicle_states

    rows = []
    with tempfile.TemporaryDirectory() as d:
        conn, refill = scene.start_scene("grid", 700, Path(d))
        for k in range(300):  # 0.1 s steps
            conn.simulationStep()
            refill.refill()
            if k >= 100 and k % 20 == 0:
                st = read_vehicle_states(conn)
                skip, nearest, need = skippable(st.x_m, st.y_m, st.speed_mps, st.length_m)
                rows.append((skip.mean(), np.median(nearest), np.median(need), len(skip)))
    r = np.array(rows)
    print(f"vehicles {r[:, 3].mean():.0f}; share skippable {r[:, 0].mean():.3f}; median nearest other vehicle "
          f"{r[:, 1].mean():.1f} m; median distance a skip needs {r[:, 2].mean():.1f} m")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
