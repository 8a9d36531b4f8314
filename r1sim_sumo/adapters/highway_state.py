"""highway-env vehicles <-> internal-frame vehicle states.

highway-env (``road.vehicles``): ``vehicle.position`` is the box centre [m] in a y-down screen frame,
``vehicle.heading`` [rad] in that frame (clockwise on screen, not wrapped), ``vehicle.speed`` [m/s] signed
along the heading, ``vehicle.velocity = speed * (cos heading, sin heading)`` [m/s], box ``LENGTH`` x ``WIDTH``
(defaults 5 m x 2 m). The internal frame is y-up: ``(x, y, yaw) = (x, -y_hw, -heading)`` through
:func:`r1sim_sumo.geometry.highway_to_internal` (a vehicle driving "down" the screen has negative yaw).

Stable ids: highway-env vehicles have no id. The first time :func:`read_highway_vehicles` sees a vehicle it
stores a per-road counter value on the vehicle object (attribute ``VEHICLE_ID_ATTR``), so the vehicle keeps
its id across steps, and ids never repeat within one road (one episode: ``env.reset`` builds a new road).
A vehicle replaced by a copy (``IDMVehicle.create_from``) is a new object and gets a new id unless
:func:`assign_vehicle_id` is used to carry the old one over.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from r1sim_sumo.adapters.vehicle_states import VehicleStates
from r1sim_sumo.geometry import highway_to_internal, internal_to_highway
from r1sim_sumo.scenario import VEHICLE

VEHICLE_ID_ATTR = "_r1sim_id"
_ROAD_COUNTER_ATTR = "_r1sim_next_vehicle_id"
DEFAULT_LENGTH_M = 5.0  # highway_env.vehicle.kinematics.Vehicle.LENGTH
DEFAULT_WIDTH_M = 2.0  # highway_env.vehicle.kinematics.Vehicle.WIDTH


@dataclass
class HighwayVehicleStates(VehicleStates):
    """States of ``N`` highway-env vehicles at one instant, internal frame (the fields of
    :class:`~r1sim_sumo.adapters.vehicle_states.VehicleStates`; ids are stable ids, see the module docstring, and
    ``agent_type`` is always 0 = vehicle) plus:

    :param crashed: ``[N]`` bool, highway-env's ``vehicle.crashed`` (sticky once set).
    :param on_road: ``[N]`` bool, highway-env's ``vehicle.on_road`` (centre on its current lane, lane-length margin).
    """

    crashed: np.ndarray
    on_road: np.ndarray

    @property
    def num_vehicles(self) -> int:
        return len(self)


@dataclass
class HighwayFrameStates:
    """States in highway-env's y-down frame, ready to write into vehicles.

    :param position_m: ``[N, 2]`` box centre [m] (``vehicle.position``).
    :param heading_rad: ``[N]`` heading [rad] in the y-down frame, wrapped to [-pi, pi) (``vehicle.heading``).
    :param speed_mps: ``[N]`` signed speed along the heading [m/s] (``vehicle.speed``).
    :param velocity_mps: ``[N, 2]`` velocity [m/s] in the y-down frame.
    """

    position_m: np.ndarray
    heading_rad: np.ndarray
    speed_mps: np.ndarray
    velocity_mps: np.ndarray


def assign_vehicle_id(road, vehicle, vehicle_id: str | None = None) -> str:
    """Stable id of ``vehicle``: the stored one, else ``vehicle_id`` if given, else the road's next counter."""
    vid = getattr(vehicle, VEHICLE_ID_ATTR, None)
    if vid is not None and vehicle_id is None:
        return vid
    if vehicle_id is None:
        n = int(getattr(road, _ROAD_COUNTER_ATTR, 0))
        setattr(road, _ROAD_COUNTER_ATTR, n + 1)
        vehicle_id = str(n)
    setattr(vehicle, VEHICLE_ID_ATTR, str(vehicle_id))
    return str(vehicle_id)


def read_highway_vehicles(road, vehicles=None) -> HighwayVehicleStates:
    """Read ``road.vehicles`` (or the given subset) into internal-frame arrays, assigning stable ids.

    :param road: ``env.unwrapped.road``.
    :param vehicles: optional iterable of vehicles of that road; default all of ``road.vehicles``, in order.
    """
    vs = list(road.vehicles if vehicles is None else vehicles)
    n = len(vs)
    ids = np.array([assign_vehicle_id(road, v) for v in vs], dtype=str) if n else np.zeros(0, "<U1")
    pos = np.array([v.position for v in vs], np.float64).reshape(n, 2)  # [N, 2] y-down
    heading = np.array([v.heading for v in vs], np.float64)  # [N]
    speed = np.array([v.speed for v in vs], np.float64)  # [N]
    vel = np.array([v.velocity for v in vs], np.float64).reshape(n, 2)  # [N, 2] y-down
    x, y, yaw = highway_to_internal(pos[:, 0], pos[:, 1], heading)
    vx, vy, _ = highway_to_internal(vel[:, 0], vel[:, 1], 0.0)
    return HighwayVehicleStates(
        ids=ids,
        agent_type=np.full(n, VEHICLE, np.int8),
        length_m=np.array([getattr(v, "LENGTH", DEFAULT_LENGTH_M) for v in vs], np.float64),
        width_m=np.array([getattr(v, "WIDTH", DEFAULT_WIDTH_M) for v in vs], np.float64),
        x_m=np.asarray(x, np.float64),
        y_m=np.asarray(y, np.float64),
        yaw_rad=np.asarray(yaw, np.float64),
        speed_mps=speed,
        vx_mps=np.asarray(vx, np.float64),
        vy_mps=np.asarray(vy, np.float64),
        crashed=np.array([bool(getattr(v, "crashed", False)) for v in vs], bool),
        on_road=np.array([bool(v.on_road) for v in vs], bool),
    )


def internal_to_highway_state(x_m, y_m, yaw_rad, speed_mps) -> HighwayFrameStates:
    """Internal-frame centre, yaw and signed speed ``[N]`` -> highway-env's y-down frame (inverse of the read).

    The velocity is ``speed * (cos heading, sin heading)``, as highway-env's ``Vehicle.velocity``.
    """
    x_m, y_m, yaw_rad, speed_mps = (
        np.atleast_1d(np.asarray(a, np.float64)) for a in (x_m, y_m, yaw_rad, speed_mps)
    )
    x_hw, y_hw, heading = internal_to_highway(x_m, y_m, yaw_rad)
    heading = np.asarray(heading, np.float64)
    return HighwayFrameStates(
        position_m=np.stack(
            np.broadcast_arrays(np.asarray(x_hw, np.float64), np.asarray(y_hw, np.float64)), axis=-1
        ),
        heading_rad=heading,
        speed_mps=speed_mps,
        velocity_mps=np.stack([speed_mps * np.cos(heading), speed_mps * np.sin(heading)], axis=-1),
    )
