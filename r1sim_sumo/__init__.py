"""r1sim-sumo: a learned, tokenized traffic policy driving the background vehicles of SUMO and highway-env.

Data flows one way: simulator -> adapter -> Scenario/tensors -> tokenizer -> model -> sampler -> actions ->
adapter -> simulator. Internal frame everywhere: metres, x east, y north, yaw in radians counter-clockwise
from +x, position = box centre, 10 Hz states.
"""

from __future__ import annotations

import os as _os

# How torch's OpenMP workers wait between parallel ops. Spinning without bound (libgomp's default 300k spins, or
# ACTIVE) made 2-thread torch steps 5-10x slower on shared CPUs (measured: 110-330 ms vs 12-21 ms per policy step),
# so workers wait passively; but sleeping workers must be woken for every op, and a policy step is ~500 small ops:
# on an idle 2-core Intel Xeon (session 26) a 700-agent drop-in decision took 83 ms on 2 threads, no faster than on
# one (82 ms). A short bounded spin first (GOMP_SPINCOUNT=10000, GNU OpenMP as in the PyPI torch wheels: tens of
# microseconds) catches the next op: 55 ms there; on a CPU shared with two other busy processes it cost ~25%
# (117-136 -> 152-165 ms per decision). `python benchmarks/run.py --only sumo_controller`, README "Speed". Both take
# effect when r1sim_sumo is imported before torch; set OMP_WAIT_POLICY (and GOMP_SPINCOUNT) yourself to override
# (GOMP_SPINCOUNT=0 with PASSIVE: never spin, for an over-subscribed CPU).
if "OMP_WAIT_POLICY" not in _os.environ:
    _os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
    _os.environ.setdefault("GOMP_SPINCOUNT", "10000")

from r1sim_sumo._version import __version__  # noqa: E402
from r1sim_sumo.scenario import AgentTracks, MapPolylines, Scenario  # noqa: E402

__all__ = ["__version__", "Scenario", "AgentTracks", "MapPolylines", "load_policy"]


def __getattr__(name: str):
    """``r1sim_sumo.load_policy`` is :func:`r1sim_sumo.model.checkpoint.load_policy`, imported on first use: it
    needs torch, which takes ~2.7 s to import (measured on this machine) while ``import r1sim_sumo`` takes ~0.2 s
    (``r1sim --help``, the simulator adapters)."""
    if name == "load_policy":
        from r1sim_sumo.model.checkpoint import load_policy

        return load_policy
    raise AttributeError(f"module 'r1sim_sumo' has no attribute {name!r}")
