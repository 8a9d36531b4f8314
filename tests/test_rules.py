"""``rules.stop_distance``: where the position drive's safety layer stops a vehicle (signals, minor links, a
junction it could not leave), read from SUMO's answers (a stand-in connection here, so each answer is chosen)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

from r1sim_sumo.sim.rules import stop_distance

LANE_M, POS_M = 150.0, 130.0  # the vehicle's lane length and its front bumper's position on it: 20 m to the line


def _conn(links, tls=(), standing_after=()):
    """A connection whose vehicle ``v`` is on ``south_in_0`` 20 m before its stop line, with next ``links`` (tuples as
    ``vehicle.getNextLinks`` gives them), signals ``tls`` and standing vehicles at the start of the lane after."""
    lengths = {"south_in_0": LANE_M, ":ring_south_0_0": 8.0, "ring_south_east_0": 30.0}
    vehicle = SimpleNamespace(
        getNextTLS=lambda vid: list(tls), getLaneID=lambda vid: "south_in_0",
        getLanePosition=lambda vid: POS_M if vid == "v" else 3.0 + 5.0,
        getLength=lambda vid: 5.0, getNextLinks=lambda vid: list(links),
        getSpeed=lambda vid: 0.0)
    lane = SimpleNamespace(getLength=lambda lane_id: lengths[lane_id],
                           getLastStepVehicleIDs=lambda lane_id: list(standing_after) if lane_id == "ring_south_east_0" else [])
    return SimpleNamespace(vehicle=vehicle, lane=lane)


def _minor_link(is_open: bool, has_foe: bool, prio: bool = False, state: str = "m"):
    # (approached lane, has priority, is open, has foe, via lane, state, direction, length)
    return ("ring_south_east_0", prio, is_open, has_foe, ":ring_south_0_0", state, "r", 8.0)


@pytest.mark.parametrize(("is_open", "has_foe", "prio", "stops"), [
    (False, True, False, True),  # SUMO finds the minor link closed for it: yield at the line
    (False, False, False, True),
    (True, True, False, False),  # open, a foe approaching: a gap SUMO's own drivers take (session 61)
    (True, False, False, False),
    (False, True, True, False),  # a link with priority: never yields
])
def test_a_vehicle_yields_at_a_minor_link_where_sumo_finds_it_closed(is_open, has_foe, prio, stops):
    d, why = stop_distance(_conn([_minor_link(is_open, has_foe, prio)]), "v", 8.0, 4.5, 100.0)
    if stops:
        assert why == "yield" and d == pytest.approx(LANE_M - POS_M)
    else:
        assert why == "" and math.isinf(d)


def test_a_red_signal_stops_before_a_link_and_a_full_exit_blocks_it():
    d, why = stop_distance(_conn([_minor_link(True, False)], tls=[("tls", 0, 12.0, "r")]), "v", 8.0, 4.5, 100.0)
    assert (d, why) == (12.0, "red")
    # open link, but the lane behind the junction starts with a standing car (back bumper 3 m in): no room for 7.5 m
    d, why = stop_distance(_conn([_minor_link(True, False)], standing_after=["w"]), "v", 8.0, 4.5, 100.0)
    assert why == "blocked" and d == pytest.approx(LANE_M - POS_M)
