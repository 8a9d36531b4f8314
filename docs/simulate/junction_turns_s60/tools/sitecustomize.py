"""Session 60 experiments on the bundled roundabout (position drive, seed 0), switched on by ``R1SIM_EXP`` (several
may be joined with ``+``) with this folder first on ``PYTHONPATH`` (a ``sitecustomize`` reaches the ``r1sim simulate``
subprocesses of ``examples/full_horizon_runs.py``). Each patches :class:`~r1sim_sumo.sim.sumo_controller.SumoController`:

* ``exit_sumo``: every controlled vehicle on one of the ring's internal lanes whose route's next edge is an ``*_out`` arm
  is handed to SUMO at decisions and never taken back (a counterfactual: SUMO drives every exit).
* ``route_path_exits`` / ``route_path_all``: at decisions the plan of a vehicle on an exit internal lane (every internal
  lane) is laid along its route's lanes at the plan's own arc lengths (the policy's speed, the route's path).
* ``junction_leaders``: a vehicle on an internal lane ignores a leader on a lane that is neither its own, a foe of it
  (``lane.getInternalFoes``), one it leads to, nor its route's next edge.
* ``lane_speed``: no faster than the lane's limit x the vehicle's speed factor, braking at its type's deceleration to
  the limits of the lanes ahead (SUMO's drivers do both).
* ``turn_handoff_snap``: a vehicle left on no lane inside a junction is handed to SUMO (instead of snapped) and taken
  back on a later route edge. (``turn_handoff_plan``, the plan's end more than 1.5 m from the vehicle's way through the
  junction, is now the package's ``junction_turns="sumo"``.)
* ``way_kappa``: the safety filter's corridor of a vehicle on an internal lane bends with its way through the junction,
  not with its plan.

All but ``way_kappa`` were measured against the controller before session 60: give ``--junction-turns policy`` to
``examples/full_horizon_runs.py`` to rerun them on today's code; ``way_kappa`` on top of ``junction_turns="sumo"``.
"""

import os

_exp = os.environ.get("R1SIM_EXP", "")
if "exit_sumo" in _exp:
    import r1sim_sumo.sim.sumo_controller as sc
    _orig = sc.SumoController._check_controlled

    def _check(self, states, ctrl):
        ids = [str(v) for v in states.ids]
        for i in range(len(ids)):
            if not ctrl[i]:
                continue
            vid = ids[i]
            try:
                lane = self.conn.vehicle.getLaneID(vid)
                road = self.conn.vehicle.getRoadID(vid)
                r, k = self.conn.vehicle.getRoute(vid), self.conn.vehicle.getRouteIndex(vid)
            except Exception:
                continue
            if (lane.startswith(":ring") or (not lane and road.startswith(":ring"))) and 0 <= k < len(r) - 1 and r[k + 1].endswith("_out"):
                self._hand_back(vid, "experiment")
                ctrl[i] = False
        return _orig(self, states, ctrl)

    sc.SumoController._check_controlled = _check

if "route_path" in _exp:
    import numpy as np

    import r1sim_sumo.sim.sumo_controller as sc
    _orig_rules = sc.SumoController._apply_rules
    _succ = {}

    def _successor(self, lane_id, next_edge):
        key = (lane_id, next_edge)
        if key not in _succ:
            nxt = -1
            try:
                for lk in self.conn.lane.getLinks(lane_id):
                    if lk[0].rsplit("_", 1)[0] == next_edge:
                        nxt = self.locator.index_of(lk[0]); break
            except Exception:
                pass
            _succ[key] = nxt
        return _succ[key]

    def _rules(self, vids, states, rows):
        _orig_rules(self, vids, states, rows)
        c, loc, fol = self.conn, self.locator, self.follower
        for vid in vids:
            rec = self.vehicles[vid]
            try:
                lane = c.vehicle.getLaneID(vid)
                if not lane.startswith(":"):
                    continue
                r, k = c.vehicle.getRoute(vid), c.vehicle.getRouteIndex(vid)
                if not (0 <= k < len(r) - 1):
                    continue
                if "exits" in _exp and not r[k + 1].endswith("_out"):
                    continue
                ki = loc.index_of(lane)
                nxt = _successor(self, lane, r[k + 1])
                if ki < 0 or nxt < 0:
                    continue
                s0 = float(c.vehicle.getLanePosition(vid)) - 0.5 * float(self._size[rec.slot, 0])
            except Exception:
                continue
            s = s0 + fol.arc[rec.slot].astype(np.float64)
            L = float(loc.length_m[ki])
            p1, a1 = loc.along(ki, np.clip(s, 0.0, L))
            p2, a2 = loc.along(nxt, np.maximum(s - L, 0.0))
            beyond = s > L
            fol.xy[rec.slot] = np.where(beyond[:, None], p2, p1)
            fol.yaw[rec.slot] = np.where(beyond, a2, a1)
            from r1sim_sumo.sim.safety_filter import path_curvature
            fol.kappa[rec.slot] = path_curvature(fol.yaw[rec.slot][None], fol.arc[rec.slot][None])[0]

    sc.SumoController._apply_rules = _rules

