"""SUMO vehicle state <-> internal agent state (box centre, yaw radians), in both directions.

Frames and units: internal = metres, x east, y north, yaw radians CCW from +x, position = box centre.
SUMO reports (and ``moveToXY`` takes) the *front-bumper centre* and a *navigational angle* in degrees
(0 = north, clockwise); the conversions are those of :mod:`r1sim_sumo.geometry`, nothing is re-derived here.

``conn`` is either the ``libsumo`` module or a ``traci`` connection (``traci.start(...)`` /
``traci.getConnection(label)``): both expose the same ``conn.vehicle`` / ``conn.simulation`` API.

Static attributes (length, width, vehicle class) are cached per connection and *vehicle type id*
(``vehicle.getTypeID``, one cheap call per vehicle): vehicles of a type share them, and SUMO gives a vehicle
whose size is changed through TraCI its own type (``<type>@<vehicle>``), so ids reused by a later
simulation with another type are read afresh. The cache of a connection is also cleared when the
simulation time goes backwards (a new simulation or ``loadState``). If you change a *type's* size or class
through TraCI (``vehicletype.setLength`` ...), call :func:`clear_static_cache`.

Cost: one getter call is ~0.4 us with libsumo (a socket round trip with TraCI); with the cache a read
makes 4 calls per vehicle (type id, position, angle, speed) instead of 6.
"""

from __future__ import annotations

import weakref

import numpy as np

from r1sim_sumo.adapters.vehicle_states import VehicleStates
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


class _StaticCache:
    """type id -> (agent_type, length_m, width_m) of one connection, plus the last time it was read."""

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

    Sizes and classes are cached per vehicle type id and connection (one call per new type instead of three per
    vehicle). The cache is dropped when simulated time goes backwards; after (re)starting or ``loadState`` of another
    simulation in the same process (libsumo is one module object), call :func:`clear_static_cache` — the
    controller, the SUMO-in-the-loop rollouts and the SUMO-again baseline do.
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

    static: list[tuple[int, float, float]] = []  # [N] (agent_type, length_m, width_m)
    dynamic: list[tuple[float, float, float, float]] = []  # [N] (x_fb, y_fb, angle_deg, speed)
    get_type, get_pos, get_angle, get_speed = v.getTypeID, v.getPosition, v.getAngle, v.getSpeed
    try:
        for vid in ids:
            tid = get_type(vid)
            e = entries.get(tid)
            if e is None:
                e = entries[tid] = (
                    VCLASS_TO_AGENT_TYPE.get(v.getVehicleClass(vid), VEHICLE), float(v.getLength(vid)), float(v.getWidth(vid))
                )
            static.append(e)
            x, y = get_pos(vid)
            dynamic.append((x, y, get_angle(vid), get_speed(vid)))
    except Exception as exc:
        if type(exc).__name__ != "TraCIException":
            raise
        present = set(v.getIDList())
        missing = [vid for vid in ids if vid not in present]
        raise KeyError(f"read_vehicle_states: vehicle(s) {missing[:5]} not in the simulation at t={now:.2f} s "
                       f"({exc}); pass ids from vehicle.getIDList()") from exc

    st = np.asarray(static, np.float64).reshape(n, 3)  # [N, 3]
    dy = np.asarray(dynamic, np.float64).reshape(n, 4)  # [N, 4]
    yaw = sumo_angle_deg_to_yaw_rad(dy[:, 2])  # [N]
    length, width, speed = st[:, 1].copy(), st[:, 2].copy(), dy[:, 3].copy()
    x_c, y_c = front_bumper_to_centre(dy[:, 0], dy[:, 1], yaw, length)
    return VehicleStates(
        ids=np.asarray(ids, dtype=str) if n else np.zeros(0, "<U1"),
        agent_type=st[:, 0].astype(np.int8), length_m=length, width_m=width,
        x_m=np.asarray(x_c, np.float64), y_m=np.asarray(y_c, np.float64), yaw_rad=np.asarray(yaw, np.float64),
        speed_mps=speed, vx_mps=speed * np.cos(yaw), vy_mps=speed * np.sin(yaw),
    )


# ---------------------------------------------------------------------------- internal -> SUMO


def read_desired_speeds(conn, veh_ids) -> np.ndarray:
    """``[N]`` float32: the speed each SUMO driver wants on its current lane [m/s], the lane's limit x its speedFactor
    (``vehicle.getAllowedSpeed``) capped by its type's maxSpeed; NaN where SUMO cannot tell (a failing query)."""
    v = conn.vehicle
    out = np.full(len(veh_ids), np.nan, np.float32)
    for i, vid in enumerate(veh_ids):
        try:
            out[i] = min(float(v.getAllowedSpeed(vid)), float(v.getMaxSpeed(vid)))
        except Exception:  # noqa: BLE001 - TraCIException / libsumo error: unknown
            pass
    return out


