"""read_vehicle_states caches sizes by vehicle type id: a later simulation in the same process reusing a type id with
another size must not get the old size (the cause of a SUMO-in-the-loop flag differing between backends)."""

from __future__ import annotations

import pytest

from r1sim_sumo._sumo_env import ensure_sumo_home, sumo_binary
from r1sim_sumo.adapters.sumo_state import clear_static_cache, read_vehicle_states
from r1sim_sumo.resources import network_files

pytestmark = pytest.mark.sumo
ensure_sumo_home()
import libsumo  # noqa: E402


def _run_with_car_length(length_m: float, begin_s: float, before_read=None) -> float:
    libsumo.start([sumo_binary("sumo"), "-n", str(network_files("motorway_merge")["net"]), "--step-length", "0.1",
                   "--begin", str(begin_s), "--no-step-log", "true", "--no-warnings", "true"])
    try:
        if before_read is not None:
            before_read()
        libsumo.vehicletype.copy("DEFAULT_VEHTYPE", "car")
        libsumo.vehicletype.setLength("car", length_m)
        libsumo.route.add("r", ["main_in", "merge", "main_out"])
        libsumo.vehicle.add("v0", "r", typeID="car", departPos="50", departSpeed="10")
        libsumo.simulationStep()
        return float(read_vehicle_states(libsumo).length_m[0])
    finally:
        libsumo.close()


def test_a_new_simulation_with_the_same_type_id_reads_its_own_sizes():
    assert _run_with_car_length(4.0, 0.0) == pytest.approx(4.0)
    # the second simulation starts later than the first ended, so the time check alone keeps the 4 m entry
    clear_static_cache(libsumo)
    assert _run_with_car_length(12.0, 100.0) == pytest.approx(12.0)


def test_a_new_controller_forgets_the_sizes_of_an_earlier_simulation():
    from r1sim_sumo.model.untrained import untrained_policy
    from r1sim_sumo.sim.sumo_controller import SumoController

    assert _run_with_car_length(4.0, 0.0) == pytest.approx(4.0)
    assert _run_with_car_length(12.0, 100.0, lambda: SumoController(libsumo, untrained_policy(0))) == pytest.approx(12.0)
