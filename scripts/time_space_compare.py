#!/usr/bin/env python3
"""Time-space pictures of several drop-in runs of one scenario side by side, along one route.

    python scripts/time_space_compare.py --out PNG LABEL=SAMPLES_JSON [LABEL=SAMPLES_JSON ...]

Each ``SAMPLES_JSON`` is the ``<scenario>_<mode>.time_space.samples.json`` that ``r1sim simulate --plot`` (and so
``examples/full_horizon_runs.py``) writes beside its picture; every panel is drawn along the route of the first one
(the route its vehicles drove most), titled with its label, on one speed colour scale.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="LABEL=path/to/<scenario>_<mode>.time_space.samples.json")
    ap.add_argument("--out", required=True, help="picture to write (.png)")
    a = ap.parse_args(argv)
    from r1sim_sumo.sim.time_space import plot_side_by_side, reproject

    series = []
    for spec in a.runs:
        label, sep, path = spec.partition("=")
        if not sep or not Path(path).is_file():
            ap.error(f"{spec!r}: give LABEL=path/to/samples.json (an existing file)")
        series.append((label, json.loads(Path(path).read_text())))
    route = series[0][1]["route"]
    panels = [{**reproject(data, route), "title": label} for label, data in series]
    plot_side_by_side(panels, Path(a.out))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
