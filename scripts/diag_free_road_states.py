"""Where and how the drop-in's vehicles drive below their desired speed on a free road, and whether they speed up.

Every 0.5 s, every vehicle on a free road (:class:`r1sim_sumo.sim.free_road_speed.FreeRoadSpeed`'s test: no leader,
signal or slowing link within 100 m) gives a sample: its edge, speed and desired speed (lane limit x speedFactor,
capped by its type's maxSpeed) [m/s], and its acceleration over the next 0.5 s [m/s^2] (when it is still in the run).
Printed: per edge, samples / mean speed / mean desired; and by how far below its desired speed a vehicle is (the gap
[m/s]), its mean acceleration over the next 0.5 s. SUMO's Krauss driver speeds up at its type's accel (2.6 m/s^2 for
the default passenger car) until it reaches its desired speed; a driver that holds its speed shows ~0 in every row.

    python scripts/diag_free_road_states.py --scenario sumo-game-ramp --drive native
    python scripts/diag_free_road_states.py --scenario sumo-game-ramp --drive commands [--checkpoint CKPT] [--guidance 2] [--sampler median:0.1]

Scenarios as in ``scripts/diag_following_headway.py``; commands drive = the drop-in's defaults, ``--control all``.
"""

from __future__ import annotations

import sys

import numpy as np
from diag_following_headway import drop_in_parser, sampled_steps, start_run

GAP_BINS = ((-np.inf, 1.0), (1.0, 3.0), (3.0, 6.0), (6.0, 10.0), (10.0, np.inf))  # desired - speed [m/s]


def run(scenario: str, drive: str, end_s: float, seed: int, checkpoint: str | None, guidance: float,
        sampler: str | None = None) -> dict:
    libsumo, ctrl = start_run(scenario, drive, end_s, seed, checkpoint, guidance, sampler)
    from r1sim_sumo.adapters.sumo_state import read_desired_speeds
    from r1sim_sumo.sim.free_road_speed import MIN_DESIRED_MPS, SAMPLE_EVERY_STEPS, FreeRoadSpeed
    from r1sim_sumo.sumo_launch import STEP_LENGTH_S

    dt = SAMPLE_EVERY_STEPS * STEP_LENGTH_S  # [s] between samples

    free = FreeRoadSpeed(libsumo)
    pending: dict[str, tuple[float, float, str]] = {}  # id -> (speed, desired, edge) at the last sample
    rows = []  # (edge, speed, desired, accel over the next 0.5 s)
    for _ in sampled_steps(libsumo, ctrl, end_s):
        now = set(libsumo.vehicle.getIDList())
        for v, (s0, des, edge) in pending.items():
            if v in now:
                rows.append((edge, s0, des, (libsumo.vehicle.getSpeed(v) - s0) / dt))
        pending = {}
        ids = [v for v in now if free.is_free(v)]
        if ctrl is not None:
            ids = [v for v in ids if v in ctrl.vehicles and ctrl.vehicles[v].state == "controlled"]
        if not ids:
            continue
        desired = read_desired_speeds(libsumo, ids).astype(np.float64)
        for v, d in zip(ids, desired.tolist(), strict=True):
            if np.isfinite(d) and d >= MIN_DESIRED_MPS:
                s = libsumo.vehicle.getSpeed(v)
                pending[v] = (s, d, libsumo.vehicle.getRoadID(v))
    return {"rows": rows}


def main(argv=None) -> int:
    ap = drop_in_parser(__doc__.splitlines()[0])
    ap.add_argument("--guidance", type=float, default=0.0, help="desired-speed guidance weight (commands / position)")
    a = ap.parse_args(argv)
    rows = run(a.scenario, a.drive, a.end, a.seed, a.checkpoint, a.guidance, a.sampler)["rows"]
    who = "SUMO" if a.drive == "native" else f"{a.checkpoint or 'r1sim-nano'}, sampler {a.sampler or 'the default'}, guidance {a.guidance:g}"
    print(f"{a.scenario} {a.drive} ({who}), {a.end:g} s, seed {a.seed}: {len(rows)} free-road samples")
    if not rows:
        return 0
    edge = np.array([r[0] for r in rows])
    s, d, acc = (np.array([r[i] for r in rows], np.float64) for i in (1, 2, 3))
    print("  per edge (most samples first): samples, mean speed / mean desired [m/s], speed / desired")
    for e in sorted(set(edge.tolist()), key=lambda e: -(edge == e).sum())[:8]:
        m = edge == e
        print(f"    {e:24s} {m.sum():6d}  {s[m].mean():5.1f} / {d[m].mean():5.1f}  {np.mean(s[m] / d[m]):.2f}")
    over = s / d
    print(f"  above the desired speed: {np.mean(over > 1.05):.3f} of the samples by > 5%, {np.mean(over > 1.1):.3f} by > 10%; "
          f"speed / desired p50 {np.median(over):.2f}, p95 {np.quantile(over, 0.95):.2f}, max {over.max():.2f}")
    print("  by gap to the desired speed [m/s]: samples, mean speed [m/s], mean acceleration over the next 0.5 s [m/s^2]")
    gap = d - s
    for lo, hi in GAP_BINS:
        m = (gap >= lo) & (gap < hi)
        if m.any():
            print(f"    {lo:5.0f} .. {hi:<5.0f} {m.sum():6d}  {s[m].mean():5.1f}  {acc[m].mean():+.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
