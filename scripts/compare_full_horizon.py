#!/usr/bin/env python3
"""Full-horizon drop-in runs of several checkpoints and seeds side by side: arrivals of the commands drive relative
to native's (and mean speed relative to native's) per scenario, and the mean over scenarios.

    python scripts/compare_full_horizon.py LABEL=REPORT_JSON [LABEL=REPORT_JSON ...] [--mode commands] [--events] [--queues]

Each ``REPORT_JSON`` is a ``report.json`` written by ``examples/full_horizon_runs.py`` (one seed, one checkpoint,
its own native rows: each run is compared with the native run of the same seed). A label that appears more than once
(``nano=s0.json nano=s1.json``) also gets a column with its mean over those reports. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path


def ratios(report: Path, mode: str) -> dict[str, tuple[float, float, float, int, int, int, float, float]]:
    """scenario -> (arrived / native arrived, mean speed / native mean speed, collision events per 1000 vehicle-km,
    arrived, native arrived, collision events, vehicle-km, the longest a queue grew without clearing [s]) of
    ``mode``'s row."""
    rows = {(r["scenario"], r["mode"]): r for r in json.loads(Path(report).read_text())}
    out = {}
    for (name, m), r in rows.items():
        nat = rows.get((name, "native"))
        if m != mode or nat is None or not nat["arrived"]:
            continue
        out[name] = (r["arrived"] / nat["arrived"], r["mean_speed_mps"] / max(nat["mean_speed_mps"], 1e-9),
                     r.get("collisions_per_1000_vkm", float("nan")), r["arrived"], nat["arrived"],
                     r.get("collisions_either", 0), r.get("vkm", 0.0), r.get("queue_growth_s", float("nan")))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("reports", nargs="+", help="LABEL=path/to/report.json")
    ap.add_argument("--mode", default="commands", help="policy mode compared with native (default commands)")
    ap.add_argument("--events", action="store_true", help="also collision events per 1000 vehicle-km in each cell "
                    "and a row of summed arrivals (native's) / events (per 1000 vehicle-km) per report")
    ap.add_argument("--queues", action="store_true", help="also the longest a queue grew without clearing [s] in each cell")
    a = ap.parse_args(argv)
    cols: list[tuple[str, dict]] = []
    for spec in a.reports:
        if "=" not in spec:
            ap.error(f"{spec!r}: give LABEL=path/to/report.json")
        label, path = spec.split("=", 1)
        if not Path(path).is_file():
            ap.error(f"{path}: no such report.json (write one with examples/full_horizon_runs.py)")
        cols.append((label, ratios(Path(path), a.mode)))
    names = list(dict.fromkeys(n for _, c in cols for n in c))
    by_label: dict[str, list[dict]] = defaultdict(list)
    for label, c in cols:
        by_label[label].append(c)
    means = [(lbl, cs) for lbl, cs in by_label.items() if len(cs) > 1]
    head = [f"{lbl}" for lbl, _ in cols] + [f"{lbl} mean of {len(cs)}" for lbl, cs in means]
    print(f"{a.mode} drive: arrivals / native's (mean speed / native's)"
          + (", collision events per 1000 vehicle-km" if a.events else "")
          + ("; longest queue growth [s]" if a.queues else "") + "\n")
    print("| scenario | " + " | ".join(head) + " |")
    print("|---|" + "---|" * len(head))

    def cell(vals: list[tuple]) -> str:
        if not vals:
            return "-"
        arr = sum(v[0] for v in vals) / len(vals)
        spd = sum(v[1] for v in vals) / len(vals)
        ev = f", {sum(v[2] for v in vals) / len(vals):.0f}" if a.events and all(len(v) > 2 for v in vals) else ""
        q = f"; {sum(v[7] for v in vals) / len(vals):.0f} s" if a.queues and all(len(v) > 7 for v in vals) else ""
        return f"{arr:.3f} ({spd:.2f}{ev}{q})"

    totals = [[] for _ in head]
    for n in names:
        cells = [[c[n]] if n in c else [] for _, c in cols] + [[c[n] for c in cs if n in c] for _, cs in means]
        for t, v in zip(totals, cells, strict=True):
            if v:
                t.append((sum(x[0] for x in v) / len(v), sum(x[1] for x in v) / len(v)))
        print(f"| {n} | " + " | ".join(cell(v) for v in cells) + " |")
    print("| **mean over scenarios** | " + " | ".join(cell(t) for t in totals) + " |")
    if a.events:
        sums = []
        for _, c in cols:
            arr, nat, ev, vkm = (sum(v[i] for v in c.values()) for i in (3, 4, 5, 6))
            sums.append(f"{arr} ({nat}) / {ev} ({1000 * ev / max(vkm, 1e-9):.0f})")
        print("| **sum: arrivals (native's) / events (per 1000 vkm)** | " + " | ".join(sums) + " |" + " |" * len(means))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
