"""SUMO's traffic rules as seen by one vehicle: where it must stop, how fast it may go, which lanes it may use.

Used by the position drive of :class:`~r1sim_sumo.sim.sumo_controller.SumoController`, where vehicles are
placed with ``moveToXY`` and SUMO's own driver model (which would stop at red lights, yield at junctions and
respect the vehicle type) is switched off. Queried once per 0.5 s decision per controlled vehicle.

* :func:`stop_distance`: distance [m] from the vehicle's front bumper to the first place ahead it must stop:
  a red signal, a yellow one it can still stop for with its comfortable deceleration, or the stop line of a link
  ahead on its route (as far as it looks) that has no priority and that SUMO reports as closed for it
  (``vehicle.getNextLinks``' ``isOpen``: minor links, stop signs, right-before-left), or that leads into a
  junction it could not leave: the lane behind the junction has no room for it, because (nearly) standing
  vehicles fill its start (SUMO's own drivers keep junctions clear the same way; a vehicle standing inside a
  junction blocks the crossing traffic and, in a roundabout, the whole ring). ``inf`` when none within reach.
* :class:`VehicleLimits`: the vehicle's max speed [m/s], acceleration, deceleration and emergency deceleration
  [m/s^2] and its vehicle class (from SUMO, per vehicle: a vType distribution may give each its own).
* :class:`LanePermissions`: whether a lane allows a vehicle class (cached per lane).
"""

from __future__ import annotations

from dataclasses import dataclass

STOP_STATES_RED = "rR"  # SUMO link states: red
STOP_STATES_YELLOW = "yY"  # yellow: stop when it can still stop comfortably
YIELD_STATES = "msw="  # minor link, stop sign, right before left, all-way stop (SUMO link state letters)
MIN_GAP_M = 2.5  # [m] room kept behind a standing vehicle (SUMO's default minGap)
JAMMED_MPS = 1.0  # [m/s] a vehicle slower than this at the start of the lane behind a junction does not make room soon


@dataclass(frozen=True)
class VehicleLimits:
    """Dynamics limits of one vehicle (SUMO vType values, possibly per-vehicle)."""

    max_speed_mps: float
    accel_mps2: float
    decel_mps2: float
    emergency_decel_mps2: float
    vclass: str

    @classmethod
    def of(cls, conn, vid: str) -> VehicleLimits:
        v = conn.vehicle
        return cls(float(v.getMaxSpeed(vid)), float(v.getAccel(vid)), float(v.getDecel(vid)),
                   float(v.getEmergencyDecel(vid)), str(v.getVehicleClass(vid)))


class LanePermissions:
    """``allows(lane_id, vclass)``: SUMO's permission of a lane for a vehicle class (asked once per lane)."""

    def __init__(self, conn):
        self.conn = conn
        self._cache: dict[str, tuple[frozenset, frozenset]] = {}

    def allows(self, lane_id: str, vclass: str) -> bool:
        p = self._cache.get(lane_id)
        if p is None:
            try:
                p = (frozenset(self.conn.lane.getAllowed(lane_id)), frozenset(self.conn.lane.getDisallowed(lane_id)))
            except Exception:  # noqa: BLE001 - unknown lane: no restriction known
                p = (frozenset(), frozenset())
            self._cache[lane_id] = p
        allowed, disallowed = p
        return vclass in allowed if allowed else vclass not in disallowed


def room_behind_junction_m(conn, lane_after: str, via_lane: str) -> float:
    """Free length [m] at the start of ``lane_after`` (the lane a junction link leads to) that (nearly) standing
    vehicles leave, less what the vehicles already on the link's internal lane ``via_lane`` will take (their length
    plus :data:`MIN_GAP_M` each). ``inf`` when every vehicle there moves at :data:`JAMMED_MPS` or more."""
    v = conn.vehicle
    rear = float("inf")
    for other in conn.lane.getLastStepVehicleIDs(lane_after):
        if v.getSpeed(other) < JAMMED_MPS:
            rear = min(rear, float(v.getLanePosition(other)) - float(v.getLength(other)))  # its back bumper [m]
    if rear == float("inf"):
        return rear
    if via_lane:
        rear -= sum(float(v.getLength(o)) + MIN_GAP_M for o in conn.lane.getLastStepVehicleIDs(via_lane))
    return rear


def stop_distance(conn, vid: str, speed_mps: float, decel_mps2: float, reach_m: float) -> tuple[float, str]:
    """Distance [m] from ``vid``'s front bumper to where it must stop, and why (``red``, ``yield``, ``blocked``
    or ``""``).

    :param speed_mps: its speed now; a yellow signal closer than ``speed^2 / (2 decel)`` is passed.
    :param reach_m: only stops within this distance [m] count.
    """
    best, why = float("inf"), ""
    for _tls, _idx, dist, state in conn.vehicle.getNextTLS(vid):
        if dist > reach_m:
            break
        if state in STOP_STATES_RED or (state in STOP_STATES_YELLOW and dist >= speed_mps**2 / (2.0 * decel_mps2)):
            best, why = float(dist), "red"
            break
    lane = conn.vehicle.getLaneID(vid)
    if not lane or lane.startswith(":"):  # inside a junction: it has the way it took
        return best, why
    dist = conn.lane.getLength(lane) - conn.vehicle.getLanePosition(vid)  # [m] to the next link's stop line
    if dist >= min(best, reach_m):
        return best, why
    own_m = float(conn.vehicle.getLength(vid)) + MIN_GAP_M
    for i, (after, prio, is_open, _has_foe, via, state, _dir, _len) in enumerate(conn.vehicle.getNextLinks(vid)):
        if dist >= min(best, reach_m):
            break
        # yielding is decided at the next link only: a foe approaching a link further on has passed by then. It yields
        # where SUMO finds the link closed for it (``isOpen``: SUMO's own gap acceptance, its drivers' decision), not
        # wherever a foe approaches (``hasFoe``: also true for gaps SUMO's drivers take; yielding on it as well until
        # session 61 cost the roundabout's and game/ramp's entries, docs/simulate/roundabout_s61)
        if i == 0 and not prio and state in YIELD_STATES and not is_open:
            return max(float(dist), 0.0), "yield"
        if after and room_behind_junction_m(conn, after, via) < own_m:
            return max(float(dist), 0.0), "blocked"
        if not after:
            break
        dist += (conn.lane.getLength(via) if via else 0.0) + conn.lane.getLength(after)
    return best, why
