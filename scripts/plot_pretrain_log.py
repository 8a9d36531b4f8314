#!/usr/bin/env python3
"""Curve of a pretraining run (``r1sim pretrain``'s ``log.csv``): training loss (label-smoothed, with its running mean)
and held-out token NLL per step, optionally against a reference NLL (e.g. the checkpoint the run started from).

    python scripts/plot_pretrain_log.py docs/training/runs/gpu_a/log.csv --label "gpu_a from r1sim-nano" \\
        --reference-nll 1.144 --out docs/training/gpu_a_training.png

Columns used: ``step``, ``loss``, ``val_nll`` (rows without it are training-only), ``tokens_per_s``.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np


def read_log(path: Path) -> dict[str, np.ndarray]:
    """``step``/``loss`` of every row and ``val_step``/``val_nll`` of the evaluated rows; errors name the file."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows or not {"step", "loss", "val_nll"} <= set(rows[0]):
        raise SystemExit(f"{path}: not a pretraining log.csv (needs the columns step, loss, val_nll)")
    val = [r for r in rows if r["val_nll"]]
    return {"step": np.array([int(r["step"]) for r in rows]), "loss": np.array([float(r["loss"]) for r in rows]),
            "val_step": np.array([int(r["step"]) for r in val]), "val_nll": np.array([float(r["val_nll"]) for r in val])}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("log", type=Path)
    ap.add_argument("--label", default="")
    ap.add_argument("--reference-nll", type=float, help="held-out NLL of the start checkpoint, drawn as a line")
    ap.add_argument("--window", type=int, default=20, help="running mean over this many logged rows")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    d = read_log(args.log)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.6))
    a1.plot(d["step"], d["loss"], lw=0.5, alpha=0.4, color="tab:blue", label="logged step")
    w = min(args.window, len(d["loss"]))
    if w > 1:
        rm = np.convolve(d["loss"], np.ones(w) / w, mode="valid")
        a1.plot(d["step"][w - 1:], rm, color="tab:blue", label=f"{w}-row running mean")
    a1.set_xlabel("step")
    a1.set_ylabel("training loss [nats, label-smoothed]")
    a1.legend(fontsize=8)
    a2.plot(d["val_step"], d["val_nll"], "o-", color="tab:orange", label="held-out token NLL")
    if args.reference_nll is not None:
        a2.axhline(args.reference_nll, ls="--", color="gray", label=f"start checkpoint {args.reference_nll:.3f}")
    a2.set_xlabel("step")
    a2.set_ylabel("val NLL [nats / token]")
    a2.legend(fontsize=8)
    fig.suptitle(args.label or str(args.log))
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    plt.close(fig)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
