"""How fast a standing queue gets going in the drop-in vs under SUMO's own drivers: the start-up delay of each
follower after its leader moves off.

Every 0.1 s step: a vehicle standing (< 0.1 m/s) with a standing leader within ``--gap`` m ahead on its route
(``vehicle.getLeader``) waits in a queue; when that leader moves off (0.1 m/s) the clock starts, and when the follower
moves off too its start-up delay is the time in between [s] (a queue discharges one vehicle per delay plus the time to
clear a length, so a follower that takes 2 s where SUMO's take 1 s halves a green light's or a roundabout entry's
throughput). Samples whose follower moves first or either leaves are dropped. The delay is split by who drove the
follower when its leader moved off: ``controlled`` (the policy), ``handed_back`` (SUMO, after a standstill hand-off or
another reason) or ``sumo`` (never controlled, or a native run).

    python scripts/diag_queue_start.py --scenario sumo-game-grid6 --drive native --end 220
    python scripts/diag_queue_start.py --scenario sumo-game-grid6 --drive commands --end 220 [--checkpoint CKPT]

Scenarios: bundled network names or sumo-game-ramp / sumo-game-cross / sumo-game-grid6; drive native, commands or
position (the drop-in's defaults, ``--control all``).
"""

from __future__ import annotations

import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from diag_following_headway import drop_in_parser, start_run  # noqa: E402  (the drop-in diagnostics' common start)

STILL_MPS = 0.1  # [m/s] standing below, moved off from


def start_delays(scenario: str, drive: str, end_s: float, seed: int, checkpoint: str | None, gap_m: float) -> dict:
    """``{driver: [delay_s, ...]}`` of every queue start-up in the run (see the module docstring)."""
    libsumo, ctrl = start_run(scenario, drive, end_s, seed, checkpoint)
    v = libsumo.vehicle
    waiting: dict[str, str] = {}  # follower -> the standing leader it waits behind
    started: dict[str, tuple[str, float, str]] = {}  # follower -> (leader, time it moved off [s], follower's driver)
    out: dict[str, list[float]] = defaultdict(list)
    try:
        for _ in range(int(round(end_s / 0.1))):
            libsumo.simulationStep()
            if ctrl is not None:
                ctrl.step()
            now = float(libsumo.simulation.getTime())
            ids = v.getIDList()
            speed = {i: float(v.getSpeed(i)) for i in ids}
            for f, (lead, t0, who) in list(started.items()):  # waiting for the follower to move off
                if f not in speed or lead not in speed:
                    del started[f]
                elif speed[f] >= STILL_MPS:
                    out[who].append(now - t0)
                    del started[f]
            for f, lead in list(waiting.items()):  # waiting for the leader to move off
                if f not in speed or lead not in speed:
                    del waiting[f]
                elif speed[lead] >= STILL_MPS:  # the clock starts (a follower moving off in the same step: 0 s)
                    rec = None if ctrl is None else ctrl.vehicles.get(f)
                    who = "sumo" if rec is None else rec.state
                    if speed[f] >= STILL_MPS:
                        out[who].append(0.0)
                    else:
                        started[f] = (lead, now, who)
                    del waiting[f]
                elif speed[f] >= STILL_MPS:  # moved off before its leader: not a queue start
                    del waiting[f]
            for i in ids:
                if speed[i] >= STILL_MPS or i in waiting or i in started:
                    continue
                lead = v.getLeader(i, gap_m)
                if lead and lead[0] in speed and speed[lead[0]] < STILL_MPS:
                    waiting[i] = lead[0]
    finally:
        libsumo.close()
    return dict(out)


def main(argv=None) -> int:
    ap = drop_in_parser(__doc__.splitlines()[0])
    ap.add_argument("--gap", type=float, default=10.0, help="a standing leader within this many m ahead makes a queue")
    a = ap.parse_args(argv)
    d = start_delays(a.scenario, a.drive, a.end, a.seed, a.checkpoint, a.gap)
    allv = np.array([x for xs in d.values() for x in xs])
    label = a.drive if a.drive == "native" else f"{a.drive} ({a.checkpoint or 'r1sim-nano'})"
    print(f"{a.scenario} {label}, {a.end:.0f} s, seed {a.seed}: {len(allv)} queue start-ups")
    print("  follower's driver: start-ups | start-up delay [s] mean, p25, median, p75, p90 | share > 2 s")
    for who, xs in sorted(d.items(), key=lambda kv: -len(kv[1])) + [("all", list(allv))]:
        x = np.asarray(xs)
        if len(x):
            p = np.percentile(x, [25, 50, 75, 90])
            print(f"    {who:12s} {len(x):6d} | {x.mean():5.2f} {p[0]:5.2f} {p[1]:5.2f} {p[2]:5.2f} {p[3]:5.2f} | "
                  f"{(x > 2.0).mean():5.1%}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