LANE_SPEED_RATIO_MAX = 1.15  # cap of lane_speed_ratio (a vehicle as long as its curve's radius: 1.118); larger
#                             ratios are measurement noise of short, slow paths
LANE_SPEED_MIN_PATH_M = 0.5  # [m] on a shorter box-centre path the ratio is not estimated (1.0)


def lane_speed_ratio(x_m: np.ndarray, y_m: np.ndarray, speed_mps: np.ndarray, valid: np.ndarray,
                     steps: int = 5) -> np.ndarray:
    """``[A]`` SUMO's speed per box-centre speed of each vehicle over its last ``steps`` 0.1 s steps (>= 1).

    SUMO's ``getSpeed`` / ``setSpeed`` is the speed of the front bumper along its lane, and SUMO puts the rear bumper
    on the lanes behind, so the box centre (the internal frame's reference point) lies on the chord between the two,
    inside a curve. On a curve of lane radius R the centre runs on ``sqrt(R^2 - L^2 / 4)`` (measured on the bundled
    roundabout's ring: 1.0061-1.0067 for 4.4-4.6 m cars, 1.047 for 12 m buses, R = 20 m). Where the body spans a
    junction's lanes the two bumpers follow lanes of other shapes and the ratio departs from that formula, so it is
    measured here instead of computed. A policy plan is a box-centre path: commanded to SUMO unconverted, every plan
    in a curve was driven that much short, and a policy that follows its own recent speed lost speed decision after
    decision through a ring (session 48).

    From the history ``x_m, y_m, speed_mps, valid [A, T]`` (box centres [m], SUMO's speeds [m/s], last step = now,
    T >= steps + 1): the distance SUMO drove along its lanes (its speeds x 0.1 s; SUMO moves each step at its new
    speed) over the box centre's path length over the same steps. 1.0 where the history is short or invalid or the
    centre moved less than :data:`LANE_SPEED_MIN_PATH_M`; clipped to ``[1, LANE_SPEED_RATIO_MAX]``."""
    x, y, v = (np.asarray(a, np.float64) for a in (x_m, y_m, speed_mps))
    ok = np.asarray(valid, bool)
    A, T = x.shape
    if T < steps + 1:
        return np.ones(A)
    path = np.hypot(np.diff(x[:, -steps - 1:], axis=1), np.diff(y[:, -steps - 1:], axis=1)).sum(1)  # [A] [m]
    lane = np.abs(v[:, -steps:]).sum(1) * 0.1  # [A] along the lanes [m]
    use = ok[:, -steps - 1:].all(1) & (path >= LANE_SPEED_MIN_PATH_M)
    r = np.where(use, lane / np.maximum(path, 1e-9), 1.0)
    return np.clip(r, 1.0, LANE_SPEED_RATIO_MAX)


def to_sumo_pose(x_m, y_m, yaw_rad, length_m):
    """Box centre pose (internal frame) -> SUMO ``(x_fb, y_fb, angle_deg)``: front-bumper centre [m] and
    navigational angle [deg, 0 = north, clockwise, in [0, 360)]. Scalars or broadcastable arrays."""
    x_fb, y_fb = centre_to_front_bumper(x_m, y_m, yaw_rad, length_m)
    return x_fb, y_fb, yaw_rad_to_sumo_angle_deg(yaw_rad)


def move_vehicle(conn, veh_id: str, x_m: float, y_m: float, yaw_rad: float, length_m: float,
                 speed_mps: float | None = None, keep_route: int = 2) -> None:
    """Place a vehicle at a box-centre pose; SUMO applies it at the next ``simulationStep``.

    Calls ``vehicle.moveToXY(veh_id, "", -1, x_fb, y_fb, angle_deg, keep_route)`` (empty edge and lane -1:
    SUMO picks the lane) and, when ``speed_mps`` is given, ``vehicle.setPreviousSpeed`` (the speed SUMO
    holds until the step, e.g. for a vehicle not yet departed). Note: at the step SUMO *recomputes* the
    speed of a moved vehicle from the displacement (distance along the route, else straight-line) divided
    by the step length, clipped to the lane's maximum speed for that vehicle (speed limit x speedFactor);
    so ``getSpeed`` after the step reflects the motion commanded, not ``speed_mps``.

    :param keep_route: moveToXY bitset: ``KEEP_ROUTE_SNAP`` (1) keep the vehicle on its route,
        ``KEEP_ROUTE_EXACT_XY`` (2, default) exact x,y even off-road (without bit 0 the route becomes the
        single edge it is mapped to), ``KEEP_ROUTE_ANY_LANE`` (4) ignore lane permissions. 3 = exact x,y
        within 100 m of the route while keeping the route. Cost: without bit 0 SUMO searches the whole
        network for the lane; on a 9-junction grid ``moveToXY`` took ~68 us with 2 vs ~9 us with 3 or 1.
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
