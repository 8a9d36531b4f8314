"""SUMO's traffic rules as seen by one vehicle: where it must stop, how fast it may go, which lanes it may use.

Used by the position drive of :class:`~r1sim_sumo.sim.sumo_controller.SumoController`, where vehicles are
placed with ``moveToXY`` and SUMO's own driver model (which would stop at red lights, yield at junctions and
respect the vehicle type) is switched off. Queried once per 0.5 s decision per controlled vehicle.

* :func:`stop_distance`: distance [m] from the vehicle's front bumper to the first place ahead it must stop:
  a red signal, a yellow one it can still stop for with its comfortable deceleration, or the end of its lane
  before a junction link without priority that SUMO reports as closed or with an approaching foe
  (``vehicle.getNextLinks``: minor links, stop signs, right-before-left). ``inf`` when none within reach.
* :class:`VehicleLimits`: the vehicle's max speed [m/s], acceleration, deceleration and emergency deceleration
  [m/s^2] and its vehicle class (from SUMO, per vehicle: a vType distribution may give each its own).
* :class:`LanePermissions`: whether a lane allows a vehicle class (cached per lane).
"""

from __future__ import annotations

from dataclasses import dataclass

STOP_STATES_RED = "rR"  # SUMO link states: red
STOP_STATES_YELLOW = "yY"  # yellow: stop when it can still stop comfortably
YIELD_STATES = "msw="  # minor link, stop sign, right before left, all-way stop (SUMO link state letters)


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


def stop_distance(conn, vid: str, speed_mps: float, decel_mps2: float, reach_m: float) -> tuple[float, str]:
    """Distance [m] from ``vid``'s front bumper to where it must stop, and why (``red``, ``yield`` or ``""``).

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
    left = conn.lane.getLength(lane) - conn.vehicle.getLanePosition(vid)
    if left >= min(best, reach_m):
        return best, why
    links = conn.vehicle.getNextLinks(vid)
    if links:
        _lane, prio, is_open, has_foe, _via, state, _dir, _len = links[0]
        if not prio and state in YIELD_STATES and (has_foe or not is_open):
            return max(float(left), 0.0), "yield"
    return best, why
