"""Collision events of SUMO's own drivers on a bundled network, counted as the drop-in's runs count them.

Runs ``r1sim simulate --native`` (SUMO drives every vehicle; SUMO's junction check on and box overlaps of any two
vehicles, :mod:`r1sim_sumo.sim.collision_events`, as in the native rows of ``docs/simulate/report.md``) once per
(network, seed) and prints its events (SUMO-reported / any), arrivals and the mean speed over vehicle-steps [m/s];
``--describe N`` lists the first N events (time, vehicles, their lanes and speeds) from the run's summary.

    python scripts/count_native_collisions.py --networks urban_intersection urban_grid --seeds 0 1 2
    python scripts/count_native_collisions.py --networks urban_grid --net-file old.net.xml --seeds 0   # another build

``--net-file`` runs a copy of the network's folder (in a temporary directory) with that ``.net.xml`` in place of the
bundled one; the bundled files are not touched.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from r1sim_sumo.resources import network_files


def count(network: str, seed: int, end_s: float, net_file: str | None = None) -> dict:
    """One native run of ``network``'s default demand (its summary from ``r1sim simulate --json``)."""
    with tempfile.TemporaryDirectory() as tmp:
        cfg = Path(network_files(network)["sumocfg"])
        if net_file:
            folder = Path(tmp) / network
            shutil.copytree(cfg.parent, folder)
            shutil.copyfile(net_file, folder / network_files(network)["net"].name)
            cfg = folder / cfg.name
        out = Path(tmp) / "summary.json"
        cmd = [sys.executable, "-m", "r1sim_sumo.cli", "simulate", "--native", "--sumocfg", str(cfg), "--seed",
               str(seed), "--end", f"{end_s:g}", "--json", str(out), "--no-progress"]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"{network} seed {seed}: r1sim simulate failed (exit {proc.returncode}):\n"
                               f"{proc.stderr[-2000:]}")
        return json.loads(out.read_text())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--networks", nargs="+", required=True, help="bundled network names (r1sim_sumo.resources)")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--end", type=float, default=900.0, help="simulated seconds [s]")
    ap.add_argument("--net-file", default=None, help="a .net.xml to run instead of the bundled one (one network)")
    ap.add_argument("--describe", type=int, default=0, help="list the first N events of each run")
    ap.add_argument("--json", default=None, help="write every run's summary to this file")
    args = ap.parse_args(argv)
    if args.net_file and len(args.networks) != 1:
        ap.error("--net-file replaces one network's .net.xml: pass exactly one name to --networks")
    runs = []
    for name in args.networks:
        for seed in args.seeds:
            s = count(name, seed, args.end, args.net_file)
            runs.append({"network": name, "seed": seed, "net_file": args.net_file, **s})
            speed = s["speed_sum_mps"] / max(s["vehicle_steps"], 1)
            print(f"{name} seed {seed}: events sumo {s['collisions_sumo']} any {s['collisions_any']}  arrived "
                  f"{s['arrived']}  mean speed {speed:.2f} m/s", flush=True)
            for e in s.get("collision_events", [])[:args.describe]:
                print(f"    {e['time_s']} {e['check']} {e['a']} {e['a_lane']} {e['a_speed_mps']} m/s | "
                      f"{e['b']} {e['b_lane']} {e['b_speed_mps']} m/s")
    if args.json:
        Path(args.json).write_text(json.dumps(runs, indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
