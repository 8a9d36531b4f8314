"""Trace named vehicles of a drop-in run step by step over a time window: lane, position along it, lateral offset
(SUMO's, + = left of the lane centre) [m], x / y [m], SUMO angle [degrees clockwise from north], speed [m/s] and who
drives them. For looking at one collision event of a report (its ``collision_events`` name the pair and the time).

    python scripts/diag_pair_trace.py --scenario sumo-game-cross --drive position --seed 0 --vehicles 3_left.1 4_vertical.0 --from 64 --to 66.5

Scenarios, drives and the controller's defaults as in ``scripts/diag_following_headway.py``; every 0.2 s in the window.
"""

from __future__ import annotations

import sys

from diag_following_headway import drop_in_parser, start_run


def main(argv=None) -> int:
    ap = drop_in_parser(__doc__.splitlines()[0])
    ap.add_argument("--vehicles", nargs="+", required=True)
    ap.add_argument("--from", dest="t0", type=float, required=True, help="window start [s]")
    ap.add_argument("--to", dest="t1", type=float, required=True, help="window end [s]")
    a = ap.parse_args(argv)
    libsumo, ctrl = start_run(a.scenario, a.drive, a.t1, a.seed, a.checkpoint, sampler=a.sampler)
    v = libsumo.vehicle
    try:
        for k in range(1, int(round(a.t1 * 10)) + 1):
            libsumo.simulationStep()
            if ctrl is not None:
                ctrl.step()
            if k < round(a.t0 * 10) or k % 2:
                continue
            now = set(v.getIDList())
            for vid in a.vehicles:
                if vid not in now:
                    continue
                x, y = v.getPosition(vid)
                rec = ctrl.vehicles.get(vid) if ctrl is not None else None
                lane = v.getLaneID(vid) or "(no lane)"
                on = lane != "(no lane)"
                print(f"{k / 10:6.1f} {vid:14s} {lane:12s} pos {v.getLanePosition(vid) if on else float('nan'):6.1f} "
                      f"lat {v.getLateralLanePosition(vid) if on else float('nan'):+5.2f} xy ({x:7.1f}, {y:7.1f}) "
                      f"angle {v.getAngle(vid):6.1f} v {v.getSpeed(vid):5.2f} {rec.state if rec else 'sumo'}")
    finally:
        if ctrl is not None:
            ctrl.close()
        else:
            libsumo.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
