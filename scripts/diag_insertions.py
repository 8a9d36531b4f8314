"""Insertions per demand flow, native vs the drop-in: how many vehicles of each flow got into the network, how late
(SUMO's depart delay), and how many were still waiting to be inserted at the end, with the most waiting per 50 s.

    python scripts/diag_insertions.py --scenario sumo-game-ramp --drive native --seed 0 --end 400
    python scripts/diag_insertions.py --scenario sumo-game-ramp --drive commands --seed 0 --end 400 [--sampler S]

Both runs see the same demand: a flow's vehicle ``f.k`` is due at the same time in every drive (the due time, insertion
time minus depart delay, is printed as a check when ``--compare`` names another run's ``--json`` output). Scenarios,
drives and the controller's defaults as in ``scripts/diag_following_headway.py``.
"""

from __future__ import annotations

import json
import sys
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
from diag_following_headway import drop_in_parser, sampled_steps, start_run

WINDOW_S = 50.0  # [s] the most vehicles waiting to insert is reported per window of this length


def flow_of(veh_id: str) -> str:
    """SUMO names a flow's vehicles ``<flow id>.<k>``."""
    return veh_id.rsplit(".", 1)[0]


def run(scenario: str, drive: str, end_s: float, seed: int, checkpoint: str | None, sampler: str | None = None) -> dict:
    """``{"departed": id -> [insertion time, depart delay] [s], "waiting_at_end": [ids], "max_waiting": {window start
    [s]: most vehicles waiting to insert}}``."""
    libsumo, ctrl = start_run(scenario, drive, end_s, seed, checkpoint, sampler=sampler)
    departed: dict[str, list[float]] = {}
    max_waiting: dict[float, int] = defaultdict(int)
    waiting: list[str] = []
    for _ in sampled_steps(libsumo, ctrl, end_s, every=1):
        t = libsumo.simulation.getTime()
        for v in libsumo.simulation.getDepartedIDList():
            departed[v] = [round(t, 1), round(libsumo.vehicle.getDepartDelay(v), 1)]
        waiting = list(libsumo.simulation.getPendingVehicles())
        w = WINDOW_S * int(t // WINDOW_S)
        max_waiting[w] = max(max_waiting[w], len(waiting))
    return {"departed": departed, "waiting_at_end": waiting, "max_waiting": dict(max_waiting)}


def main(argv=None) -> int:
    ap = drop_in_parser(__doc__.splitlines()[0])
    ap.add_argument("--json", default=None, help="write the run's insertions here")
    ap.add_argument("--compare", default=None, help="another run's --json: check both saw the same due times")
    a = ap.parse_args(argv)
    res = run(a.scenario, a.drive, a.end, a.seed, a.checkpoint, a.sampler)
    dep, waiting = res["departed"], res["waiting_at_end"]
    by_flow: dict[str, list[float]] = defaultdict(list)
    for v, (_t, delay) in dep.items():
        by_flow[flow_of(v)].append(delay)
    still = Counter(flow_of(v) for v in waiting)
    print(f"{a.scenario} {a.drive} seed {a.seed}, {a.end:g} s: per flow, vehicles inserted, mean / max depart delay [s], "
          "still waiting to insert at the end")
    for f in sorted(set(by_flow) | set(still)):
        d = by_flow.get(f, [])
        m = f"{np.mean(d):6.2f} / {np.max(d):6.1f}" if d else "     - /      -"
        print(f"  {f:12s} {len(d):5d}  {m}  {still.get(f, 0):4d}")
    print(f"  total        {len(dep):5d}  waiting at the end {len(waiting)}")
    print("  most waiting to insert per " + f"{WINDOW_S:g} s: "
          + ", ".join(f"{w:g}-{w + WINDOW_S:g}: {n}" for w, n in sorted(res["max_waiting"].items())))
    if a.compare:
        other = json.loads(Path(a.compare).read_text())["departed"]
        common = set(dep) & set(other)
        same = sum(abs((dep[v][0] - dep[v][1]) - (other[v][0] - other[v][1])) < 0.15 for v in common)
        print(f"  due times equal to {a.compare}'s for {same} of the {len(common)} vehicles both inserted")
    if a.json:
        Path(a.json).write_text(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
