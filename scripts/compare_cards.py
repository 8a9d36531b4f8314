#!/usr/bin/env python3
"""Issue 19's card targets, side by side, from model-card folders (each written by ``python -m
r1sim_sumo.train.model_card DIR ...``, which leaves ``DIR/model_card.json``).

    python scripts/compare_cards.py runs/cards/nano46_r16 runs/cards/s51_nudge [...] [--markdown]

Prints, per card: rollouts per scene, held-out NLL, closed-loop collision rate, offroad rate over the log window
(overall and per network), RMM and the share of the constant-velocity -> log-replay RMM gap it closes, and which of
issue 19's card targets hold (collision <= 0.03, offroad over the log window <= 0.05 on every network, RMM >= 75% of
the gap).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

COLLISION_MAX = 0.03
OFFROAD_LW_MAX = 0.05
GAP_MIN = 0.75


def card_row(folder: str | Path) -> dict:
    """One card's figures: ``{name, rollouts, nll, collision, offroad_lw, per_network: {net: offroad_lw}, rmm, gap,
    targets: {collision, offroad, rmm}}`` (targets True where issue 19's bound holds)."""
    path = Path(folder) / "model_card.json"
    if not path.exists():
        raise FileNotFoundError(f"{path}: no model card here; write one with python -m r1sim_sumo.train.model_card {folder} ...")
    card = json.loads(path.read_text())
    cl = card["closed_loop"]
    pol, cv, log = (cl["overall"][k] for k in ("policy", "constant_velocity", "log_replay"))
    nets = {n: v["policy"]["realism/offroad_rate_log_window"] for n, v in sorted(cl["per_network"].items())}
    rmm = pol["realism/rmm"]
    gap = (rmm - cv["realism/rmm"]) / (log["realism/rmm"] - cv["realism/rmm"])
    nll = card.get("token_metrics", {}).get("policy", {}).get("nll")
    row = {"name": Path(folder).name, "rollouts": cl["rollouts"], "nll": nll,
           "collision": pol["realism/collision_rate"], "offroad_lw": pol["realism/offroad_rate_log_window"],
           "per_network": nets, "rmm": rmm, "gap": gap}
    row["targets"] = {"collision": row["collision"] <= COLLISION_MAX,
                      "offroad": max(nets.values()) <= OFFROAD_LW_MAX, "rmm": gap >= GAP_MIN}
    return row


def table(rows: list[dict]) -> str:
    nets = sorted({n for r in rows for n in r["per_network"]})
    head = ["card", "rollouts", "NLL", "collision", "offroad LW"] + nets + ["RMM (gap)", "targets met"]
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        met = [k for k, ok in r["targets"].items() if ok]
        cells = [r["name"], str(r["rollouts"]), "" if r["nll"] is None else f"{r['nll']:.3f}", f"{r['collision']:.4f}",
                 f"{r['offroad_lw']:.4f}"] + [f"{r['per_network'].get(n, float('nan')):.3f}" for n in nets]
        cells += [f"{r['rmm']:.4f} ({r['gap']:.0%})", f"{len(met)}/3" + ("" if len(met) == 3 else
                  " (missed: " + ", ".join(k for k, ok in r["targets"].items() if not ok) + ")")]
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cards", nargs="+", help="model-card folders (each with model_card.json)")
    a = ap.parse_args(argv)
    print(table([card_row(c) for c in a.cards]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
