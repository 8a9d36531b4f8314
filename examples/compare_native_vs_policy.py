"""Same demand, SUMO-native vs policy-driven: speed and headway distributions, plotted to a PNG.

Run: ``python examples/compare_native_vs_policy.py [--network motorway_merge] [--end 120] [--untrained]
[--out compare.png]``

Each run starts the network's .sumocfg with the same seed (hence the same departures), records every
vehicle's speed and, for vehicles with a leader, the time headway (gap / speed) each 0.1 s step.
"""

from __future__ import annotations

import argparse

import numpy as np

import r1sim_sumo
from r1sim_sumo._sumo_env import ensure_sumo_home
from r1sim_sumo.model.untrained import untrained_policy
from r1sim_sumo.resources import network_files
from r1sim_sumo.sim.sumo_controller import SumoController
from r1sim_sumo.sumo_launch import sumo_command


def run_once(cfg, end_s: float, policy=None, seed: int = 0) -> dict:
    ensure_sumo_home()
    import libsumo as sumo

    sumo.start(sumo_command(seed, sumocfg=cfg))
    ctrl = SumoController(sumo, policy, seed=seed) if policy is not None else None
    speeds, headways = [], []
    try:
        for _ in range(int(end_s / 0.1)):
            sumo.simulationStep()
            if ctrl is not None:
                ctrl.step()
            for v in sumo.vehicle.getIDList():
                sp = sumo.vehicle.getSpeed(v)
                speeds.append(sp)
                lead = sumo.vehicle.getLeader(v, 100.0)
                if lead and sp > 1.0:
                    headways.append(max(lead[1], 0.0) / sp)  # [s] gap to the leader / own speed
    finally:  # native, then the policy on the same .sumocfg in this process: ctrl.close() (see SumoController.close)
        if ctrl is not None:
            ctrl.close()
        else:
            sumo.close()
    return {"speed": np.asarray(speeds), "headway": np.asarray(headways),
            "stats": ctrl.stats.summary() if ctrl is not None else None}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--network", default="motorway_merge")
    ap.add_argument("--end", type=float, default=120.0, help="simulated seconds per run")
    ap.add_argument("--untrained", action="store_true", help="random nano policy (no checkpoint needed)")
    ap.add_argument("--out", default="compare_native_vs_policy.png")
    args = ap.parse_args()

    policy = untrained_policy() if args.untrained else r1sim_sumo.load_policy()
    cfg = network_files(args.network)["sumocfg"]
    runs = {"SUMO native": run_once(cfg, args.end), "policy": run_once(cfg, args.end, policy)}

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for name, r in runs.items():
        axes[0].hist(r["speed"], bins=40, range=(0, 45), density=True, histtype="step", label=name)
        axes[1].hist(r["headway"], bins=40, range=(0, 6), density=True, histtype="step", label=name)
        print(f"{name}: mean speed {r['speed'].mean():.2f} m/s, median headway "
              f"{np.median(r['headway']) if len(r['headway']) else float('nan'):.2f} s")
    axes[0].set_xlabel("speed [m/s]")
    axes[1].set_xlabel("time headway [s]")
    for ax in axes:
        ax.set_ylabel("density")
        ax.legend()
    fig.suptitle(f"{args.network}: {args.end:g} s, same demand and seed")
    fig.tight_layout()
    fig.savefig(args.out, dpi=120)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
