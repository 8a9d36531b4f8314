"""SUMO vehicle state <-> internal agent state (box centre, yaw radians), in both directions.

Frames and units: internal = metres, x east, y north, yaw radians CCW from +x, position = box centre.
SUMO reports (and ``moveToXY`` takes) the *front-bumper centre* and a *navigational angle* in degrees
(0 = north, clockwise); the conversions are those of :mod:`r1sim_sumo.geometry`, nothing is re-derived here.

``conn`` is either the ``libsumo`` module or a ``traci`` connection (``traci.start(...)`` /
``traci.getConnection(label)``): both expose the same ``conn.vehicle`` / ``conn.simulation`` API.

Static attributes (length, width, vehicle class) are cached per connection and vehicle id. The cache of a
connection is cleared when the simulation time goes backwards (a new simulation or ``loadState``) and a
vehicle's entry is refreshed when it appears in ``simulation.getDepartedIDList()`` (inserted in the last
step, e.g. an id reused by ``vehicle.add``). If you change a vehicle's type or size through TraCI, or start
a new simulation that reuses ids without reading states at its first steps, call
:func:`clear_static_cache`.

Timing (libsumo, 2 shared CPU cores, measured by ``tests/test_sumo_adapters.py::test_timing_100``):
see the report of that test; about 0.4 us per getter call, i.e. roughly 2-3 us per vehicle.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from r1sim_sumo.geometry import (
    centre_to_front_bumper,
    front_bumper_to_centre,
    sumo_angle_deg_to_yaw_rad,
    yaw_rad_to_sumo_angle_deg,
)
from r1sim_sumo.scenario import CYCLIST, PEDESTRIAN, VEHICLE

# SUMO vClass -> agent type (everything else is a vehicle)
VCLASS_TO_AGENT_TYPE = {"bicycle": CYCLIST, "pedestrian": PEDESTRIAN}

# speed mode 32 = only bit 5 set: bits 0-4 cleared (no safe-speed / car-following cap, no max accel, no max
# decel limit, no right of way before junctions, no braking for red lights); bit 5 set = disregard right
# of way inside junctions. Default is 31. The controller's commanded motion is executed unmodified.
SPEED_MODE_NO_CHECKS = 32
# lane change mode 0: no strategic, cooperative, speed-gain or keep-right changes of its own, and
# TraCI lane-change requests ignore the safety of others. Default is 1621 (0b011001010101).
LANE_CHANGE_MODE_NONE = 0

# moveToXY keepRoute bits
KEEP_ROUTE_SNAP = 1  # bit 0: map onto the closest position within the existing route (else any edge; the
#                      route is then replaced by that single edge and the vehicle arrives at its end)
KEEP_ROUTE_EXACT_XY = 2  # bit 1: place at the exact x,y (lateral offset too), even off the road
KEEP_ROUTE_ANY_LANE = 4  # bit 2: ignore lane permissions when mapping


@dataclass
class VehicleStates:
    """States of ``N`` vehicles at one instant (internal frame, box centres).

    :param ids: ``[N]`` str SUMO vehicle ids.
    :param agent_type: ``[N]`` int8, 0 vehicle / 1 cyclist (vClass bicycle) / 2 pedestrian (vClass pedestrian).
    :param length_m, width_m: ``[N]`` float64 box size [m].
    :param x_m, y_m: ``[N]`` float64 box centre [m]; ``yaw_rad`` ``[N]`` [rad, CCW from east, in [-pi, pi)].
    :param speed_mps: ``[N]`` float64 speed along the heading [m/s]; ``vx_mps, vy_mps`` ``[N]`` velocity [m/s].
    """

    ids: np.ndarray
    agent_type: np.ndarray
    length_m: np.ndarray
    width_m: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray
    speed_mps: np.ndarray
    vx_mps: np.ndarray
    vy_mps: np.ndarray

    def __len__(self) -> int:
        return int(len(self.ids))


class _StaticCache:
    """veh id -> (agent_type, length_m, width_m) of one connection, plus the last time it was read."""

    __slots__ = ("entries", "last_time_s")

    def __init__(self) -> None:
        self.entries: dict[str, tuple[int, float, float]] = {}
        self.last_time_s = -np.inf


_CACHES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _cache_for(conn) -> _StaticCache:
    try:
        cache = _CACHES.get(conn)
        if cache is None:
            cache = _CACHES[conn] = _StaticCache()
        return cache
    except TypeError:  # connection object not weak-referenceable: no sharing across calls
        return _StaticCache()


def clear_static_cache(conn=None) -> None:
    """Forget cached vehicle sizes/classes of ``conn`` (all connections when ``None``)."""
    if conn is None:
        _CACHES.clear()
    else:
        _CACHES.pop(conn, None)


def read_vehicle_states(conn, veh_ids: list[str] | None = None) -> VehicleStates:
    """Read the current state of vehicles from SUMO, converted to the internal frame.

    :param conn: ``libsumo`` module or a ``traci`` connection.
    :param veh_ids: vehicles to read, in this order; ``None`` = all vehicles on the network
        (``vehicle.getIDList()``). An id not in the simulation raises ``KeyError`` naming it.
    """
    v = conn.vehicle
    ids = list(v.getIDList()) if veh_ids is None else list(veh_ids)
    n = len(ids)
    cache = _cache_for(conn)
    now = float(conn.simulation.getTime())
    if now < cache.last_time_s:
        cache.entries.clear()
    cache.last_time_s = now
    entries = cache.entries
    for d in conn.simulation.getDepartedIDList():
        entries.pop(d, None)
    if len(entries) > 4 * n + 4096:  # prune vehicles that left long ago
        keep = set(ids)
        cache.entries = entries = {k: e for k, e in entries.items() if k in keep}

    agent_type = np.empty(n, np.int8)  # [N]
    raw = np.empty((n, 6), np.float64)  # [N, (x_fb, y_fb, angle_deg, speed, length, width)]
    try:
        for i, vid in enumerate(ids):
            e = entries.get(vid)
            if e is None:
                e = entries[vid] = (
                    VCLASS_TO_AGENT_TYPE.get(v.getVehicleClass(vid), VEHICLE), float(v.getLength(vid)), float(v.getWidth(vid))
                )
            x, y = v.getPosition(vid)
            raw[i] = (x, y, v.getAngle(vid), v.getSpeed(vid), e[1], e[2])
            agent_type[i] = e[0]
    except Exception as exc:
        if type(exc).__name__ != "TraCIException":
            raise
        missing = [vid for vid in ids if vid not in set(v.getIDList())]
        raise KeyError(f"read_vehicle_states: vehicle(s) {missing[:5]} not in the simulation at t={now:.2f} s "
                       f"({exc}); pass ids from vehicle.getIDList()") from exc

    yaw = sumo_angle_deg_to_yaw_rad(raw[:, 2])  # [N]
    length, width, speed = raw[:, 4].copy(), raw[:, 5].copy(), raw[:, 3].copy()
    x_c, y_c = front_bumper_to_centre(raw[:, 0], raw[:, 1], yaw, length)
    return VehicleStates(
        ids=np.asarray(ids, dtype=str) if n else np.zeros(0, "<U1"),
        agent_type=agent_type, length_m=length, width_m=width,
        x_m=np.asarray(x_c, np.float64), y_m=np.asarray(y_c, np.float64), yaw_rad=np.asarray(yaw, np.float64),
        speed_mps=speed, vx_mps=speed * np.cos(yaw), vy_mps=speed * np.sin(yaw),
    )


# ---------------------------------------------------------------------------- internal -> SUMO


def to_sumo_pose(x_m, y_m, yaw_rad, length_m):
    """Box centre pose (internal frame) -> SUMO ``(x_fb, y_fb, angle_deg)``: front-bumper centre [m] and
    navigational angle [deg, 0 = north, clockwise, in [0, 360)]. Scalars or broadcastable arrays."""
    x_fb, y_fb = centre_to_front_bumper(x_m, y_m, yaw_rad, length_m)
    return x_fb, y_fb, yaw_rad_to_sumo_angle_deg(yaw_rad)


def move_vehicle(conn, veh_id: str, x_m: float, y_m: float, yaw_rad: float, length_m: float,
                 speed_mps: float | None = None, keep_route: int = 2) -> None:
    """Place a vehicle at a box-centre pose; SUMO applies it at the next ``simulationStep``.

    Calls ``vehicle.moveToXY(veh_id, "", -1, x_fb, y_fb, angle_deg, keep_route)`` (empty edge and lane -1:
    SUMO picks the lane) and, when ``speed_mps`` is given, ``vehicle.setPreviousSpeed`` so the reported
    speed (and SUMO's follower logic) use it.

    :param keep_route: moveToXY bitset: ``KEEP_ROUTE_SNAP`` (1) keep the vehicle on its route,
        ``KEEP_ROUTE_EXACT_XY`` (2, default) exact x,y even off-road (without bit 0 the route becomes the
        single edge it is mapped to), ``KEEP_ROUTE_ANY_LANE`` (4) ignore lane permissions. 3 = exact x,y
        within 100 m of the route while keeping the route.
    """
    x_fb, y_fb, angle_deg = to_sumo_pose(float(x_m), float(y_m), float(yaw_rad), float(length_m))
    conn.vehicle.moveToXY(veh_id, "", -1, float(x_fb), float(y_fb), float(angle_deg), int(keep_route))
    if speed_mps is not None:
        conn.vehicle.setPreviousSpeed(veh_id, float(speed_mps))


def take_control(conn, veh_id: str) -> None:
    """Stop SUMO's own driver model from fighting an external controller of ``veh_id``.

    ``setSpeedMode(v, 32)``: all speed checks off (no safe-speed cap from car following, no accel/decel
    limits, no right-of-way or red-light braking; bit 5 = disregard right of way inside junctions), so a
    commanded speed is applied as is. ``setLaneChangeMode(v, 0)``: no lane changes of its own (strategic,
    cooperative, speed gain, keep right all off). Collisions are then the controller's responsibility.
    """
    conn.vehicle.setSpeedMode(veh_id, SPEED_MODE_NO_CHECKS)
    conn.vehicle.setLaneChangeMode(veh_id, LANE_CHANGE_MODE_NONE)
