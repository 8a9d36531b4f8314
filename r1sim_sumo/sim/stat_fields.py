"""Fields of the simulation counters (:class:`~r1sim_sumo.sim.sumo_controller.ControllerStats`,
:class:`~r1sim_sumo.sim.highway_vehicle.CoordinatorStats`), each carrying what it counts and in which unit.

A counter declared as ``arrived: int = count("vehicles that completed their route", "vehicles")`` keeps its meaning next to its
value at run time: :func:`legend` turns a stats class into ``{name: "meaning [unit]"}``, which ``r1sim simulate
--json`` writes beside the numbers so a reader of the JSON file does not need the source to know that
``time_policy_s`` is wall seconds and ``vkm_all`` vehicle-kilometres.
"""

from __future__ import annotations

import dataclasses
from collections import Counter

__all__ = ["amount", "count", "label", "legend", "listing", "tally"]


def count(meaning: str, unit: str):
    """An integer counter starting at 0, counting ``unit`` (``"vehicles"``, ``"events"``, ``"vehicle-steps"``: one
    vehicle for one 0.1 s step, ...)."""
    return dataclasses.field(default=0, metadata={"meaning": meaning, "unit": unit})


def amount(meaning: str, unit: str):
    """A float accumulator starting at 0.0, in ``unit`` (``"s"`` wall or simulated seconds, ``"km"``, ...)."""
    return dataclasses.field(default=0.0, metadata={"meaning": meaning, "unit": unit})


def tally(meaning: str, unit: str):
    """A :class:`collections.Counter` of events by kind, e.g. ``unit="vehicles by reason"``."""
    return dataclasses.field(default_factory=Counter, metadata={"meaning": meaning, "unit": unit})


def listing(meaning: str, unit: str):
    """A list of identifiers, e.g. ``unit="vehicle ids"``, empty at the start."""
    return dataclasses.field(default_factory=list, metadata={"meaning": meaning, "unit": unit})


def label(meaning: str, unit: str):
    """A string describing the run (mode, drive, ...), empty at the start; ``unit`` names its values."""
    return dataclasses.field(default="", metadata={"meaning": meaning, "unit": unit})


def legend(stats) -> dict[str, str]:
    """``{field name: "meaning [unit]"}`` of a stats dataclass (class or instance), in declaration order.

    Raises ``TypeError`` naming the field when one was declared without :func:`count`, :func:`amount`, ... (it
    would have no meaning to print)."""
    out = {}
    for f in dataclasses.fields(stats):
        if "meaning" not in f.metadata:
            raise TypeError(f"{getattr(stats, '__name__', type(stats).__name__)}.{f.name}: declare it with "
                            "r1sim_sumo.sim.stat_fields.count/amount/tally/listing/label so that it has a meaning")
        out[f.name] = f"{f.metadata['meaning']} [{f.metadata['unit']}]"
    return out
