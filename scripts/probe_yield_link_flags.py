#!/usr/bin/env python3
"""Two vehicles at the bundled roundabout: does SUMO see a ``moveToXY``-placed vehicle approaching, and what do the
link flags of ``vehicle.getNextLinks`` say while SUMO's own driver decides to enter?

    python scripts/probe_yield_link_flags.py [--ring-pos 5] [--entry-pos 60]

Vehicle ``R`` drives the ring (``ring_north_west`` -> ``ring_west_south`` -> ``ring_south_east`` ...) starting
``--ring-pos`` m into ``ring_north_west`` at 8 m/s; vehicle ``E`` approaches the ring on ``south_in`` (a yield link at
junction ``ring_south``) starting ``--entry-pos`` m into it at 8 m/s. SUMO's drivers drive both. The run is made twice:

1. ``sumo``: SUMO drives ``R``;
2. ``moved``: ``R`` is placed every 0.1 s with ``moveToXY`` (``keepRoute`` 3, speed mode ``--moved-speed-mode``,
   default 32 as the position drive sets) on the poses it had in run 1.

Every 0.5 s it prints both vehicles' lanes and speeds and ``E``'s next link's ``hasFoe`` flag (the flag the position
drive's yield rule reads, ``r1sim_sumo/sim/rules.py``), and at the end when ``E`` entered the junction and the
closest the two came. Equal lines in both runs mean that SUMO's junction model sees the placed vehicle as it sees its
own; an entry while ``hasFoe`` is still true means SUMO's driver takes a gap that the flag alone would refuse.
"""

from __future__ import annotations

import argparse
import math

from r1sim_sumo.sumo_launch import settle_remote_control


def run(conn, net: str, mode: str, ring_pos_m: float, entry_pos_m: float, trace=None, speed_mode: int = 32) -> list:
    conn.start(["sumo", "-n", net, "--step-length", "0.1", "--no-step-log", "--collision.action", "warn",
                "--collision.check-junctions", "--no-warnings"])
    try:
        conn.route.add("rr", ["ring_north_west", "ring_west_south", "ring_south_east", "ring_east_north"])
        conn.route.add("er", ["south_in", "ring_south_east", "east_out"])
        conn.vehicle.add("R", "rr", departPos=str(ring_pos_m), departSpeed="8")
        conn.vehicle.add("E", "er", departPos=str(entry_pos_m), departSpeed="8")
        conn.simulationStep()
        if mode == "moved":
            conn.vehicle.setSpeedMode("R", speed_mode)
            conn.vehicle.setLaneChangeMode("R", 0)
        poses, entered, closest = [], None, math.inf
        for k in range(1, 250):
            if mode == "moved" and k - 1 < len(trace):
                x, y, a = trace[k - 1]
                conn.vehicle.moveToXY("R", "", -1, x, y, a, 3)
            conn.simulationStep()
            ids = conn.vehicle.getIDList()
            if "R" not in ids or "E" not in ids:
                break
            (rx, ry), (ex, ey) = conn.vehicle.getPosition("R"), conn.vehicle.getPosition("E")
            closest = min(closest, math.hypot(rx - ex, ry - ey))
            poses.append((rx, ry, conn.vehicle.getAngle("R")))
            lane = conn.vehicle.getLaneID("E")
            links = conn.vehicle.getNextLinks("E")
            if entered is None and lane.startswith(":"):
                entered = k * 0.1
            if k % 5 == 0:
                print(f"{mode:6s} t={k * 0.1:4.1f} s  R {conn.vehicle.getLaneID('R'):18s} {conn.vehicle.getSpeed('R'):5.2f} m/s"
                      f" | E {lane:18s} {conn.vehicle.getLanePosition('E'):6.1f} m {conn.vehicle.getSpeed('E'):5.2f} m/s"
                      f"  hasFoe {links[0][3] if links else '-'}")
        print(f"{mode}: E entered the junction at {entered} s; closest centre distance R-E {closest:.2f} m; "
              f"collisions {conn.simulation.getCollidingVehiclesNumber()}")
        return poses
    finally:
        settle_remote_control(conn)  # libsumo keeps pending moveToXY past close (r1sim_sumo.sumo_launch)
        conn.close()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ring-pos", type=float, default=5.0, help="R's start on ring_north_west [m]")
    ap.add_argument("--entry-pos", type=float, default=60.0, help="E's start on south_in [m] (its end at ~145 m)")
    ap.add_argument("--moved-speed-mode", type=int, default=32,
                    help="R's speed mode in the moved run (32: the position drive's, take_control; 31: SUMO's default)")
    a = ap.parse_args(argv)
    # isort: off
    import r1sim_sumo  # noqa: F401 - first, as `r1sim simulate`
    import libsumo as conn
    # isort: on
    from r1sim_sumo._sumo_env import ensure_sumo_home
    from r1sim_sumo.resources import network_files

    ensure_sumo_home()
    net = str(network_files("roundabout")["net"])
    trace = run(conn, net, "sumo", a.ring_pos, a.entry_pos)
    run(conn, net, "moved", a.ring_pos, a.entry_pos, trace, a.moved_speed_mode)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
