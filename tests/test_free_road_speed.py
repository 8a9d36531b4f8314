"""The free-road speed share of the drop-in report: SUMO's own drivers on an open motorway are near their desired
speed, drivers told to go at half of it show about half, and a vehicle with a reason to be slower is not counted."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from r1sim_sumo._sumo_env import ensure_sumo_home, sumo_binary
from r1sim_sumo.resources import network_files
from r1sim_sumo.sim.free_road_speed import FREE_LOOK_M, FreeRoadSpeed
from r1sim_sumo.sim.sumo_controller import ControllerStats

ensure_sumo_home()
import libsumo  # noqa: E402

SUMO_OPTS = ["--no-step-log", "true", "--no-warnings", "true", "--time-to-teleport", "-1", "--seed", "0"]


def _share(slow_factor: float | None, seconds: float = 120.0) -> ControllerStats:
    """Native lane_drop run; with ``slow_factor`` every vehicle is told (setSpeed) to drive that share of its desired
    speed from its insertion on."""
    libsumo.start([sumo_binary("sumo"), "-c", str(network_files("lane_drop")["sumocfg"]), "--step-length", "0.1",
                   "--end", str(seconds + 1), *SUMO_OPTS])
    try:
        stats, fr = ControllerStats(), FreeRoadSpeed(libsumo)
        for _ in range(int(seconds / 0.1)):
            libsumo.simulationStep()
            if slow_factor is not None:
                for vid in libsumo.simulation.getDepartedIDList():
                    want = min(libsumo.vehicle.getAllowedSpeed(vid), libsumo.vehicle.getMaxSpeed(vid))
                    libsumo.vehicle.setSpeed(vid, slow_factor * want)
            fr.step(stats, libsumo.vehicle.getIDList)
        return stats
    finally:
        libsumo.close()


@pytest.mark.sumo
def test_sumo_drivers_near_their_desired_speed_and_slow_drivers_at_half():
    native = _share(None).summary()
    slow = _share(0.5).summary()
    assert native["free_road_samples"] > 200 and slow["free_road_samples"] > 200
    assert 0.85 <= native["free_road_speed_share"] <= 1.05
    # lane limit x speedFactor changes along lane_drop, setSpeed was once: the share stays near one half
    assert 0.4 <= slow["free_road_speed_share"] <= 0.6


class FakeVehicle:
    """One vehicle ``v`` on lane ``e_0`` (200 m long, 30 m/s limit) at ``pos`` [m], with the given surroundings."""

    def __init__(self, lane="e_0", pos=20.0, leader=None, tls=(), links=(("f_0", "", True, True, False, "M", "s", 0.0),)):
        self.lane, self.pos, self.leader, self.tls, self.links = lane, pos, leader, list(tls), list(links)

    def conn(self):
        veh = SimpleNamespace(getLaneID=lambda v: self.lane, getLeader=lambda v, d: self.leader,
                              getNextTLS=lambda v: self.tls, getLanePosition=lambda v: self.pos,
                              getNextLinks=lambda v: self.links)
        lane = SimpleNamespace(getLength=lambda ln: 200.0, getMaxSpeed=lambda ln: {"e_0": 30.0, "f_0": 30.0, "g_0": 15.0}[ln])
        return SimpleNamespace(vehicle=veh, lane=lane)


@pytest.mark.parametrize("surroundings, free", [
    ({}, True),
    ({"leader": ("w", FREE_LOOK_M - 1.0)}, False),  # someone ahead
    ({"leader": ("w", FREE_LOOK_M + 5.0)}, True),  # far ahead
    ({"leader": ("", -1.0)}, True),  # SUMO's "no leader"
    ({"tls": [("J1", 0, 60.0, "r")]}, False),  # a signal ahead
    ({"lane": ":J1_0_0"}, False),  # inside a junction
    ({"pos": 150.0}, True),  # near the lane end, straight on with priority onto an as-fast lane
    ({"pos": 150.0, "links": [("f_0", "", True, True, False, "M", "r", 0.0)]}, False),  # a right turn
    ({"pos": 150.0, "links": [("f_0", "", False, True, True, "m", "s", 0.0)]}, False),  # no priority: may yield
    ({"pos": 150.0, "links": [("g_0", "", True, True, False, "M", "s", 0.0)]}, False),  # a slower road ahead
    ({"pos": 150.0, "links": []}, False),  # the end of its route
])
def test_what_counts_as_a_free_road(surroundings, free):
    assert FreeRoadSpeed(FakeVehicle(**surroundings).conn()).is_free("v") is free


def test_samples_every_half_second_and_only_free_vehicles():
    fake = FakeVehicle()
    conn = fake.conn()
    conn.vehicle.getAllowedSpeed = lambda v: 30.0
    conn.vehicle.getMaxSpeed = lambda v: 50.0
    conn.vehicle.getSpeed = lambda v: 15.0
    stats, fr = ControllerStats(), FreeRoadSpeed(conn)
    asked = []
    for _ in range(10):
        fr.step(stats, lambda: asked.append(1) or ["v"])
    assert len(asked) == 2 and stats.free_road_samples == 2  # steps 5 and 10
    assert np.isclose(stats.summary()["free_road_speed_share"], 0.5)
    fake.leader = ("w", 10.0)
    for _ in range(5):
        fr.step(stats, lambda: ["v"])
    assert stats.free_road_samples == 2
