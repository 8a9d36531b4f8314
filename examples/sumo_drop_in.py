"""Attach the learned policy to your own SUMO loop (libsumo or TraCI) in a few lines.

Run: ``python examples/sumo_drop_in.py [--traci] [--untrained] [--steps 300]``

The policy drives half of the vehicles (``control="fraction=0.5"``); the others stay SUMO-driven and are
context for the policy. SUMO must run with a 0.1 s step.
"""

from __future__ import annotations

import argparse

import r1sim_sumo
from r1sim_sumo._sumo_env import ensure_sumo_home
from r1sim_sumo.model.untrained import untrained_policy
from r1sim_sumo.resources import network_files
from r1sim_sumo.sim.sumo_controller import SumoController
from r1sim_sumo.sumo_launch import sumo_command


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--traci", action="store_true", help="TraCI instead of libsumo")
    ap.add_argument("--untrained", action="store_true", help="random nano policy (no checkpoint needed)")
    ap.add_argument("--steps", type=int, default=300, help="0.1 s steps to simulate")
    args = ap.parse_args()

    ensure_sumo_home()
    if args.traci:
        import traci as sumo
    else:
        import libsumo as sumo
    policy = untrained_policy() if args.untrained else r1sim_sumo.load_policy()

    cfg = network_files("motorway_merge")["sumocfg"]
    sumo.start(sumo_command(seed=0, sumocfg=cfg))  # --step-length 0.1, collision checks, no teleports

    # --- the drop-in part: create once, call step() after every simulationStep -----------------------
    ctrl = SumoController(sumo, policy, control="fraction=0.5", seed=0)
    for _ in range(args.steps):
        sumo.simulationStep()
        ctrl.step()  # alternatively, once before the loop: ctrl.attach_step_listener()
    # ----------------------------------------------------------------------------------------------------

    ctrl.release_all()
    ctrl.close()  # closes SUMO; with libsumo it first lets SUMO carry out the controller's last moves
    s = ctrl.stats.summary()
    print({k: s[k] for k in ("departed", "arrived", "running", "controlled_total", "handbacks", "collisions_sumo",
                             "collisions_sat", "vkm_controlled", "mean_speed_mps")})


if __name__ == "__main__":
    main()
