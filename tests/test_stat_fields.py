"""The simulation counters carry their meaning and unit (r1sim_sumo.sim.stat_fields)."""

from collections import Counter
from dataclasses import dataclass, fields

import pytest

from r1sim_sumo.sim.highway_vehicle import CoordinatorStats
from r1sim_sumo.sim.stat_fields import amount, count, legend, tally
from r1sim_sumo.sim.sumo_controller import ControllerStats


@pytest.mark.parametrize("cls", [ControllerStats, CoordinatorStats])
def test_every_counter_has_a_meaning_and_a_unit(cls):
    text = legend(cls)
    assert list(text) == [f.name for f in fields(cls)]
    for name, line in text.items():
        meaning, _, unit = line.rpartition(" [")
        assert meaning and unit.endswith("]") and len(unit) > 1, (name, line)


def test_fields_start_empty_and_independent():
    a, b = ControllerStats(), ControllerStats()
    a.handbacks["stuck"] += 1
    a.arrived += 2
    assert b.handbacks == Counter() and b.arrived == 0 and b.drive == ""
    assert a.summary()["handbacks"] == {"stuck": 1} and a.summary()["arrived"] == 2
    assert ControllerStats(drive="commands").drive == "commands"


def test_a_field_without_meaning_is_named_in_the_error():
    @dataclass
    class Stats:
        seen: int = count("things seen", "things")
        took_s: float = amount("time taken", "s")
        kinds: Counter = tally("things by kind", "things by kind")
        bare: int = 0

    with pytest.raises(TypeError, match=r"Stats\.bare: declare it with"):
        legend(Stats)

