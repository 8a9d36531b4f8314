#!/usr/bin/env python3
"""One scenario's full-horizon drop-in runs over many seeds, pooled per variant: collision events per 1000 vehicle-km
per seed and pooled (all events over all vehicle-km), arrivals, and the longest a queue grew without clearing per seed.

    python scripts/pool_seed_runs.py --scenario urban_intersection --mode position --seeds 0-7 \\
        s66=runs/s66fin_s{seed} s67=runs/s67i_s{seed} [--native runs/s66z_s{seed}]

Each ``LABEL=PATTERN`` names a variant; ``{seed}`` in the pattern is replaced by each seed and the folder must hold
``<scenario>_<mode>.json`` (as ``examples/full_horizon_runs.py --out`` writes it). Seeds whose file is missing are
left out of that row (the row says how many it has). ``--native``: the same for SUMO's own drivers, a row of its own.
Prints a markdown table. Events are pooled as the issue counts them: all events of the seeds over all their
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


def row(label: str, pattern: str, scenario: str, mode: str, seeds: list[int]) -> str:
    per, queues, events, vkm, arrived, n = [], [], 0.0, 0.0, 0, 0
    for s in seeds:
        f = Path(pattern.format(seed=s)) / f"{scenario}_{mode}.json"
        if not f.exists():
            per.append("-")
            queues.append("-")
            continue
        d = json.loads(f.read_text())
        rate, km = float(d["collisions_per_1000_vkm"]), float(d["vkm_all"])
        events += rate * km / 1000.0
        vkm += km
        arrived += int(d["arrived"])
        n += 1
        per.append(f"{rate:.0f}")
        q = float(d["longest_queue_growth_s"])
        queues.append(f"**{q:.0f}**" if q > LONG_QUEUE_S else f"{q:.0f}")
    pooled = 1000.0 * events / vkm if vkm else float("nan")
    return (f"| {label} | {n} | {' / '.join(per)} | {pooled:.1f} | {events:.0f} | {arrived:,} | "
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
    print("| variant | runs | collision events per 1000 vehicle-km, per seed | pooled | events | arrivals "
          "| longest queue growth [s], per seed |")
    print("|---|---|---|---|---|---|---|")
    if a.native:
        print(row("native (SUMO's drivers)", a.native, a.scenario, "native", seeds))
    for v in a.variants:
        label, _, pattern = v.partition("=")
        if not pattern:
            ap.error(f"variant {v!r}: expected LABEL=PATTERN")
        print(row(label, pattern, a.scenario, a.mode, seeds))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
