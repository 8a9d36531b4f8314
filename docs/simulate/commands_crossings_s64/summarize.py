#!/usr/bin/env python3
"""Session 64: the commands drive with SUMO driving the speed through crossing junctions (``--junction-crossings
sumo``) against the policy's commands there (``policy``, the commands drive's default before session 64), 8 scenarios
x seeds 0-7, each run against native SUMO on the same demand and seed.

    python docs/simulate/commands_crossings_s64/summarize.py [--runs runs] > docs/simulate/commands_crossings_s64/seeds0to7.md

Rows come from the report.json files of ``examples/full_horizon_runs.py`` (a list of rows, one per scenario and mode):
seed 0 from runs/ship63_s0 (policy; session 60's commands rows, the drive unchanged since) and runs/jx63cmdx_s0
(sumo); seeds 1-7: the roundabout, game/ramp and game/grid6 from runs/carry58_cmd_gains_sS (policy) and
runs/jx63cmdx_sS (sumo, roundabout and game/ramp), the other scenarios from runs/jx64cmd_sS (policy) and
runs/jx64cmdx_sS (sumo). Where both folders hold a scenario, the later one in the list wins.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

SCENARIOS = ["motorway_merge", "lane_drop", "urban_grid", "urban_intersection", "roundabout", "sumo-game-ramp",
             "sumo-game-cross", "sumo-game-grid6"]
SOURCES = {  # variant -> seed -> folders, later ones win
    "policy": {0: ["ship63_s0"], **{s: [f"carry58_cmd_gains_s{s}", f"jx64cmd_s{s}"] for s in range(1, 8)}},
    "sumo": {0: ["jx63cmdx_s0"], **{s: [f"jx63cmdx_s{s}", f"jx64cmdx_s{s}"] for s in range(1, 8)}},
}


def rows(runs: Path, folders: list[str]) -> dict[tuple[str, str], dict]:
    out: dict[tuple[str, str], dict] = {}
    for f in folders:
        p = runs / f / "report.json"
        if p.exists():
            out.update({(r["scenario"], r["mode"]): r for r in json.loads(p.read_text())})
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", default="runs")
    a = ap.parse_args()
    runs = Path(a.runs)
    cell: dict[tuple[str, str, int], tuple] = {}  # (variant, scenario, seed) -> (arr ratio, speed ratio, events, native events, arrived, native arrived, queue s)
    for var, by_seed in SOURCES.items():
        for seed, folders in by_seed.items():
            r = rows(runs, folders)
            for sc in SCENARIOS:
                c, n = r.get((sc, "commands")), r.get((sc, "native"))
                if c is None or n is None:
                    continue
                cell[var, sc, seed] = (c["arrived"] / n["arrived"], c["mean_speed_mps"] / n["mean_speed_mps"],
                                       c["collisions_either"], n["collisions_either"], c["arrived"], n["arrived"],
                                       c.get("queue_growth_s") or 0.0, c.get("policy_vkm_share"))
    seeds = range(8)
    print("Commands drive, `--junction-crossings policy` (before session 64) vs `sumo`: per scenario over the seeds both "
          "have, arrivals / native's (mean, lowest, seeds >= 0.98), mean speed / native's (mean), collision events "
          "(sum; native's sum on the same seeds), runs with events where native has none.\n")
    print("| scenario | seeds | policy: arrivals mean / lowest / >= 0.98 | sumo: arrivals mean / lowest / >= 0.98 | "
          "speed policy / sumo | events policy / sumo (native) | events where native has none: policy / sumo |")
    print("|---|---|---|---|---|---|---|")
    tot = {"policy": [0, 0, 0], "sumo": [0, 0, 0]}
    for sc in SCENARIOS:
        both = [s for s in seeds if ("policy", sc, s) in cell and ("sumo", sc, s) in cell]
        if not both:
            continue
        line = [sc, f"{both[0]}-{both[-1]}" if both == list(range(both[0], both[-1] + 1)) else ",".join(map(str, both))]
        speeds, events, bad = [], [], []
        for var in ("policy", "sumo"):
            v = [cell[var, sc, s] for s in both]
            ar = [x[0] for x in v]
            line.append(f"{sum(ar) / len(ar):.3f} / {min(ar):.3f} / {sum(x >= 0.98 for x in ar)} of {len(ar)}")
            speeds.append(f"{sum(x[1] for x in v) / len(v):.2f}")
            events.append(str(sum(x[2] for x in v)))
            bad.append(str(sum(x[2] > 0 and x[3] == 0 for x in v)))
            tot[var][0] += sum(x[4] for x in v)
            tot[var][1] += sum(x[5] for x in v)
            tot[var][2] += sum(x[2] for x in v)
        native_events = sum(cell["sumo", sc, s][3] for s in both)
        line += [" / ".join(speeds), f"{' / '.join(events)} ({native_events})", " / ".join(bad)]
        print("| " + " | ".join(line) + " |")
    for var, (arr, nat, ev) in tot.items():
        print(f"| **all ({var})** | | {arr} of native's {nat} arrivals ({arr / nat:.4f}) | | | {ev} events | |")
    print("\nPer seed, arrivals summed over the scenarios present in both variants (policy / sumo / native):\n")
    print("| seed | scenarios | policy | sumo | native |")
    print("|---|---|---|---|---|")
    for s in seeds:
        scs = [sc for sc in SCENARIOS if ("policy", sc, s) in cell and ("sumo", sc, s) in cell]
        if scs:
            p = sum(cell["policy", sc, s][4] for sc in scs)
            q = sum(cell["sumo", sc, s][4] for sc in scs)
            n = sum(cell["sumo", sc, s][5] for sc in scs)
            print(f"| {s} | {len(scs)} | {p} | {q} | {n} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
