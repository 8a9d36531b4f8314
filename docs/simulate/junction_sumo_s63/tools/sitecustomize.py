"""Session 63 experiments (position drive), switched on by ``R1SIM_EXP`` with this folder first on ``PYTHONPATH`` (a
``sitecustomize`` reaches the ``r1sim simulate`` subprocesses of ``examples/full_horizon_runs.py``).

* ``jx<kind>_<S>``: SUMO drives a policy vehicle through a junction: it is handed to SUMO (reason ``junction_turn``)
  within ``max(20 m, S s x its allowed speed)`` of its lane's end (SUMO's front bumper) and taken back by the policy on
  its route's next edge (the package's retake rule for ``junction_turn``). ``<kind>`` says which lane ends:
  ``tls`` a signalised link, ``minor`` a link without priority (SUMO states m = s w), ``tlsminor`` either, ``all``
  every lane end that is not open (:meth:`SumoController._lane_end_is_open`: a crossing, turn, yield or signal).
"""

import os
import re

_exp = os.environ.get("R1SIM_EXP", "")
_m = re.search(r"jx(tlsminor|tls|minor|all)_(\d+(?:\.\d+)?)", _exp)
if _m:
    import r1sim_sumo.sim.sumo_controller as sc

    _KIND, _AHEAD_S = _m.group(1), float(_m.group(2))
    _SIGNAL, _MINOR = set("GgrRyYuUoO"), set("m=sw")
    _orig_check = sc.SumoController._check_controlled
    _kinds: dict[str, bool] = {}

    def _hands_over_at(self, lane: str) -> bool:
        if lane not in _kinds:
            try:
                states = {lk[5] for lk in self.conn.lane.getLinks(lane)}
            except Exception:  # noqa: BLE001
                states = set()
            if _KIND == "all":
                k = self.locator.index_of(lane)
                hit = bool(states) and k >= 0 and not self._lane_end_is_open(k)
            else:
                hit = (("tls" in _KIND and bool(states & _SIGNAL)) or ("minor" in _KIND and bool(states & _MINOR)))
            _kinds[lane] = hit
        return _kinds[lane]

    def _check_controlled(self, states, ctrl):
        _orig_check(self, states, ctrl)
        c = self.conn
        for vid, rec in list(self.vehicles.items()):
            if rec.state != "controlled":
                continue
            try:
                lane = c.vehicle.getLaneID(vid)
                if not lane or lane.startswith(":"):
                    continue
                edge = lane.rsplit("_", 1)[0]
                route = rec.route
                if edge not in route or edge == route[-1] or not _hands_over_at(self, lane):
                    continue
                left_m = float(c.lane.getLength(lane)) - float(c.vehicle.getLanePosition(vid))
                if left_m <= max(20.0, _AHEAD_S * self._allowed_speed(vid)):
                    rec.handback_edge = edge
                    self._hand_back(vid, "junction_turn")
            except Exception:  # noqa: BLE001
                continue

    sc.SumoController._check_controlled = _check_controlled

_c = re.search(r"clear(\d+)", _exp)
if _c:
    # ``clearN`` (on the package's junction_crossings="sumo"): a vehicle SUMO drove through a junction
    # (``junction_crossing`` / ``junction_turn``) is taken back only once its front bumper is its length + N m into
    # the next edge (the package: at once), so that its box has left the junction and turned onto the lane
    import r1sim_sumo.sim.sumo_controller as sc

    _CLEAR_M = float(_c.group(1))
    _orig_retake = sc.SumoController._may_retake

    def _may_retake(self, vid, rec, speed_mps):
        if not _orig_retake(self, vid, rec, speed_mps):
            return False
        if rec.reason in ("junction_turn", "junction_crossing"):
            try:
                return float(self.conn.vehicle.getLanePosition(vid)) >= self._size[rec.slot, 0] + _CLEAR_M
            except Exception:  # noqa: BLE001
                return False
        return True

    sc.SumoController._may_retake = _may_retake

if "cmdx" in _exp:
    # ``cmdx``: the commands drive's counterpart (not the package's): within the crossing reach of a crossing lane end,
    # and on a junction's internal lane, SUMO drives the speed of a commands-drive vehicle (as it does near the end of
    # a lane that does not continue its route: ``route_merge``); the policy's speed commands resume on the next edge
    import r1sim_sumo.sim.sumo_controller as sc

    _orig_route_merge = sc.SumoController._check_route_merge

    def _check_route_merge(self, vid, rec, speed_mps):
        was = rec.route_merge
        _orig_route_merge(self, vid, rec, speed_mps)
        if rec.route_merge:
            return
        try:
            lane = self.conn.vehicle.getLaneID(vid)
            here = lane.startswith(":")
            if not here and lane:
                near = self._near_lane_end(vid, sc.crossing_reach_m(self._allowed_speed(vid)))
                here = near is not None and self._crossing_at_end(near)
        except Exception:  # noqa: BLE001
            here = False
        if here:
            rec.route_merge = True
            if not was:
                self.conn.vehicle.setSpeed(vid, -1)
            rec.lat_drift_m, rec.lc_target = 0.0, None

    sc.SumoController._check_route_merge = _check_route_merge
