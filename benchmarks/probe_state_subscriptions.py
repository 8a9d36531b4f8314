"""Does reading SUMO's vehicle states through libsumo subscriptions beat the controller's per-vehicle getters?

One process, the 9 x 9 city grid of :mod:`bench_sumo_controller` with ~700 cars (no policy): after 10 s of warm-up,
alternating blocks of 50 steps read every vehicle's type, position, angle and speed either with
:func:`r1sim_sumo.adapters.sumo_state.read_vehicle_states` (what the controller does each 0.1 s step) or with
``vehicle.subscribe`` + ``getAllSubscriptionResults`` (every vehicle subscribed once; SUMO collects the values inside
``simulationStep``). Prints ms per step of ``simulationStep`` and of the read for each, two rounds; the sum is what
counts, since subscriptions move work into the step.

    python benchmarks/probe_state_subscriptions.py [--vehicles 700] [--steps 50] [--rounds 2]

Session 32 (Intel Xeon, 2 cores, idle; 699 vehicles): read 1.43-1.47 ms per step with the getters, 1.08-1.39 with
subscriptions, but the step 2.54-3.09 -> 3.63-5.27 ms: a net loss, not adopted (a first run beside two drop-in runs:
read 2.4 -> 1.8-2.2 ms, step 4.8-5.3 -> 7.0-8.8 ms).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_sumo_controller as scene  # noqa: E402

VARS = (0x4F, 0x42, 0x43, 0x40)  # TraCI variable ids: type id, position, angle, speed


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=int, default=700)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--rounds", type=int, default=2)
    a = ap.parse_args(argv)
    from r1sim_sumo.adapters.sumo_state import read_vehicle_states

    with tempfile.TemporaryDirectory() as d:
        conn, _ = scene.start_scene("grid", a.vehicles, Path(d))
        for _ in range(100):
            conn.simulationStep()
        print(f"{len(conn.vehicle.getIDList())} vehicles")

        def timed(read) -> tuple[float, float]:
            t_step = t_read = 0.0
            for _ in range(a.steps):
                t0 = time.perf_counter()
                conn.simulationStep()
                t1 = time.perf_counter()
                read()
                t_step, t_read = t_step + t1 - t0, t_read + time.perf_counter() - t1
            return 1e3 * t_step / a.steps, 1e3 * t_read / a.steps

        def getters() -> None:
            read_vehicle_states(conn)

        def subscribed() -> None:
            for vid in conn.simulation.getDepartedIDList():
                conn.vehicle.subscribe(vid, VARS)
            res = conn.vehicle.getAllSubscriptionResults()
            np.array([(r[0x42][0], r[0x42][1], r[0x43], r[0x40]) for r in res.values()])

        for _ in range(a.rounds):
            for vid in conn.vehicle.getIDList():
                conn.vehicle.subscribe(vid, VARS)
            step_ms, read_ms = timed(subscribed)
            print(f"subscriptions  step {step_ms:.2f} ms  read {read_ms:.2f} ms")
            for vid in conn.vehicle.getIDList():
                conn.vehicle.unsubscribe(vid)
            step_ms, read_ms = timed(getters)
            print(f"getters        step {step_ms:.2f} ms  read {read_ms:.2f} ms")
        conn.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
