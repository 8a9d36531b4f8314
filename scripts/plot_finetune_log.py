#!/usr/bin/env python3
"""Training curve of a fine-tuning run (``r1sim finetune``'s ``log.csv``): reward, collision rate and distance to the
reference per iteration, each with its 10-iteration running mean (single iterations vary mostly with the scenes drawn).

    python scripts/plot_finetune_log.py docs/training/runs/grpo_g/log.csv --label "grpo_g from r1sim-nano" \\
        --mark 75 100 --out docs/training/grpo_g_training.png

``--mark`` draws a vertical line at the given iterations (e.g. the shipped ones). Columns used: ``iter``, ``reward``
(mean token reward), ``collision_rate`` (share of token steps of the rollouts with a collision), ``distance_m`` (mean
distance to the reference trajectory [m]).
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

PANELS = (("reward", "mean token reward"), ("collision_rate", "collision rate (token steps)"),
          ("distance_m", "distance to reference [m]"))
WINDOW = 10


def read_log(path: Path) -> dict[str, np.ndarray]:
    """The numeric columns of a fine-tuning ``log.csv``; a missing column is an error naming the file."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise SystemExit(f"{path}: no rows")
    missing = [c for c in ("iter", *(p[0] for p in PANELS)) if c not in rows[0]]
    if missing:
        raise SystemExit(f"{path}: missing column(s) {missing}; is it the log.csv of `r1sim finetune`?")
    return {c: np.array([float(r[c]) for r in rows]) for c in ("iter", *(p[0] for p in PANELS))}


def running_mean(y: np.ndarray, w: int = WINDOW) -> np.ndarray:
    """Mean of the last ``w`` values (fewer at the start)."""
    c = np.cumsum(np.insert(y, 0, 0.0))
    n = np.minimum(np.arange(1, len(y) + 1), w)
    return (c[1:] - c[np.arange(1, len(y) + 1) - n]) / n


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", type=Path)
    ap.add_argument("--label", default=None)
    ap.add_argument("--mark", type=int, nargs="*", default=[])
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = read_log(a.log)
    fig, axes = plt.subplots(1, len(PANELS), figsize=(14, 3.6))
    for ax, (col, ylabel) in zip(axes, PANELS, strict=True):
        ax.plot(d["iter"], d[col], "o-", ms=3, lw=0.8, alpha=0.5, label=a.label or a.log.parent.name)
        ax.plot(d["iter"], running_mean(d[col]), lw=2.0, label=f"{WINDOW}-iteration running mean")
        for m in a.mark:
            ax.axvline(m, color="grey", ls="--", lw=0.8)
        ax.set_xlabel("iteration")
        ax.set_ylabel(ylabel)
        ax.legend(fontsize=7)
    fig.tight_layout()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out, dpi=110)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
