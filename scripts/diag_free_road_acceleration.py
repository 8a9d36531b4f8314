#!/usr/bin/env python3
"""How a lone policy-driven car speeds up on an empty road, against SUMO driving the same car (issue 20, session 14).

    python scripts/diag_free_road_acceleration.py [CHECKPOINT] [--sampler topk:5] [--drive commands]

Two probes on bundled networks with no other traffic, each car's speed [m/s] every 2 s from its departure:

- ``motorway``: motorway_merge mainline, cars depart at 2, 0 and 5 m/s (lanes 0, 1, 2) 20 s apart;
- ``roundabout``: cars depart standing 60 m into three approaches (east, north, south) and cross the roundabout
  (lane limits 13.9 m/s on the approaches, 7.9-8.3 m/s in the ring).

The car type is a Krauss passenger car with ``accel 2.6 m/s^2``, ``sigma 0`` and ``speedFactor 1``, so the native
row is SUMO's deterministic profile. The controller takes a car over after its first 1.1 s (eleven 10 Hz states);
``--drive commands`` (default) or ``position``; ``--sampler`` as ``r1sim simulate``. Prints one row per car and mode and
the mean acceleration [m/s^2] over the first 8 s (on the roundabout it includes braking into the ring).

``python -m r1sim_sumo.evaluate_free_road`` (the learning curve's probe) follows the policy's plans without SUMO; this
script runs the drop-in controller in SUMO, next to SUMO driving the same cars. Session 14 (r1sim-nano, commands, top-5):
2.06-2.14 m/s^2 over the first 8 s from 0-5 m/s on the motorway (native 2.60), and 5-8 m/s in the roundabout (native 8.2-9.4).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import libsumo

import r1sim_sumo
from r1sim_sumo.resources import network_path
from r1sim_sumo.sim.sumo_controller import SumoController
from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command

CAR = ('<vType id="car" vClass="passenger" length="4.6" width="1.8" minGap="2.5" maxSpeed="50.0" accel="2.6" '
       'decel="4.5" emergencyDecel="9.0" sigma="0.0" tau="1.0" speedFactor="1.0" carFollowModel="Krauss"/>')
PROBES = {  # network -> (routes, vehicles) of the probe's route file
    "motorway_merge": (
        {"mainline": "main_in merge main_out"},
        [("m0", "mainline", 0, 'departLane="0" departSpeed="2"'), ("m1", "mainline", 20, 'departLane="1" departSpeed="0"'),
         ("m2", "mainline", 40, 'departLane="2" departSpeed="5"')]),
    "roundabout": (
        {"east_left": "east_in ring_east_north ring_north_west ring_west_south south_out",
         "north_right": "north_in ring_north_west west_out",
         "south_straight": "south_in ring_south_east ring_east_north north_out"},
        [("r0", "east_left", 0, 'departSpeed="0" departPos="60"'), ("r1", "north_right", 30, 'departSpeed="0" departPos="60"'),
         ("r2", "south_straight", 60, 'departSpeed="0" departPos="60"')]),
}
SAMPLE_EVERY_S = 2.0
ACCEL_WINDOW_S = 8.0


def write_probe(network: str, folder: Path) -> Path:
    """A ``.sumocfg`` of the bundled ``network`` with the probe's lone cars (nothing else) in ``folder``."""
    routes, vehicles = PROBES[network]
    rou = ["<routes>", "    " + CAR]
    rou += [f'    <route id="{rid}" edges="{edges}"/>' for rid, edges in routes.items()]
    rou += [f'    <vehicle id="{vid}" type="car" route="{rid}" depart="{t}" {extra}/>' for vid, rid, t, extra in vehicles]
    rou.append("</routes>")
    (folder / "probe.rou.xml").write_text("\n".join(rou) + "\n")
    net = network_path(network) / f"{network}.net.xml"
    end = vehicles[-1][2] + 40
    cfg = folder / "probe.sumocfg"
    cfg.write_text(f'<configuration><input><net-file value="{net}"/><route-files value="probe.rou.xml"/></input>'
                   f'<time><begin value="0"/><end value="{end}"/><step-length value="0.1"/></time></configuration>\n')
    return cfg


def speeds(cfg: Path, policy, drive: str | None, sampler: str) -> dict[str, list[float]]:
    """Each car's speed [m/s] every 2 s from its departure; ``drive=None`` = SUMO drives (native)."""
    libsumo.start(sumo_command(seed=0, sumocfg=str(cfg)))
    try:
        ctl = None if drive is None else SumoController(libsumo, policy, drive=drive, sampler=sampler)
        out: dict[str, list[float]] = {}
        every = round(SAMPLE_EVERY_S / 0.1)
        k = 0
        while libsumo.simulation.getMinExpectedNumber() > 0:
            libsumo.simulationStep()
            if ctl is not None:
                ctl.step()
            for vid in libsumo.vehicle.getIDList():
                out.setdefault(vid, [])
            if k % every == 0:
                for vid in libsumo.vehicle.getIDList():
                    out[vid].append(float(libsumo.vehicle.getSpeed(vid)))
            k += 1
        return out
    finally:
        settle_remote_control(libsumo)  # libsumo keeps pending moveToXY past close (r1sim_sumo.sumo_launch)
        libsumo.close()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", nargs="?", default="r1sim-nano")
    ap.add_argument("--sampler", default="topk:5")
    ap.add_argument("--drive", default="commands", choices=["commands", "position"])
    a = ap.parse_args(argv)
    policy = r1sim_sumo.load_policy(a.checkpoint)
    n_acc = round(ACCEL_WINDOW_S / SAMPLE_EVERY_S)
    with tempfile.TemporaryDirectory() as d:
        for network in PROBES:
            cfg = write_probe(network, Path(d))
            for mode, drive in (("native", None), (f"{a.checkpoint} {a.drive} {a.sampler}", a.drive)):
                for vid, v in speeds(cfg, policy, drive, a.sampler).items():
                    acc = (v[n_acc] - v[0]) / ACCEL_WINDOW_S if len(v) > n_acc else float("nan")
                    print(f"{network:15s} {mode:32s} {vid}: first-8-s accel {acc:4.2f} m/s^2; speed every 2 s "
                          + " ".join(f"{x:4.1f}" for x in v[:16]))


if __name__ == "__main__":
    main()
