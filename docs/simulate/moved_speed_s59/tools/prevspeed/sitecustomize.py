"""Experiment (session 59): tell SUMO each moved vehicle's speed (setPreviousSpeed) before the next step, so SUMO's
followers see the speed the controller moved it at instead of SUMO's recomputed reading."""
import os
if os.environ.get("R1SIM_PREVSPEED") == "1":
    import r1sim_sumo.sim.sumo_controller as sc
    _orig = sc.SumoController._move

    def _move(self, k, states):
        sp = self.conn.vehicle.setPreviousSpeed
        for vid, rec in self.vehicles.items():
            if rec.state == "controlled" and self._moved_at[rec.slot] == k - 1:
                try:
                    sp(vid, float(self._moved_speed[rec.slot]))
                except Exception:
                    pass
        return _orig(self, k, states)

    sc.SumoController._move = _move
