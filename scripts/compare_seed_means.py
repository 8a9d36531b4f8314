#!/usr/bin/env python3
"""Two drop-in settings over the same seeds, per scenario: mean arrivals relative to native's, how many seeds reach a
share, on how many seeds the second delivers more, and collision events on the seeds where native has none.

    python scripts/compare_seed_means.py greedy=R0,R1,... median=R0,R1,... [--mode commands] [--share 0.98]
        [--scenarios roundabout sumo-game-ramp]

Each ``R`` is a ``report.json`` of ``examples/full_horizon_runs.py`` (or its folder); the two lists pair up by position
(same seed, same native run).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def _rows(path: str) -> list[dict]:
    p = Path(path)
    return json.loads((p / "report.json" if p.is_dir() else p).read_text())


def _cell(rows: list[dict], scenario: str, mode: str) -> tuple[float, int, int] | None:
    """(arrivals / native's, the mode's collision events, native's), or None when the report lacks the scenario."""
    by = {r["mode"]: r for r in rows if r.get("scenario") == scenario}
    if mode not in by or "native" not in by or not by["native"]["arrived"]:
        return None
    return by[mode]["arrived"] / by["native"]["arrived"], by[mode]["collisions_either"], by["native"]["collisions_either"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("settings", nargs=2, help="LABEL=report,report,... (paired by position)")
    ap.add_argument("--mode", default="commands")
    ap.add_argument("--share", type=float, default=0.98, help="arrivals share counted per seed (default 0.98)")
    ap.add_argument("--scenarios", nargs="+", default=None, help="default: every scenario of the first report")
    a = ap.parse_args(argv)
    (la, ra), (lb, rb) = (s.split("=", 1) for s in a.settings)
    ra, rb = [_rows(p) for p in ra.split(",")], [_rows(p) for p in rb.split(",")]
    if len(ra) != len(rb):
        ap.error(f"{la} has {len(ra)} reports, {lb} {len(rb)}: they pair up by seed")
    scenarios = a.scenarios or list(dict.fromkeys(r["scenario"] for r in ra[0]))
    print(f"{a.mode} drive, {len(ra)} seeds: arrivals / native's, mean (seeds >= {a.share:g}); seeds where {lb} delivers "
          f"more / as many; collision events on seeds where native has none\n")
    print(f"| scenario | {la} | {lb} | {lb} more / equal | events where native has none: {la} / {lb} |")
    print("|---|---|---|---|---|")
    for sc in scenarios:
        pairs = [(x, y) for x, y in ((_cell(p, sc, a.mode), _cell(q, sc, a.mode)) for p, q in zip(ra, rb, strict=True))
                 if x is not None and y is not None]
        if not pairs:
            continue
        n = len(pairs)
        ma, mb = sum(x[0] for x, _ in pairs) / n, sum(y[0] for _, y in pairs) / n
        ka, kb = sum(x[0] >= a.share for x, _ in pairs), sum(y[0] >= a.share for _, y in pairs)
        more, same = sum(y[0] > x[0] for x, y in pairs), sum(y[0] == x[0] for x, y in pairs)
        ea, eb = sum(x[1] for x, _ in pairs if x[2] == 0), sum(y[1] for _, y in pairs if y[2] == 0)
        print(f"| {sc} | {ma:.3f} ({ka}/{n}) | {mb:.3f} ({kb}/{n}) | {more} / {same} | {ea} / {eb} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
