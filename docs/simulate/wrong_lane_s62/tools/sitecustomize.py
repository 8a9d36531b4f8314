"""Session 62 experiments (position drive), switched on by ``R1SIM_EXP`` (joined with ``+``) with this folder first on
``PYTHONPATH`` (a ``sitecustomize`` reaches the ``r1sim simulate`` subprocesses of ``examples/full_horizon_runs.py``).

* ``wlM_S``: a position-drive vehicle in a lane that does not lead on along its route is handed to SUMO to change lanes
  within ``max(M m, S s x speed)`` of the lane's end (session 61's rule: 40 m / 4 s), e.g. ``wl130_10``.
* ``wlsumo``: within 10 s x its allowed speed (SUMO LC2013's strategic look-ahead); now the package's rule.
* ``wlnext``: the 10 s look-ahead only where the lane does not reach the route's next edge (session 61's rule where it
  does).
* ``resumeNN``: a standstill hand-off is taken back at NN % of the allowed speed (the package: 60 %).
* ``QLOG=FILE``: log of the queues open for 20 s or more (queue_growth).
"""

import os
import re

_exp = os.environ.get("R1SIM_EXP", "")
_m = re.search(r"wl(\d+)_(\d+)", _exp)
if _m:
    import r1sim_sumo.sim.sumo_controller as sc

    sc.WRONG_LANE_AHEAD_M = float(_m.group(1))
    sc.WRONG_LANE_AHEAD_S = float(_m.group(2))

if "wlsumo" in _exp:
    # ``wlsumo``: within SUMO LC2013's strategic look-ahead of the lane's end: 10 s (its LOOK_FORWARD) x the lane's
    # allowed speed for the vehicle (not its current speed: a vehicle in a queue is handed over as early as a free one);
    # ``wlsumo2``: 2 x that for a change to the left (LC2013's lcLookaheadLeft default 2.0)
    import r1sim_sumo.sim.sumo_controller as sc

    sc.WRONG_LANE_AHEAD_M = 1.0e6  # the box-centre pre-filter of _check_controlled lets every vehicle through

    def _near_lane_end(self, vid, speed_mps):
        try:
            lane = self.conn.vehicle.getLaneID(vid)
            if not lane or lane.startswith(":"):
                return None
            left_m = float(self.locator.length_m[self.locator.index_of(lane)]) - float(self.conn.vehicle.getLanePosition(vid))
            reach = 10.0 * float(self.conn.vehicle.getAllowedSpeed(vid))
            if "wlsumo2" in _exp:
                best = self._best_lane_entry(vid, lane)
                if best is not None and best[0] > 0:
                    reach *= 2.0
        except Exception:
            return None
        return lane if left_m <= reach else None

    sc.SumoController._near_lane_end = _near_lane_end

_r = re.search(r"resume(\d+)", _exp)
if _r:
    # ``resumeNN``: a vehicle handed to SUMO at a standstill is taken back once SUMO has it at NN % of its allowed speed
    # (the package: 60 %)
    import r1sim_sumo.sim.sumo_controller as sc

    sc.RESUME_SPEED_SHARE = int(_r.group(1)) / 100.0

if os.environ.get("QLOG"):
    # ``QLOG=FILE`` (any variant, or none): every second, each queue (r1sim_sumo.sim.queue_growth) that has not cleared
    # for 20 s or more: ``time head start=.. min=N@t max=N growth=S``
    import r1sim_sumo.sim.queue_growth as qg

    _orig_update = qg.QueueGrowthTracker.update
    _qlog = open(os.environ["QLOG"], "w")

    def _update(self, stats, conn, ids, speed_mps, now_s, waiting_to_insert):
        sampled = (self._n + 1) % self.every == 0
        _orig_update(self, stats, conn, ids, speed_mps, now_s, waiting_to_insert)
        if not sampled:
            return
        for head, ep in self._open.items():
            if now_s - ep.start_s >= 20:
                _qlog.write(f"{now_s:.0f} {head} start={ep.start_s:.0f} min={ep.min_n}@{ep.min_at_s:.0f} max={ep.max_n} "
                            f"growth={ep.growth_s}\n")
        _qlog.flush()

    qg.QueueGrowthTracker.update = _update

if "wlnext" in _exp:
    # ``wlnext`` (on the package since 8c5dbb3): the 10 s look-ahead only for a lane that does not reach the route's
    # next edge; a lane that does (the change could still be made on the next edge, e.g. game/ramp's approach to its
    # off-ramp split) keeps session 61's max(40 m, 4 s x speed)
    import r1sim_sumo.sim.sumo_controller as sc

    _orig_near = sc.SumoController._near_lane_end
    _reaches: dict = {}

    def _near_lane_end_next(self, vid, reach_m):
        try:
            lane = self.conn.vehicle.getLaneID(vid)
            route, i = self.conn.vehicle.getRoute(vid), int(self.conn.vehicle.getRouteIndex(vid))
            if lane and not lane.startswith(":") and 0 <= i < len(route) - 1:
                key = (lane, route[i + 1])
                if key not in _reaches:
                    _reaches[key] = any(str(lk[0]).rsplit("_", 1)[0] == route[i + 1] for lk in self.conn.lane.getLinks(lane))
                if _reaches[key]:
                    reach_m = min(reach_m, sc.route_merge_reach_m(self.conn.vehicle.getSpeed(vid)))
        except Exception:
            pass
        return _orig_near(self, vid, reach_m)

    sc.SumoController._near_lane_end = _near_lane_end_next
