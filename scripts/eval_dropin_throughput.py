#!/usr/bin/env python3
"""Drop-in throughput of checkpoints on the two merges that jam: arrivals and mean speed against native SUMO.

    python scripts/eval_dropin_throughput.py CHECKPOINT [CHECKPOINT ...] [--seeds 0 1 2] [--out DIR]

The model card's 8 s scenes do not show whether a policy keeps a merge flowing for minutes (session 15: the better card
model delivered fewer vehicles on the merges). This runs ``r1sim simulate --drive commands`` (the default Krauss cap,
top-5) per checkpoint and seed on

- ``motorway_merge`` (bundled), 300 s;
- ``sumo-game-ramp`` (SUMO's own ``tools/game/ramp.sumocfg``), its full 400 s;

plus SUMO alone (``--native``) on the same seeds, and writes ``throughput.json`` and ``throughput.md`` (mean and range
over the seeds of arrivals, arrivals relative to native, mean speed [m/s], free-road speed / desired speed of the
driven vehicles: :mod:`r1sim_sumo.sim.free_road_speed`; n/a for summaries cached before it existed) into ``--out``.
One run takes 1-2 min on one core.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

SCENARIOS = {"motorway_merge": (["--network", "motorway_merge"], 300.0), "sumo-game-ramp": (None, 400.0)}


def _scenario_args(name: str) -> tuple[list[str], float]:
    args, end = SCENARIOS[name]
    if args is None:
        import sumo

        args = ["--sumocfg", str(Path(sumo.SUMO_HOME) / "tools" / "game" / "ramp.sumocfg")]
    return args, end


def _weights_tag(checkpoint: str) -> str:
    """First 8 hex digits of the SHA-256 of the checkpoint's weights (a bundled name or a folder), so that a cached
    run is not reused after a bundled name is re-shipped with other weights."""
    import hashlib

    from r1sim_sumo.model.checkpoint import BUNDLED_DIR

    p = Path(checkpoint)
    folder = p if p.is_dir() else BUNDLED_DIR / checkpoint
    return hashlib.sha256((folder / "model.safetensors").read_bytes()).hexdigest()[:8]


def run(name: str, checkpoint: str | None, seed: int, out: Path) -> dict:
    """One ``r1sim simulate`` run (``checkpoint`` None = native); returns its summary (cached in ``out``, keyed by the
    checkpoint's path and weights)."""
    tag = "native" if checkpoint is None else checkpoint.strip("/").replace("/", "_") + "_" + _weights_tag(checkpoint)
    js = out / f"{name}_{tag}_seed{seed}.json"
    if not js.exists():
        args, end = _scenario_args(name)
        cmd = [sys.executable, "-m", "r1sim_sumo.cli", "simulate", *args, "--end", f"{end:g}", "--seed", str(seed),
               "--json", str(js), "--no-progress"]
        cmd += ["--native"] if checkpoint is None else ["--drive", "commands", "--checkpoint", checkpoint]
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed (exit {r.returncode}):\n{r.stderr[-2000:]}")
    return json.loads(js.read_text())


def _fmt(v) -> str:
    return "n/a" if v is None else f"{v:.3f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("checkpoints", nargs="+")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), choices=list(SCENARIOS))
    ap.add_argument("--out", default="runs/throughput")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in a.scenarios:
        native = {s: run(name, None, s, out) for s in a.seeds}
        for ck in [None, *a.checkpoints]:
            runs = [native[s] if ck is None else run(name, ck, s, out) for s in a.seeds]
            arr = np.array([r["arrived"] for r in runs], float)
            rel = arr / np.array([native[s]["arrived"] for s in a.seeds], float)
            spd = np.array([r["mean_speed_mps"] for r in runs])  # [m/s] over all vehicles and steps
            free = [r["free_road_speed_share"] for r in runs if r.get("free_road_speed_share") is not None]
            row = {"scenario": name, "driver": ck or "native", "seeds": a.seeds, "arrived": arr.tolist(),
                   "arrived_mean": float(arr.mean()), "arrived_vs_native": float(rel.mean()),
                   "arrived_vs_native_range": [float(rel.min()), float(rel.max())], "mean_speed_mps": float(spd.mean()),
                   "free_road_speed_share": float(np.mean(free)) if free else None,
                   "collisions_sumo": int(sum(r["collisions_sumo"] for r in runs))}
            rows.append(row)
            print(f"{name:15s} {row['driver']:45s} arrived {row['arrived_mean']:6.1f} ({row['arrived_vs_native']:.3f} of "
                  f"native, {rel.min():.3f}-{rel.max():.3f}), mean speed {row['mean_speed_mps']:.1f} m/s, free-road "
                  f"speed share {_fmt(row['free_road_speed_share'])}, "
                  f"SUMO collisions {row['collisions_sumo']}", flush=True)
    (out / "throughput.json").write_text(json.dumps(rows, indent=1) + "\n")
    md = ["| scenario | driver | arrivals (mean over seeds) | vs native (range) | mean speed [m/s] | free-road speed / desired "
          "| SUMO collisions |", "|---|---|---|---|---|---|---|"]
    md += [f"| {r['scenario']} | {r['driver']} | {r['arrived_mean']:.1f} | {r['arrived_vs_native']:.3f} "
           f"({r['arrived_vs_native_range'][0]:.3f}-{r['arrived_vs_native_range'][1]:.3f}) | {r['mean_speed_mps']:.1f} | "
           f"{_fmt(r['free_road_speed_share'])} | {r['collisions_sumo']} |" for r in rows]
    (out / "throughput.md").write_text(f"Seeds {a.seeds}; `python scripts/eval_dropin_throughput.py "
                                       f"{' '.join(a.checkpoints)} --seeds {' '.join(map(str, a.seeds))}`\n\n"
                                       + "\n".join(md) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
