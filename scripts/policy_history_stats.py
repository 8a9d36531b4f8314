#!/usr/bin/env python3
"""What states does the policy make, and what does SUMO do from them? Policy-history windows vs the default recipe.

    python scripts/policy_history_stats.py data/generated/default/val data/generated/policy_history/val [--max 400]

Per dataset split, over the motorway networks' cars valid at the window's current index and 2 s later (both
motorways' lanes are limited to 33.3 m/s): the share driving below ``SLOW_MPS``, their mean speed, and their mean
acceleration over the next 2 s [m/s^2], i.e. what the labels of such states teach. Prints one row per dataset and
network (markdown).
"""

from __future__ import annotations

import argparse
from collections import defaultdict

from r1sim_sumo.scenario import ScenarioDataset

MOTORWAYS = ("lane_drop", "motorway_merge")
SLOW_MPS = 20.0


def stats(folder: str, max_windows: int) -> dict:
    ds = ScenarioDataset(folder)
    step = max(1, len(ds) // max_windows)
    acc = defaultdict(lambda: {"n": 0, "slow": 0, "short": 0.0, "slow_acc": 0.0, "windows": 0})
    for i in range(0, len(ds), step):
        sc = ds[i]
        net = sc.metadata.get("network")
        if net not in MOTORWAYS:
            continue
        a, ci = sc.agents, sc.current_index
        later = ci + 20
        ok = a.valid[:, ci] & a.valid[:, later] & (a.agent_type == 0)
        v0, v1 = a.speed_mps[ok, ci], a.speed_mps[ok, later]
        slow = v0 < SLOW_MPS
        r = acc[net]
        r["windows"] += 1
        r["n"] += int(ok.sum())
        r["slow"] += int(slow.sum())
        r["short"] += float(v0[slow].sum())
        r["slow_acc"] += float(((v1 - v0)[slow] / 2.0).sum())
    return acc


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("folders", nargs="+")
    ap.add_argument("--max", type=int, default=400, help="windows read per folder at most (evenly spaced)")
    a = ap.parse_args(argv)
    print(f"| data | network | windows | cars | below {SLOW_MPS:g} m/s | their mean speed [m/s] | their accel. next 2 s [m/s^2] |")
    print("|---|---|---|---|---|---|---|")
    for f in a.folders:
        for net, r in sorted(stats(f, a.max).items()):
            print(f"| {f} | {net} | {r['windows']} | {r['n']} | {r['slow'] / max(r['n'], 1):.1%} | "
                  f"{r['short'] / max(r['slow'], 1):.1f} | {r['slow_acc'] / max(r['slow'], 1):+.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
