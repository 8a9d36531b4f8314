"""Input ablations for diagnostics: the drop-in's policy sees its map without (some of) the road edges, or with
junction curbs added.

Any ``r1sim`` command run with this folder on ``PYTHONPATH`` and ``R1SIM_DROP_ROAD_EDGES`` set builds every
:class:`~r1sim_sumo.sim.policy_driver.PolicyDriver` from the map minus the road-edge polylines chosen there: ``all``,
or a comma-separated list of parts of their SUMO ids (``<edge>#left`` / ``#right``; e.g. ``_in#,_out#``). SUMO's
network and the controller's lane bookkeeping are unchanged. The model was trained with road edges, so this asks
which input a behaviour comes from; it is not a way to run the policy. ::

    PYTHONPATH=scripts/policy_map_ablation R1SIM_DROP_ROAD_EDGES=all python examples/full_horizon_runs.py \\
        --out runs/no_road_edges --modes native commands --reuse native --scenarios roundabout sumo-game-ramp

``R1SIM_JUNCTION_CURBS=1`` adds road edges around every junction: SUMO's maps have none across a junction, so the
road edges of each approach end at the junction mouth. The outline of each junction's shape (``<junction shape=...>``)
becomes road-edge polylines, minus its mouths: outline segments longer than :data:`MOUTH_MIN_M` whose middle lies
within :data:`MOUTH_NEAR_M` of the end of a lane that enters or leaves the junction. A heuristic for the bundled
networks' junctions, for asking whether the edges' ends are what the policy stops at.

(``scripts/diag_roundabout_entry.py --drop-road-edges / --junction-curbs`` call these functions directly.)
"""

from __future__ import annotations

import os

MOUTH_MIN_M = 3.0  # [m] outline segments at least this long may be a mouth (curb segments are shorter)
MOUTH_NEAR_M = 3.0  # [m] ... when their middle is this close to the end of a lane entering or leaving the junction


def junction_curbs(net_file: str) -> list:
    """Curb polylines ``[n, 2]`` [m, the network's frame] of every junction of ``net_file`` (see the module text)."""
    import numpy as np
    import sumolib

    net = sumolib.net.readNet(net_file, withInternal=False)
    curbs = []
    for node in net.getNodes():
        shape = np.asarray(node.getShape(), float)[:, :2]
        if len(shape) < 3:
            continue
        ends = [np.asarray(lane.getShape()[-1][:2]) for e in node.getIncoming() for lane in e.getLanes()]
        ends += [np.asarray(lane.getShape()[0][:2]) for e in node.getOutgoing() for lane in e.getLanes()]
        ring = np.vstack([shape, shape[:1]])
        keep = []
        for a, b in zip(ring[:-1], ring[1:], strict=True):
            mid = (a + b) / 2
            mouth = np.linalg.norm(b - a) >= MOUTH_MIN_M and any(np.linalg.norm(mid - q) <= MOUTH_NEAR_M for q in ends)
            keep.append(not mouth)
        start = keep.index(False) if False in keep else 0  # walk the outline from a mouth so that chains do not wrap
        chain: list = []
        for k in range(len(keep)):
            i = (start + k) % len(keep)
            if keep[i]:
                chain = chain or [ring[i]]
                chain.append(ring[i + 1])
            elif chain:
                curbs.append(np.asarray(chain))
                chain = []
        if chain:
            curbs.append(np.asarray(chain))
    return [c for c in curbs if np.linalg.norm(np.diff(c, axis=0), axis=1).sum() > 0.5]  # dead ends: no outline


def add_junction_curbs_to_policy_map(net_file: str | None = None) -> None:
    """Make every :class:`PolicyDriver` built from here on see its map plus :func:`junction_curbs` of ``net_file``
    (default: the network SUMO runs, asked from libsumo as the controller does). The host's traffic-light states
    (one row per polyline of its own map) get a "no signal" row per curb."""
    import numpy as np

    import r1sim_sumo.sim.policy_driver as policy_driver
    from r1sim_sumo.scenario import TL_NONE, MapPolylines

    build = policy_driver.PolicyDriver

    def with_curbs(policy, road_map, *args, **kwargs):
        if net_file is None:
            import libsumo  # not at start-up: importing libsumo sets SUMO_HOME to its own data folder (no tools/game)

        curbs = junction_curbs(net_file or libsumo.simulation.getOption("net-file"))
        m = road_map
        polys = [m.polyline(i) for i in range(m.num_polylines)] + curbs
        n = len(curbs)
        tl = np.vstack([m.tl_state, np.zeros((n, m.tl_state.shape[1]), np.int8)])
        road_map = MapPolylines.from_lists(polys, [*m.kind, *[1] * n], [*m.lane_id, *[f"junction#curb{k}" for k in range(n)]],
                                           [*m.speed_limit_mps, *[0.0] * n], [*m.width_m, *[0.0] * n], tl, m.successors)
        print(f"policy map: {n} junction curb polylines added")
        driver = build(policy, road_map, *args, **kwargs)
        plan = driver.plan

        def plan_with_curb_rows(hist, tl=None, *a, **kw):  # the host's signal states have a row per map polyline
            if tl is not None and len(tl) == m.num_polylines:  # of its own map: the curbs read "no signal"
                tl = np.concatenate([np.asarray(tl), np.full((n, *np.shape(tl)[1:]), TL_NONE, np.asarray(tl).dtype)])
            return plan(hist, tl, *a, **kw)

        driver.plan = plan_with_curb_rows
        return driver

    policy_driver.PolicyDriver = with_curbs


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


if os.environ.get("R1SIM_JUNCTION_CURBS"):
    add_junction_curbs_to_policy_map()
if os.environ.get("R1SIM_DROP_ROAD_EDGES"):
    drop_road_edges_from_policy_map(os.environ["R1SIM_DROP_ROAD_EDGES"].split(","))
