#!/usr/bin/env python3
"""How the logged speed trend goes on: the next 0.5 s speed change given the last one, in a compact token dataset.

    python scripts/log_speed_trend.py [data/tokens/ext] [--split train]

From the logged boundary poses (every 0.5 s) of every agent: the mean speed of three consecutive 0.5 s segments
v1, v2, v3 [m/s]; per bin of the previous change v2 - v1 and of the speed v2, the mean next change v3 - v2 and the
share of next changes above +0.2 m/s. The reference for ``scripts/probe_token_distribution.py --history-accel``: a
past speeding up at 2 m/s^2 is a previous change of +1 m/s.
"""

from __future__ import annotations

import argparse

import numpy as np

PREV_BINS = ((-1.4, -0.6), (-0.6, -0.2), (-0.2, 0.2), (0.2, 0.6), (0.6, 1.4))  # [m/s] previous 0.5 s speed change
SPEED_BINS = ((5.0, 15.0), (15.0, 25.0), (25.0, 40.0))  # [m/s]


def trend_table(gt_x: np.ndarray, gt_y: np.ndarray, gt_valid: np.ndarray) -> list[dict]:
    """Rows (prev bin, speed bin, n, mean next change [m/s], share of next changes > 0.2 m/s) from boundary poses
    ``[A, P]`` [m] every 0.5 s and their validity."""
    sp = np.hypot(np.diff(gt_x.astype(np.float64), axis=1), np.diff(gt_y.astype(np.float64), axis=1)) / 0.5
    ok = gt_valid[:, 1:].astype(bool) & gt_valid[:, :-1].astype(bool)
    o = ok[:, :-2] & ok[:, 1:-1] & ok[:, 2:]
    d1, d2, base = (sp[:, 1:-1] - sp[:, :-2])[o], (sp[:, 2:] - sp[:, 1:-1])[o], sp[:, 1:-1][o]
    rows = []
    for lo, hi in PREV_BINS:
        for vlo, vhi in SPEED_BINS:
            m = (d1 >= lo) & (d1 < hi) & (base >= vlo) & (base < vhi)
            n = int(m.sum())
            rows.append({"prev": (lo, hi), "speed": (vlo, vhi), "n": n,
                         "next_mean": float(d2[m].mean()) if n else float("nan"),
                         "next_up_share": float((d2[m] > 0.2).mean()) if n else float("nan")})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("tokens", nargs="?", default="data/tokens/ext")
    ap.add_argument("--split", default="train")
    a = ap.parse_args(argv)
    from r1sim_sumo.tokens.compact import CompactTokenDataset

    d = CompactTokenDataset(a.tokens, a.split)
    print(f"{a.tokens} ({a.split}): next 0.5 s speed change given the previous one")
    print("| previous change [m/s] | speed [m/s] | n | next change, mean [m/s] | next change > +0.2 m/s |")
    print("|---|---|---|---|---|")
    for r in trend_table(d.a["gt_x"], d.a["gt_y"], d.a["gt_valid"]):
        print(f"| {r['prev'][0]:+.1f} .. {r['prev'][1]:+.1f} | {r['speed'][0]:.0f}-{r['speed'][1]:.0f} | {r['n']} | "
              f"{r['next_mean']:+.3f} | {r['next_up_share']:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
