#!/usr/bin/env python3
"""Side-by-side table of two ``r1sim evaluate`` reports of the same rollouts scored with two realism computations.

    python scripts/compare_metric_reports.py docs/eval_nano_test docs/eval_nano_test_legacy [--out docs/eval_nano_test/metric_vs_legacy.md]

Both folders hold a ``report.json`` of the same command (same checkpoint, data, samplers, rollouts and seeds), one
with ``--metric wosac`` (the official computation) and one with ``--metric legacy``; the script refuses reports whose
rollouts differ (minADE must match, it does not depend on the metric). Prints a markdown table of RMM, the three
bucket scores and the collision rate, new vs old, for all scenarios and the Easy / Hard splits.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

KEYS = [("realism/rmm", "RMM"), ("bucket/kinematic", "kinematic"), ("bucket/interactive", "interactive"),
        ("bucket/map_based", "map-based"), ("realism/collision_rate", "collision rate")]
PARTS = [("summary", "all scenarios"), ("summary_easy", "Easy"), ("summary_hard", "Hard")]


def table(new: dict, old: dict) -> str:
    lines = []
    for part, title in PARTS:
        lines += [f"**{title}** (official WOSAC / legacy)", "",
                  "| model / sampler | " + " | ".join(label for _, label in KEYS) + " |",
                  "|---|" + "---|" * len(KEYS)]
        for name, row in new[part].items():
            ref = old[part][name]
            if abs(row.get("realism/min_ade", 0.0) - ref.get("realism/min_ade", 0.0)) > 1e-6:
                raise SystemExit(f"compare_metric_reports: '{name}' ({part}) has a different minADE in the two reports: "
                                 "they score different rollouts; run the same evaluate command with --metric wosac and legacy")
            lines.append(f"| {name} | " + " | ".join(f"{row[k]:.3f} / {ref[k]:.3f}" for k, _ in KEYS) + " |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("new", help="report folder scored with --metric wosac")
    ap.add_argument("old", help="report folder scored with --metric legacy")
    ap.add_argument("--out", default=None, help="also write the table to this markdown file")
    a = ap.parse_args(argv)
    reports = []
    for folder in (a.new, a.old):
        path = Path(folder) / "report.json"
        if not path.exists():
            print(f"compare_metric_reports: {path} not found; run `r1sim evaluate ... --out {folder}` first", file=sys.stderr)
            return 2
        reports.append(json.loads(path.read_text()))
    text = table(*reports)
    print(text)
    if a.out:
        Path(a.out).write_text("# Realism: official WOSAC computation vs the legacy one, same rollouts\n\n"
                               f"`{a.new}` vs `{a.old}`; each cell is official / legacy.\n\n" + text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
