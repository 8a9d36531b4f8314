"""Why the position drive's safety layer holds a vehicle below its plan's speed: by which cap, and whether the
filter's leader is the vehicle SUMO sees ahead on the lane (``vehicle.getLeader``).

    python docs/simulate/filter_holds_s55/diag_filter_holds.py --scenario sumo-game-ramp --end 200 [--seed 0]

Runs the position drive (safety layer on, the drive's defaults, the shipped r1sim-nano) and at every 0.1 s step counts
the controlled vehicle-steps whose allowed speed is more than 0.1 m/s below the plan's, by the cap that binds: the
Krauss safe speed behind the filter's leader (split by whether SUMO's own leader within 100 m is that vehicle, another
one, or none), the stop-line speed (red light / yield), or the type's acceleration / max speed. Units: m/s, m.
"""
from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "scripts"))
from diag_following_headway import drop_in_parser, sampled_steps, start_run  # noqa: E402


def main(argv=None) -> int:
    ap = drop_in_parser(__doc__.splitlines()[0])
    ap.set_defaults(drive="position", end=200.0)
    a = ap.parse_args(argv)
    lib, ctrl = start_run(a.scenario, "position", a.end, a.seed, a.checkpoint, sampler=a.sampler)
    sf = ctrl.safety
    kinds: Counter = Counter()
    gaps: dict[str, list[float]] = {"same": [], "other_lane": [], "sumo_none": []}
    total = [0]
    orig = ctrl._allowed_speeds

    def wrapped(states, vids, slots):
        allowed, floor = orig(states, vids, slots)
        rows = ctrl._row_of_slot[slots]
        v_plan = ctrl.follower.plan_speed(slots, 0.1)
        known = rows >= 0
        gap, v_lead, lead = sf.leader_gap(rows[known], states.x_m, states.y_m, states.yaw_rad, states.length_m,
                                          states.width_m, states.speed_mps, ctrl.follower.kappa[slots[known]])
        g_all = np.full(len(slots), np.inf)
        l_all = np.full(len(slots), -1)
        g_all[known], l_all[known] = gap, lead
        v_now = states.speed_mps[np.maximum(rows, 0)]
        lim = ctrl._limits[slots]
        acc = np.where(np.isnan(lim[:, 1]), np.inf, lim[:, 1])
        vmax = np.where(np.isnan(lim[:, 0]), np.inf, lim[:, 0])
        v_cap = np.minimum(vmax, v_now + acc * 0.1)
        total[0] += len(slots)
        for i in np.flatnonzero(allowed < v_plan - 0.1):
            vid = vids[i]
            stop = ctrl._stop_m[slots[i]] - ctrl.follower.prog_m[slots[i]]
            if allowed[i] >= v_cap[i] - 0.05:
                kinds["type accel / max speed"] += 1
            elif l_all[i] >= 0:
                try:
                    sl = lib.vehicle.getLeader(vid, 100.0)
                except Exception:  # noqa: BLE001
                    sl = None
                fl = str(states.ids[l_all[i]])
                if sl and sl[0] == fl:
                    kinds["Krauss: SUMO's leader"] += 1
                    gaps["same"].append(g_all[i])
                elif sl and sl[0]:
                    kinds["Krauss: another vehicle than SUMO's leader"] += 1
                    gaps["other_lane"].append(g_all[i])
                else:
                    kinds["Krauss: SUMO sees no leader within 100 m"] += 1
                    gaps["sumo_none"].append(g_all[i])
            elif np.isfinite(stop):
                kinds["stop line (red / yield)"] += 1
            else:
                kinds["other"] += 1
        return allowed, floor

    ctrl._allowed_speeds = wrapped
    for _ in sampled_steps(lib, ctrl, a.end):
        pass
    held = sum(kinds.values())
    print(f"{a.scenario} position seed {a.seed}, {a.end:g} s: {total[0]} controlled vehicle-steps, {held} held "
          f"({held / max(total[0], 1):.1%})")
    for k, n in kinds.most_common():
        print(f"  {k:45s} {n:7d}  {n / max(held, 1):.1%}")
    for k, g in gaps.items():
        if g:
            print(f"  filter gap [m] when {k}: median {np.median(g):.1f}, 10% {np.quantile(g, 0.1):.1f}, 90% {np.quantile(g, 0.9):.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
