"""How fast vehicles speed up when they have room to, in traffic: the policy's plans (position drive) vs SUMO's drivers
(native), same scenario and seed.

    python docs/simulate/filter_holds_s55/diag_room_acceleration.py --scenario motorway_merge --end 300 --drive position|native

Every 0.5 s, a vehicle (the policy's in the position drive, every one in native) *has room* when it is on a normal lane
at least 3 m/s below its desired speed (``vehicle.getAllowedSpeed``), with no signal within 100 m, and its leader
within 200 m (if any) is at least 2 s of its speed + 2.5 m ahead and not slower. Printed: how many such samples, and
the mean acceleration [m/s^2] over the next 0.5 s: the plan's (position: last planned speed - speed now, / 0.5 s) or
SUMO's realised one (native). Units: m, m/s, m/s^2.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "scripts"))
from diag_following_headway import drop_in_parser, sampled_steps, start_run  # noqa: E402


def has_room(lib, vid: str) -> bool:
    v = lib.vehicle
    if v.getLaneID(vid).startswith(":"):
        return False
    s = v.getSpeed(vid)
    if s > v.getAllowedSpeed(vid) - 3.0:
        return False
    if any(t[2] < 100.0 for t in v.getNextTLS(vid)):
        return False
    lead = v.getLeader(vid, 200.0)
    if lead and lead[0]:
        return lead[1] >= 2.0 * s + 2.5 and v.getSpeed(lead[0]) >= s
    return True


def main(argv=None) -> int:
    ap = drop_in_parser(__doc__.splitlines()[0])
    ap.set_defaults(drive="position", end=300.0)
    a = ap.parse_args(argv)
    lib, ctrl = start_run(a.scenario, a.drive, a.end, a.seed, a.checkpoint, sampler=a.sampler)
    acc: list[float] = []
    pending: dict[str, float] = {}  # native: vehicle -> speed when it had room, 0.5 s ago
    for _ in sampled_steps(lib, ctrl, a.end):
        if ctrl is None:
            now = {vid: lib.vehicle.getSpeed(vid) for vid in lib.vehicle.getIDList()}
            acc += [(now[v] - s0) / 0.5 for v, s0 in pending.items() if v in now]
            pending = {v: s for v, s in now.items() if has_room(lib, v)}
        elif ctrl.last_plan is not None:
            ids, plan = ctrl.last_plan
            for j, vid in enumerate(ids):
                rec = ctrl.vehicles.get(vid)
                if rec is None or rec.state != "controlled" or not has_room(lib, vid):
                    continue
                acc.append((float(plan.speed_mps[j, -1]) - lib.vehicle.getSpeed(vid)) / 0.5)
    acc_a = np.asarray(acc)
    print(f"{a.scenario} {a.drive} seed {a.seed}, {a.end:g} s: {len(acc_a)} samples with room; acceleration over the "
          f"next 0.5 s mean {acc_a.mean():.2f}, median {np.median(acc_a):.2f}, share >= 1.5 m/s^2 {(acc_a >= 1.5).mean():.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
