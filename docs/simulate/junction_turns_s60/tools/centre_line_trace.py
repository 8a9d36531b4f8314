"""The centre-line check of ``tests/test_sumo_controller.py::test_position_drive_keeps_plans_off_the_other_direction``,
measured both ways: controlled vehicle-steps on the leftmost lane of urban_intersection's normal edges under a plan
drifting left at 1 m/s (60 s, untrained stand-in policy, :class:`FastStraightDriver` of the tests), and of them those
more than 10 cm over the lane's left edge by SUMO's lateral position (the front bumper's) and by the box centre's
(less ``(L / 2) sin d``, d the yaw against the lane), with the vehicles over by the front-bumper measure.

    python docs/simulate/junction_turns_s60/tools/centre_line_trace.py [sumo|policy]
"""
import sys
from collections import Counter

import libsumo
import numpy as np

sys.path.insert(0, "tests")
import test_sumo_controller as T  # noqa: E402

from r1sim_sumo.model.untrained import untrained_policy  # noqa: E402
from r1sim_sumo.sim.sumo_controller import SumoController  # noqa: E402

turns = sys.argv[1] if len(sys.argv) > 1 else "sumo"
libsumo.start(T._cmd("urban_intersection", end="60"))
ctrl = SumoController(libsumo, untrained_policy(0), drive="position", offroad_margin_m=1e6, standstill_handoff_s=None,
                      junction_turns=turns)
drv = T.FastStraightDriver()
drv.speed, drv.drift_mps = 8.0, 1.0
ctrl.driver = drv
on_left = over_front = over_centre = 0
who = Counter()
for _ in range(400):
    libsumo.simulationStep()
    ctrl.step()
    for v in ctrl.controlled_ids():
        lane = libsumo.vehicle.getLaneID(v)
        if not lane or lane.startswith(":"):
            continue
        edge, idx = lane.rsplit("_", 1)
        if int(idx) != libsumo.edge.getLaneNumber(edge) - 1:
            continue
        on_left += 1
        half, w = 0.5 * libsumo.lane.getWidth(lane) + 0.1, 0.5 * libsumo.vehicle.getWidth(v)
        front = libsumo.vehicle.getLateralLanePosition(v)
        d = np.radians(libsumo.lane.getAngle(lane, libsumo.vehicle.getLanePosition(v)) - libsumo.vehicle.getAngle(v))
        centre = front - 0.5 * libsumo.vehicle.getLength(v) * np.sin(d)
        if front + w > half:
            over_front += 1
            who[(v, lane)] += 1
        over_centre += centre + w > half
T._close(libsumo)
print(f"junction_turns={turns}: {on_left} steps on a leftmost lane; over by the front bumper {over_front}, by the box "
      f"centre {over_centre}; hand-backs {dict(ctrl.stats.handbacks)}; most over (front): {who.most_common(4)}")
