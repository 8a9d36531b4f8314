"""Input ablation for diagnostics: the drop-in's policy sees its map without (some of) the road edges.

Any ``r1sim`` command run with this folder on ``PYTHONPATH`` and ``R1SIM_DROP_ROAD_EDGES`` set builds every
:class:`~r1sim_sumo.sim.policy_driver.PolicyDriver` from the map minus the road-edge polylines chosen there: ``all``,
or a comma-separated list of parts of their SUMO ids (``<edge>#left`` / ``#right``; e.g. ``_in#,_out#``). SUMO's
network and the controller's lane bookkeeping are unchanged. The model was trained with road edges, so this asks
which input a behaviour comes from; it is not a way to run the policy. ::

    PYTHONPATH=scripts/policy_map_ablation R1SIM_DROP_ROAD_EDGES=all python examples/full_horizon_runs.py \\
        --out runs/no_road_edges --modes native commands --reuse native --scenarios roundabout sumo-game-ramp

(``scripts/diag_roundabout_entry.py --drop-road-edges`` calls :func:`drop_road_edges_from_policy_map` directly.)
"""

from __future__ import annotations

import os


def drop_road_edges_from_policy_map(parts: list[str]) -> None:
    """Make every :class:`PolicyDriver` built from here on see its map without the road edges whose id contains one
    of ``parts`` (every road edge with ``"all"``)."""
    import numpy as np

    import r1sim_sumo.sim.policy_driver as policy_driver

    build = policy_driver.PolicyDriver

    def without_edges(policy, road_map, *args, **kwargs):
        ids = road_map.lane_id.astype(str)
        drop = (road_map.kind == 1) & np.array(["all" in parts or any(p in i for p in parts) for i in ids], bool)
        print(f"policy map: {int(drop.sum())} of {int((road_map.kind == 1).sum())} road edges left out")
        return build(policy, road_map.select(~drop), *args, **kwargs)

    policy_driver.PolicyDriver = without_edges


if os.environ.get("R1SIM_DROP_ROAD_EDGES"):
    drop_road_edges_from_policy_map(os.environ["R1SIM_DROP_ROAD_EDGES"].split(","))