if "lane_speed" in _exp:
    import numpy as np

    import r1sim_sumo.sim.sumo_controller as sc
    _orig_rules2 = sc.SumoController._apply_rules
    _orig_allowed = sc.SumoController._allowed_speeds
    _maxspeed = {}

    def _lane_v(conn, lane):
        if lane not in _maxspeed:
            _maxspeed[lane] = (float(conn.lane.getMaxSpeed(lane)), float(conn.lane.getLength(lane)))
        return _maxspeed[lane]

    def _rules2(self, vids, states, rows):
        _orig_rules2(self, vids, states, rows)
        c = self.conn
        if not hasattr(self, "_lim_d"):
            self._lim_d = {}
        for vid in vids:
            rec = self.vehicles[vid]
            try:
                sf = float(c.vehicle.getSpeedFactor(vid))
                lane = c.vehicle.getLaneID(vid)
                if not lane:
                    self._lim_d[rec.slot] = None
                    continue
                vl, L = _lane_v(c, lane)
                d = [0.0]; v = [vl * sf]
                dist = L - float(c.vehicle.getLanePosition(vid))
                for after, _p, _o, _f, via, _s, _dir, _len in c.vehicle.getNextLinks(vid):
                    if dist > 60.0:
                        break
                    if via:
                        vv, Lv = _lane_v(c, via); d.append(dist); v.append(vv * sf); dist += Lv
                    if not after:
                        break
                    va, La = _lane_v(c, after); d.append(dist); v.append(va * sf); dist += La
                self._lim_d[rec.slot] = (np.array(d), np.array(v), self._k)
            except Exception:
                self._lim_d[rec.slot] = None

    def _allowed2(self, states, vids, slots):
        allowed, floor = _orig_allowed(self, states, vids, slots)
        lim_d = getattr(self, "_lim_d", {})
        lim = self._limits[slots]
        cap = np.full(len(slots), np.inf)
        for i, s in enumerate(slots.tolist()):
            e = lim_d.get(s)
            if e is None:
                continue
            d, v, _k = e
            b = 4.5 if np.isnan(lim[i, 2]) else lim[i, 2]
            prog = self.follower.prog_m[s]
            dd = np.maximum(d - prog, 0.0)
            cap[i] = float(np.min(np.sqrt(v * v + 2.0 * b * dd)))
        col = self._k % sc.N_HISTORY_10HZ
        v_now = np.where(self._moved_at[slots] == self._k - 1, self._moved_speed[slots], cap)
        edec = np.where(np.isnan(lim[:, 3]), self.safety.emergency_decel_mps2, lim[:, 3])
        cap = np.maximum(cap, v_now - edec * sc.STEP_LENGTH_S)
        self.stats.speed_limited += 0
        allowed = np.minimum(allowed, cap)
        return allowed, None if floor is None else np.minimum(floor, allowed)

    sc.SumoController._apply_rules = _rules2
    sc.SumoController._allowed_speeds = _allowed2

