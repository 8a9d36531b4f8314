"""Experiment (session 59): the position drive as before session 59 (plans from SUMO's speed reading, the acceleration
cap from the displacement)."""
import os
if os.environ.get("R1SIM_SUMOSPEED") == "1":
    import r1sim_sumo.sim.sumo_controller as sc
    sc.SumoController._speed_as_moved = lambda self, row, slots: None
    _orig = sc.SumoController._allowed_speeds

    def _allowed(self, states, vids, slots):
        at = self._moved_at.copy()
        self._moved_at[:] = -2
        try:
            return _orig(self, states, vids, slots)
        finally:
            self._moved_at[:] = at

    sc.SumoController._allowed_speeds = _allowed
