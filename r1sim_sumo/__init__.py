"""r1sim-sumo: a learned, tokenized traffic policy driving the background vehicles of SUMO and highway-env.

Data flows one way: simulator -> adapter -> Scenario/tensors -> tokenizer -> model -> sampler -> actions ->
adapter -> simulator. Internal frame everywhere: metres, x east, y north, yaw in radians counter-clockwise
from +x, position = box centre, 10 Hz states.
"""

from __future__ import annotations

import os as _os

# OpenMP threads that spin while waiting make 2-thread torch steps 5-10x slower on shared CPUs (measured:
# 110-330 ms vs 12-21 ms per policy step). Takes effect when r1sim_sumo is imported before torch; users can
# override it by setting the variable themselves.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

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
