"""Session 61 experiments (position drive), switched on by ``R1SIM_EXP`` (joined with ``+``) with this folder first on
``PYTHONPATH`` (a ``sitecustomize`` reaches the ``r1sim simulate`` subprocesses of ``examples/full_horizon_runs.py``).

* ``turns_all``: besides the package's ``junction_turns="sumo"`` rule, every controlled vehicle on a junction's internal
  lane whose link turns (SUMO direction ``r``, ``l``, ``R``, ``L``) is handed to SUMO at decisions (``junction_turn``)
  and taken back on a later edge of its route.
* ``turns_minor``: the same, only where the link leaves a road of higher SUMO priority for one of lower priority
  (leaving the major road: the roundabout's exits, not its entries). Now the package's rule (``junction_turns="sumo"``).
* ``yield_open``: a policy vehicle yields at a minor link (``rules.stop_distance``) only where SUMO reports the link
  closed for it (``isOpen`` of ``vehicle.getNextLinks``, SUMO's own gap acceptance), not whenever a foe approaches.
* ``no_off_route``: session 60's rule (a plan leaving its way through the junction -> SUMO) switched off.
* ``sm7``: the position drive's vehicles in SUMO speed mode 7 once taken (instead of 32).
* ``handoffN``: the standstill hand-off after N s (default 5).
* ``yield_sumo``: a policy vehicle standing at a minor link's stop line for the yield rule is handed to SUMO at once.
"""

import os

_exp = os.environ.get("R1SIM_EXP", "")
if "turns_" in _exp:
    import r1sim_sumo.sim.sumo_controller as sc

    _orig = sc.SumoController._hand_over_off_route_turns
    _dir: dict = {}
    _prio: dict = {}

    def _edge_priority(self, edge):
        if not _prio:
            import sumolib
            path = self.conn.simulation.getOption("net-file")
            if not os.path.isabs(path):
                path = os.path.join(os.path.dirname(self.conn.simulation.getOption("configuration-file")), path)
            net = sumolib.net.readNet(path)
            for e in net.getEdges():
                _prio[e.getID()] = e.getPriority()
        return _prio.get(edge, 0)

    def _turn_dir(self, lane, from_edge):
        key = (lane, from_edge)
        if key not in _dir:
            d = ""
            try:
                for k in range(self.conn.edge.getLaneNumber(from_edge)):
                    for lk in self.conn.lane.getLinks(f"{from_edge}_{k}"):
                        if lk[4] == lane:
                            d = lk[6]
            except Exception:
                pass
            _dir[key] = d
        return _dir[key]

    def _hand_over(self, vids, slots):
        _orig(self, vids, slots)
        for vid in vids:
            rec = self.vehicles[vid]
            if rec.state != "controlled":
                continue
            try:
                lane = self.conn.vehicle.getLaneID(vid)
                route, i = self.conn.vehicle.getRoute(vid), int(self.conn.vehicle.getRouteIndex(vid))
            except Exception:
                continue
            if not lane.startswith(":") or not 0 <= i < len(route) - 1:
                continue
            if _turn_dir(self, lane, route[i]) not in ("r", "l", "R", "L"):
                continue
            if "turns_minor" in _exp and not _edge_priority(self, route[i]) > _edge_priority(self, route[i + 1]):
                continue
            self._hand_back(vid, "junction_turn")
            rec.handback_edge = route[i]

    sc.SumoController._hand_over_off_route_turns = _hand_over

