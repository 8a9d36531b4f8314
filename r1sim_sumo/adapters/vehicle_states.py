"""States of the vehicles of a simulator at one instant, as the adapters read them (internal frame)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class VehicleStates:
    """States of ``N`` vehicles at one instant (internal frame: metres, x east, y north, box centres).

    :param ids: ``[N]`` str simulator ids (SUMO vehicle id, highway-env stable id).
    :param agent_type: ``[N]`` int8, 0 vehicle / 1 cyclist / 2 pedestrian.
    :param length_m, width_m: ``[N]`` float64 box size [m].
    :param x_m, y_m: ``[N]`` float64 box centre [m]; ``yaw_rad`` ``[N]`` [rad, CCW from east, in [-pi, pi)].
    :param speed_mps: ``[N]`` float64 signed speed along the heading [m/s]; ``vx_mps, vy_mps`` ``[N]`` velocity [m/s].
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
