"""How far the controlled vehicles of a drop-in run turn off their lanes: at every decision, each controlled vehicle's
heading against the heading of the lane its box centre is on (the controller's heading-aware lane locator), counted
where it exceeds 30 / 45 / 60 / 90 degrees on a normal lane with the box centre more than 8 m from both lane ends
(turns into and out of junctions left out), with the vehicles it concerns.

    python scripts/diag_heading_off_lane.py --scenario roundabout --drive position --end 900 --seed 0 [--list 10]

Session 65 (docs/simulate/along_lane_s65): with the package of session 64 only the roundabout's west_left.4 (a U-turn
45 m before its route's end) and one vehicle of motorway_merge went past 45 degrees at seed 0 on the bundled networks
measured, 24 standing vehicles on game/grid6. Scenarios, drives and the controller's defaults as in
``scripts/diag_following_headway.py``.
"""

from __future__ import annotations

import sys

import numpy as np
from diag_following_headway import drop_in_parser, sampled_steps, start_run

CLEAR_M = 8.0  # [m] box centre this far from both lane ends
THRESHOLDS_DEG = (30, 45, 60, 90)


def main(argv=None) -> int:
    ap = drop_in_parser(__doc__.splitlines()[0])
    ap.add_argument("--list", type=int, default=10, help="print the first N decisions past 45 degrees")
    a = ap.parse_args(argv)
    if a.drive == "native":
        ap.error("--drive native has no controlled vehicles")
    from r1sim_sumo.geometry import wrap_angle
    from r1sim_sumo.sim.sumo_controller import SumoController

    rows = []  # (time [s], vehicle, lane, off [deg])
    check = SumoController._check_controlled

    def measured(self, states, ctrl_mask):
        ci = np.flatnonzero(ctrl_mask)
        if len(ci):
            loc = self.locator
            xy = np.stack([states.x_m[ci], states.y_m[ci]], -1)
            lane, _d, _h, along = loc.locate(xy, states.yaw_rad[ci])
            k = np.maximum(lane, 0)
            ok = (lane >= 0) & ~loc.is_internal[k] & (along > CLEAR_M) & (loc.length_m[k] - along > CLEAR_M)
            if ok.any():
                _, heading = loc.lateral_offset(k[ok], along[ok], xy[ok])
                off = np.degrees(np.abs(wrap_angle(states.yaw_rad[ci][ok] - heading)))
                for j, d in zip(np.flatnonzero(ok), off, strict=True):
                    if d > THRESHOLDS_DEG[0]:
                        rows.append((self._k * 0.1, str(states.ids[ci[j]]), loc.lane_id[k[j]], float(d)))
        return check(self, states, ctrl_mask)

    SumoController._check_controlled = measured
    libsumo, ctrl = start_run(a.scenario, a.drive, a.end, a.seed, a.checkpoint, sampler=a.sampler)
    for _ in sampled_steps(libsumo, ctrl, a.end):
        pass
    print(f"{a.scenario} {a.drive} seed {a.seed}, {a.end:g} s: controlled vehicles' heading off their lane at decisions "
          f"(normal lanes, box centre > {CLEAR_M:g} m from both ends)")
    for lo in THRESHOLDS_DEG:
        sel = [r for r in rows if r[3] > lo]
        print(f"  > {lo:3d} deg: {len(sel):5d} decisions, {len({r[1] for r in sel}):4d} vehicles")
    for t, vid, lane, d in [r for r in rows if r[3] > 45][: a.list]:
        print(f"    t={t:6.1f} s  {vid:24s} {lane:20s} {d:6.1f} deg")
    return 0


if __name__ == "__main__":
    sys.exit(main())
