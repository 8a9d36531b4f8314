"""How long the vehicles of one demand stream spend on each edge of their route, native vs the drop-in, and how many
enter each edge: where a drive loses arrivals (slower edges) or never gets the vehicles in (fewer entering the first
edge: blocked insertions, when the first edge is where they depart).

    python scripts/diag_edge_times.py --scenario sumo-game-ramp --drive native --seed 1 --stream highway
    python scripts/diag_edge_times.py --scenario sumo-game-ramp --drive commands --seed 1 --stream highway [--sampler S]

A vehicle's time on an edge [s] runs from the step it is first seen on the edge to the step it is first seen on the
next normal edge (junction-internal lanes are added to the edge before them); vehicles still on an edge at the end are
left out of that edge. Scenarios, drives and the controller's defaults as in ``scripts/diag_following_headway.py``.
"""

from __future__ import annotations

import sys
from collections import defaultdict

import numpy as np
from diag_following_headway import drop_in_parser, start_run


def run(scenario: str, drive: str, end_s: float, seed: int, checkpoint: str | None, stream: str,
        sampler: str | None = None) -> dict[str, list[float]]:
    """``{"spent": edge -> the times [s] the stream's vehicles spent on it, "last_seen_on": edge -> vehicles whose
    last edge it was}``."""
    libsumo, ctrl = start_run(scenario, drive, end_s, seed, checkpoint, sampler=sampler)
    from r1sim_sumo.sumo_launch import STEP_LENGTH_S

    enter: dict[str, tuple[str, float]] = {}  # vehicle -> (edge, time it was first seen there [s])
    spent: dict[str, list[float]] = defaultdict(list)
    try:
        for _ in range(int(round(end_s / STEP_LENGTH_S))):
            libsumo.simulationStep()
            if ctrl is not None:
                ctrl.step()
            t = libsumo.simulation.getTime()
            for v in libsumo.vehicle.getIDList():
                if not v.startswith(stream):
                    continue
                e = libsumo.vehicle.getRoadID(v)
                if e.startswith(":"):
                    continue
                prev = enter.get(v)
                if prev is None or prev[0] != e:
                    if prev is not None:
                        spent[prev[0]].append(t - prev[1])
                    enter[v] = (e, t)
    finally:
        if ctrl is not None:
            ctrl.close()
        else:
            libsumo.close()
    last: dict[str, int] = defaultdict(int)  # edge -> vehicles last seen on it (arrived from it, or still on it)
    for e, _t in enter.values():
        last[e] += 1
        spent.setdefault(e, [])
    return {"spent": dict(spent), "last_seen_on": dict(last)}


def main(argv=None) -> int:
    ap = drop_in_parser(__doc__.splitlines()[0])
    ap.add_argument("--stream", default="highway", help="vehicle id prefix of the demand stream (SUMO flow id)")
    a = ap.parse_args(argv)
    res = run(a.scenario, a.drive, a.end, a.seed, a.checkpoint, a.stream, a.sampler)
    spent, last = res["spent"], res["last_seen_on"]
    print(f"{a.scenario} {a.drive} seed {a.seed}, {a.end:g} s, stream '{a.stream}': per edge, vehicles that left it, "
          "mean / p90 time on it [s], vehicles last seen on it (arrived from it or still there)")
    for e, ts in sorted(spent.items(), key=lambda kv: -len(kv[1])):
        m = f"{np.mean(ts):6.1f} / {np.quantile(ts, 0.9):6.1f}" if ts else "     - /      -"
        print(f"  {e:14s} {len(ts):5d}  {m}  {last.get(e, 0):4d}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
