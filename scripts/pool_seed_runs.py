#!/usr/bin/env python3
"""One scenario's full-horizon drop-in runs over many seeds, pooled per variant: collision events per 1000 vehicle-km
per seed and pooled (all events over all vehicle-km), arrivals, and the longest a queue grew without clearing per seed.

    python scripts/pool_seed_runs.py --scenario urban_intersection --mode position --seeds 0-7 \\
        s66=runs/s66fin_s{seed} s67=runs/s67i_s{seed} [--native runs/s66z_s{seed}]

Each ``LABEL=PATTERN`` names a variant; ``{seed}`` in the pattern is replaced by each seed and the folder must hold
``<scenario>_<mode>.json`` (as ``examples/full_horizon_runs.py --out`` writes it). Seeds whose file is missing are
left out of that row (the row says how many it has). ``--native``: the same for SUMO's own drivers, a row of its own.
With ``--native`` each row also has its arrivals over the seeds it has against native's on the same seeds and the mean of its
per-seed mean-speed ratios. Prints a markdown table. Events are pooled as the issue counts them: all events of the seeds over all their
vehicle-km, so that a run with 0-9 events does not weigh as much as its per-seed rate suggests.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

LONG_QUEUE_S = 60.0  # [s] issue 20's bound on a queue growing without clearing


def parse_seeds(spec: str) -> list[int]:
    """``"0-7"`` or ``"0,2,5"`` or ``"3"`` -> seeds."""
    out: list[int] = []
    for part in spec.split(","):
        if "-" in part:
            a, b = part.split("-")
            out.extend(range(int(a), int(b) + 1))
        else:
            out.append(int(part))
    return out


def _load(pattern: str, seed: int, scenario: str, mode: str) -> dict | None:
    f = Path(pattern.format(seed=seed)) / f"{scenario}_{mode}.json"
    return json.loads(f.read_text()) if f.exists() else None


def row(label: str, pattern: str, scenario: str, mode: str, seeds: list[int], native: str | None) -> str:
    """One variant's table row; with ``native`` (a pattern) also its arrivals and mean speed against native's on the
    same seeds (arrivals summed over the seeds it has, speed the mean of the per-seed ratios)."""
    per, queues, events, vkm, arrived, nat_arrived, speed, n = [], [], 0.0, 0.0, 0, 0, [], 0
    for s in seeds:
        d = _load(pattern, s, scenario, mode)
        if d is None:
            per.append("-")
            queues.append("-")
            continue
        rate, km = float(d["collisions_per_1000_vkm"]), float(d["vkm_all"])
        events += rate * km / 1000.0
        vkm += km
        arrived += int(d["arrived"])
        n += 1
        per.append(f"{rate:.0f}")
        q = float(d["longest_queue_growth_s"])
        queues.append(f"**{q:.0f}**" if q > LONG_QUEUE_S else f"{q:.0f}")
        nat = _load(native, s, scenario, "native") if native else None
        if nat is not None:
            nat_arrived += int(nat["arrived"])
            speed.append(float(d["mean_speed_mps"]) / max(float(nat["mean_speed_mps"]), 1e-9))
    pooled = 1000.0 * events / vkm if vkm else float("nan")
    vs = (f" {arrived / nat_arrived:.3f} | {sum(speed) / len(speed):.3f} |" if nat_arrived and speed else " - | - |") \
        if native else ""
    return (f"| {label} | {n} | {' / '.join(per)} | {pooled:.1f} | {events:.0f} | {arrived:,} |{vs} "
            f"{' / '.join(queues)} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("variants", nargs="+", help="LABEL=PATTERN with {seed} (a folder per seed)")
    ap.add_argument("--scenario", required=True)
    ap.add_argument("--mode", default="position", help="the drive of the rows (native, commands, position, ...)")
    ap.add_argument("--seeds", default="0-7")
    ap.add_argument("--native", default=None, help="PATTERN of the native runs' folders (a row of SUMO's own drivers)")
    a = ap.parse_args(argv)
    seeds = parse_seeds(a.seeds)
    print(f"{a.scenario}, {a.mode} drive, seeds {a.seeds}; a queue growing past {LONG_QUEUE_S:.0f} s in bold\n")
    vs = " arrivals / native's | speed / native's |" if a.native else ""
    print("| variant | runs | collision events per 1000 vehicle-km, per seed | pooled | events | arrivals |" + vs
          + " longest queue growth [s], per seed |")
    print("|---|---|---|---|---|---|" + ("---|---|" if a.native else "") + "---|")
    if a.native:
        print(row("native (SUMO's drivers)", a.native, a.scenario, "native", seeds, a.native))
    for v in a.variants:
        label, _, pattern = v.partition("=")
        if not pattern:
            ap.error(f"variant {v!r}: expected LABEL=PATTERN")
        print(row(label, pattern, a.scenario, a.mode, seeds, a.native))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
