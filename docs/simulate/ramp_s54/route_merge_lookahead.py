"""Session 54 experiment: game/ramp, commands drive, SUMO driving the speed of a vehicle on a lane that does not continue
its route (the on-ramp's acceleration lane) from farther ahead of the lane's end.

The controller hands such a vehicle's speed to SUMO within max(WRONG_LANE_AHEAD_M, speed x WRONG_LANE_AHEAD_S) of the
lane's end (40 m, 4 s). This script sets the two constants and runs the scenario's 400 s:

    python docs/simulate/ramp_s54/route_merge_lookahead.py SEED AHEAD_S AHEAD_M

Prints arrivals, vehicles still waiting to insert at the end and the decisions SUMO drove the speed (route merge).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "scripts"))
import r1sim_sumo.sim.sumo_controller as sc  # noqa: E402

sc.WRONG_LANE_AHEAD_S = float(sys.argv[2])
sc.WRONG_LANE_AHEAD_M = float(sys.argv[3])
from diag_following_headway import start_run  # noqa: E402

seed = int(sys.argv[1])
libsumo, ctrl = start_run("sumo-game-ramp", "commands", 400, seed, None)
arrived = 0
try:
    for _ in range(4000):
        libsumo.simulationStep()
        ctrl.step()
        arrived += len(libsumo.simulation.getArrivedIDList())
    waiting = len(libsumo.simulation.getPendingVehicles())
finally:
    ctrl.close()
print(f"seed {seed} ahead {sys.argv[2]} s / {sys.argv[3]} m: arrivals {arrived}, waiting to insert {waiting}, "
      f"route-merge decisions {ctrl.stats.route_merge_decisions}, policy vkm share {ctrl.stats.summary()['policy_vkm_share']:.3f}")
