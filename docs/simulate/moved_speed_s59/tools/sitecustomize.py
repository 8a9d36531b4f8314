"""Experiment (session 59): the position drive as before session 59. ``R1SIM_SUMOSPEED=1``: plans from SUMO's speed
reading of a moved vehicle and the acceleration cap from its displacement; ``=2``: that and neither the centre-line snap
nor the carriageway rule's lane inheritance (session 58's controller). ``R1SIM_NOSNAP=1`` (alone): the moved speed
without the centre-line snap and the lane inheritance (session 59's first step)."""
import os

_mode = os.environ.get("R1SIM_SUMOSPEED", "")
if _mode in ("1", "2"):
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
    if _mode == "2":
        sc.SumoController._snap_standing_over_centre_line = lambda self, slots: None
        sc.SumoController._inherit_lanes = lambda self, lane, half, along, xy: None

if os.environ.get("R1SIM_NOSNAP") == "1":
    import r1sim_sumo.sim.sumo_controller as sc
    sc.SumoController._snap_standing_over_centre_line = lambda self, slots: None
    sc.SumoController._inherit_lanes = lambda self, lane, half, along, xy: None