if "yield_open" in _exp:
    # a policy vehicle yields at a minor link only when SUMO reports the link closed for it (not for any approaching foe)
    import r1sim_sumo.sim.rules as rules
    import r1sim_sumo.sim.sumo_controller as sc

    def _stop_distance(conn, vid, speed_mps, decel_mps2, reach_m):
        best, why = float("inf"), ""
        for _tls, _idx, dist, state in conn.vehicle.getNextTLS(vid):
            if dist > reach_m:
                break
            if state in rules.STOP_STATES_RED or (state in rules.STOP_STATES_YELLOW and dist >= speed_mps**2 / (2.0 * decel_mps2)):
                best, why = float(dist), "red"
                break
        lane = conn.vehicle.getLaneID(vid)
        if not lane or lane.startswith(":"):
            return best, why
        dist = conn.lane.getLength(lane) - conn.vehicle.getLanePosition(vid)
        if dist >= min(best, reach_m):
            return best, why
        own_m = float(conn.vehicle.getLength(vid)) + rules.MIN_GAP_M
        for i, (after, prio, is_open, _has_foe, via, state, _dir, _len) in enumerate(conn.vehicle.getNextLinks(vid)):
            if dist >= min(best, reach_m):
                break
            if i == 0 and not prio and state in rules.YIELD_STATES and not is_open:
                return max(float(dist), 0.0), "yield"
            if after and rules.room_behind_junction_m(conn, after, via) < own_m:
                return max(float(dist), 0.0), "blocked"
            if not after:
                break
            dist += (conn.lane.getLength(via) if via else 0.0) + conn.lane.getLength(after)
        return best, why

    sc.stop_distance = _stop_distance

if "no_off_route" in _exp:
    # session 60's rule (a plan ending more than 1.5 m from its way through the junction -> SUMO) switched off; the turns
    # off the major road (session 61) stay SUMO's; a plan that leaves every lane inside a junction is snapped (session 31)
    import r1sim_sumo.sim.sumo_controller as sc

    sc.OFF_ROUTE_IN_JUNCTION_M = 1.0e6

if "sm7" in _exp:
    # the position drive's vehicles in SUMO speed mode 7 (safe speed, max accel, max decel; no right-of-way bits) once
    # taken, instead of 32 (every check off): SUMO's entering drivers judged gaps in front of moved vehicles in mode 32
    # as if they would not brake (session 43's probe); tried then with SUMO's speed reading in the history (lane_drop
    # lost 9% of its arrivals), retried on the history of the moved speed (session 59)
    import r1sim_sumo.sim.sumo_controller as sc

    _orig_take = sc.SumoController._take

    def _take_sm7(self, vid):
        ok = _orig_take(self, vid)
        if ok and self.drive == "position":
            try:
                self.conn.vehicle.setSpeedMode(vid, 7)
            except Exception:
                pass
        return ok

    sc.SumoController._take = _take_sm7

if "handoff" in _exp:
    # the standstill hand-off after N s instead of the default 5 s (R1SIM_EXP=handoff2, handoff10, ...)
    import re

    import r1sim_sumo.sim.sumo_controller as sc

    _secs = float(re.search(r"handoff(\d+)", _exp).group(1))
    _orig_init = sc.SumoController.__init__

    def _init(self, *a, **k):
        _orig_init(self, *a, **k)
        self.standstill_handoff_s = _secs

    sc.SumoController.__init__ = _init

if "yield_sumo" in _exp:
    # a policy vehicle standing (< 0.3 m/s) within 3 m of a minor link's stop line where the yield rule holds it is
    # handed to SUMO at once (reason standstill: SUMO's driver enters when it finds its gap; taken back once moving)
    import math

    import r1sim_sumo.sim.sumo_controller as sc

    _orig_sd = sc.stop_distance
    _last: dict = {}

    def _sd(conn, vid, *a):
        d, why = _orig_sd(conn, vid, *a)
        _last[vid] = (d, why)
        return d, why

    sc.stop_distance = _sd
    _orig_apply = sc.SumoController._apply_rules

    def _apply(self, vids, states, rows):
        _last.clear()
        _orig_apply(self, vids, states, rows)
        for j, vid in enumerate(vids):
            d, why = _last.get(vid, (math.inf, ""))
            if why == "yield" and d < 3.0 and abs(float(states.speed_mps[rows[j]])) < 0.3:
                self._hand_back(vid, "standstill")

    sc.SumoController._apply_rules = _apply
