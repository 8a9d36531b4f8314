"""libsumo keeps the vehicles of a pending moveToXY past ``close``: the reproduction behind session 50's CI crashes.

    R1SIM_FUSED_ATTENTION=0 R1SIM_FUSED_DROPOUT=0 PYTHONMALLOC=malloc valgrind --error-limit=no \
        python3.11 scripts/repro_libsumo_pending_move.py [--settle]

(``python3.11`` the interpreter itself, not a pyenv shim, or valgrind checks the shell; the switches turn off the
project's AVX-512 C kernels, which valgrind cannot run.) A vehicle ``fol`` behind a
leader on motorway_merge is driven by the drop-in controller (position drive: a ``moveToXY`` after every SUMO step);
the loop ends right after a controller step and the simulation is closed; then the same two vehicles are started in a
new simulation and it steps. Without ``--settle`` valgrind reports invalid reads in
``libsumo::Helper::postProcessRemoteControl`` (``MSVehicle::getInfluencer`` on a vehicle freed by
``Simulation::close``): a segmentation fault whenever the freed memory has been reused. With ``--settle`` the run ends
through ``SumoController.close()`` (``r1sim_sumo.sumo_launch.settle_remote_control``) and valgrind reports none.
"""

from __future__ import annotations

import argparse


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--settle", action="store_true", help="end the first run with SumoController.close()")
    a = ap.parse_args(argv)

    import libsumo
    import torch

    from r1sim_sumo._sumo_env import ensure_sumo_home, sumo_binary
    from r1sim_sumo.model.untrained import untrained_policy
    from r1sim_sumo.resources import network_files
    from r1sim_sumo.sim.sumo_controller import SumoController

    torch.set_num_threads(1)
    ensure_sumo_home()
    net = str(network_files("motorway_merge")["net"])

    def start() -> None:
        libsumo.start([sumo_binary("sumo"), "-n", net, "--step-length", "0.1", "--no-step-log", "true",
                       "--no-warnings", "true", "--collision.action", "warn"])
        libsumo.route.add("r", ["main_in", "merge", "main_out"])
        libsumo.vehicle.add("lead", "r", departLane="1", departPos="120", departSpeed="15")
        libsumo.vehicle.add("fol", "r", departLane="1", departPos="55", departSpeed="15")

    start()
    ctrl = SumoController(libsumo, untrained_policy(0), drive="position", control="id=fol", offroad_margin_m=1e6)
    for _ in range(100):
        libsumo.simulationStep()
        ctrl.step()  # ends with a moveToXY of fol, carried out only by the next step
    print("first run: fol is", ctrl.vehicles["fol"].state, flush=True)
    if a.settle:
        ctrl.close()
    else:
        libsumo.close()
    start()  # a vehicle "fol" again
    for _ in range(10):
        libsumo.simulationStep()
    libsumo.close()
    print("second run stepped", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
