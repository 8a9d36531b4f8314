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

__version__ = "0.1.0"

from r1sim_sumo.scenario import AgentTracks, MapPolylines, Scenario  # noqa: E402

__all__ = ["__version__", "Scenario", "AgentTracks", "MapPolylines", "load_policy"]


def load_policy(name_or_path: str | None = None, device: str = "cpu"):
    """Load a policy checkpoint: ``None`` = the shipped default, a bundled name, or a directory path."""
    from r1sim_sumo.model.checkpoint import load_policy as _load

    return _load(name_or_path, device=device)
