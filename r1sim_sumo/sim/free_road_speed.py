"""Free-road speed: how close vehicles drive to the speed they want where nothing holds them back.

The drop-in report's arrivals and mean speed mix two causes: traffic that jams and drivers that go slower than they
want on an open road. This measure isolates the second. A vehicle is on a *free road* at a sample when

- it is on a normal lane (not inside a junction);
- no leader is within :data:`FREE_LOOK_M` ahead along its route (``vehicle.getLeader``);
- no traffic light is within :data:`FREE_LOOK_M` ahead (``vehicle.getNextTLS``);
- the end of its lane is further than :data:`FREE_LOOK_M` ahead, or the next link on its way is a straight,
  open link with priority onto a lane with no lower speed limit (``vehicle.getNextLinks``: no turn or slower road
  to slow for, no yield);
- SUMO knows its desired speed (the lane's limit x its speedFactor, capped by its type's maxSpeed:
  :func:`~r1sim_sumo.adapters.sumo_state.read_desired_speeds`), at least :data:`MIN_DESIRED_MPS`.

Its *free-road speed share* is speed / desired speed, averaged over such vehicle-samples. A SUMO driver (Krauss) on
a free road drives at its desired speed (share ~1 after its acceleration, less ``sigma`` dawdling); a policy that holds
whatever speed it has shows a share below 1. Sampled every :data:`SAMPLE_EVERY_STEPS` steps (0.5 s at 0.1 s steps)
by ``r1sim simulate`` for every vehicle in native runs and for the vehicles the policy drives in policy runs; it is a
report measure and costs a few TraCI calls per vehicle and sample, so the controller itself does not compute it.

Units: metres, m/s; SUMO's own lane positions.
"""

from __future__ import annotations

import numpy as np

from r1sim_sumo.adapters.sumo_state import read_desired_speeds

__all__ = ["FREE_LOOK_M", "MIN_DESIRED_MPS", "SAMPLE_EVERY_STEPS", "FreeRoadSpeed"]

FREE_LOOK_M = 100.0  # [m] no leader, signal or slowing link within this ahead
MIN_DESIRED_MPS = 1.0  # [m/s] vehicles wanting less are not counted (parking manoeuvres, odd types)
SAMPLE_EVERY_STEPS = 5  # one sample per 0.5 s of simulated time at 0.1 s steps
STRAIGHT = "s"  # SUMO link direction of a straight link
LEADER_MIN_GAP_M = 2.5  # [m] is_free(leader_headway_s=...): gap beyond the headway a leader must leave (SUMO's minGap)
LEADER_SLOWER_MPS = 0.5  # [m/s] is_free(leader_headway_s=...): a leader slower than this below the follower counts


class FreeRoadSpeed:
    """Accumulates ``free_road_samples`` and ``free_road_speed_share_sum`` of a
    :class:`~r1sim_sumo.sim.sumo_controller.ControllerStats` (its ``summary()`` gives the mean as
    ``free_road_speed_share``).

    :param conn: ``libsumo`` or a ``traci`` connection.
    :param look_m: how far ahead [m] the road must be free.
    """

    def __init__(self, conn, look_m: float = FREE_LOOK_M):
        self.conn = conn
        self.look_m = float(look_m)
        self._lane_length: dict[str, float] = {}
        self._lane_speed: dict[str, float] = {}
        self._steps = 0

    def step(self, stats, vehicles) -> None:
        """Call after every simulation step; every :data:`SAMPLE_EVERY_STEPS` calls it samples the vehicles that
        ``vehicles()`` returns (ids: all of them, or those a policy drives; only called when sampling)."""
        self._steps += 1
        if self._steps % SAMPLE_EVERY_STEPS:
            return
        ids = [v for v in vehicles() if self.is_free(v)]
        if not ids:
            return
        desired = read_desired_speeds(self.conn, ids).astype(np.float64)
        speed = np.array([self.conn.vehicle.getSpeed(v) for v in ids], np.float64)
        ok = np.isfinite(desired) & (desired >= MIN_DESIRED_MPS)
        stats.free_road_samples += int(ok.sum())
        stats.free_road_speed_share_sum += float((speed[ok] / desired[ok]).sum())

    def _max_speed(self, lane: str) -> float:
        """The lane's speed limit [m/s] (cached per lane)."""
        v = self._lane_speed.get(lane)
        if v is None:
            v = self._lane_speed[lane] = float(self.conn.lane.getMaxSpeed(lane))
        return v

    def is_free(self, vid: str, leader_headway_s: float | None = None) -> bool:
        """Whether nothing ahead of ``vid`` gives it a reason to drive below its desired speed (module docstring);
        ``False`` when a query fails (a vehicle that just left). ``leader_headway_s`` (None: any leader within the
        look-ahead counts): a leader at least this many seconds of ``vid``'s speed ahead (plus
        :data:`LEADER_MIN_GAP_M`), and not slower than ``vid`` by more than :data:`LEADER_SLOWER_MPS`, is no reason to
        drive slower (the drop-in's open-road decoding, ``SumoController(free_road_headway_s=...)``); the report
        measure counts every leader."""
        v, look = self.conn.vehicle, self.look_m
        try:
            lane = v.getLaneID(vid)
            if not lane or lane.startswith(":"):
                return False
            lead = v.getLeader(vid, look)
            if lead and lead[0] and lead[1] < look:
                if leader_headway_s is None:
                    return False
                own = float(v.getSpeed(vid))
                if lead[1] < leader_headway_s * own + LEADER_MIN_GAP_M or float(v.getSpeed(lead[0])) < own - LEADER_SLOWER_MPS:
                    return False
            if any(t[2] < look for t in v.getNextTLS(vid)):
                return False
            length = self._lane_length.get(lane)
            if length is None:
                length = self._lane_length[lane] = float(self.conn.lane.getLength(lane))
            if length - float(v.getLanePosition(vid)) > look:
                return True
            links = v.getNextLinks(vid)
            if not links:  # the end of its route (it slows to arrive) or a dead end
                return False
            nxt = links[0]  # (lane, via, hasPriority, isOpen, hasFoe, state, direction, length)
            if not (nxt[2] and nxt[3] and nxt[6] == STRAIGHT):
                return False
            return self._max_speed(nxt[0]) >= self._max_speed(lane)  # no slower road to brake for
        except Exception:  # noqa: BLE001 - TraCIException / libsumo error: not counted
            return False