if "junction_leaders" in _exp:
    import numpy as np

    import r1sim_sumo.sim.sumo_controller as sc
    _orig_allowed3 = sc.SumoController._allowed_speeds
    _foes = {}

    def _allowed3(self, states, vids, slots):
        c = self.conn
        orig_lg = self.safety.leader_gap
        ids = [str(v) for v in states.ids]
        me = self

        def lg(rows, *a, **kw):
            gap, vl, lead = orig_lg(rows, *a, **kw)
            for n, r in enumerate(np.asarray(rows).tolist()):
                if lead[n] < 0:
                    continue
                try:
                    ego = ids[r]
                    el = c.vehicle.getLaneID(ego)
                    if not el.startswith(":"):
                        continue
                    ol = c.vehicle.getLaneID(ids[lead[n]])
                    if not ol:
                        continue
                    if el not in _foes:
                        _foes[el] = set(c.lane.getInternalFoes(el)) | {el} | {lk[0] for lk in c.lane.getLinks(el)}
                    route, k = c.vehicle.getRoute(ego), c.vehicle.getRouteIndex(ego)
                    if ol in _foes[el] or (not ol.startswith(":") and ol.rsplit("_", 1)[0] in route[k + 1:k + 2]):
                        continue
                    gap[n], vl[n], lead[n] = np.inf, 0.0, -1
                    me.stats.reroutes["exp_dropped_leader"] += 1
                except Exception:
                    continue
            return gap, vl, lead

        object.__setattr__(self.safety, "leader_gap", lg)
        try:
            return _orig_allowed3(self, states, vids, slots)
        finally:
            object.__setattr__(self.safety, "leader_gap", orig_lg)

    sc.SumoController._allowed_speeds = _allowed3

if "turn_handoff" in _exp:
    import numpy as np

    import r1sim_sumo.sim.sumo_controller as sc
    _orig_retake = sc.SumoController._may_retake

    def _retake(self, vid, rec, speed):
        if rec.reason == "junction_turn":
            try:
                road = self.conn.vehicle.getRoadID(vid)
            except Exception:
                return False
            route = rec.route
            return road in route and rec.handback_edge in route and route.index(road) > route.index(rec.handback_edge)
        return _orig_retake(self, vid, rec, speed)

    sc.SumoController._may_retake = _retake

    def _handoff(self, vid, rec):
        try:
            r, k = self.conn.vehicle.getRoute(vid), self.conn.vehicle.getRouteIndex(vid)
        except Exception:
            return False
        if not (0 <= k < len(r) - 1):
            return False
        self._hand_back(vid, "junction_turn")
        rec.handback_edge = r[k]
        return True

    if "snap" in _exp:
        _orig_move5 = sc.SumoController._move

        def _move5(self, k, states):
            for vid, rec in list(self.vehicles.items()):
                if rec.state != "controlled":
                    continue
                try:
                    lane = self.conn.vehicle.getLaneID(vid)
                    inj = not lane and self.conn.vehicle.getRoadID(vid).startswith(":")
                except Exception:
                    inj = False
                if inj:
                    _handoff(self, vid, rec)
            return _orig_move5(self, k, states)

        sc.SumoController._move = _move5


if "way_kappa" in _exp:
    import numpy as np

    import r1sim_sumo.sim.sumo_controller as sc
    _orig = sc.SumoController._apply_rules

    def _rules(self, vids, states, rows):
        _orig(self, vids, states, rows)
        c, loc, fol = self.conn, self.locator, self.follower
        for vid in vids:
            rec = self.vehicles[vid]
            if rec.state != "controlled":
                continue
            found = self._junction_way(vid)
            if found is None:
                continue
            try:
                s0 = max(float(c.vehicle.getLanePosition(vid)) - 0.5 * float(self._size[rec.slot, 0]), 0.0)
            except Exception:
                continue
            way = found[1]
            k0, nxt = way[0], way[-1]
            L0 = float(loc.length_m[k0])
            D = max(float(fol.arc[rec.slot, -1]), 4.0)
            _, h0 = loc.along(k0, np.array([s0]))
            s1 = s0 + D
            _, h1 = loc.along(k0, np.array([s1])) if s1 <= L0 else loc.along(nxt, np.array([s1 - L0]))
            d = float(np.arctan2(np.sin(h1[0] - h0[0]), np.cos(h1[0] - h0[0])))
            fol.kappa[rec.slot] = d / D
            self.stats.reroutes["exp_way_kappa"] += 1

    sc.SumoController._apply_rules = _rules
