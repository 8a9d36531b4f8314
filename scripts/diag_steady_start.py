#!/usr/bin/env python3
"""Does a policy-driven car speed up from a *steady* low speed on an empty road? (issue 19/20, session 16)

    python scripts/diag_steady_start.py [CHECKPOINT ...] [--v0 5 10 15] [--json OUT.json]

Each probe car departs alone at ``v0`` [m/s] and is held there by ``vehicle.setSpeed`` for its first ``--hold``
seconds (2 and 4 by default), as a car leaving a queue or a merge looks; then the drop-in controller (``--drive
commands``, top-5, ``--seeds`` 0 1 2) or SUMO (the ``native`` row) drives it for 30 s. The controller takes the car over at its
first decision with 1.1 s of history (1.5 s after departure) and remembers its own last decisions (up to 2.5 s of
its past, ``PolicyDriver(memory=True)``): after a 2 s hold it has seen ~1.5 s of steady driving, after a 4 s hold
(its commands overridden by the hold) ~2.5 s. Roads:

- ``ramp``: the 2-lane, 1.1 km straight last edge ``gneE11`` of SUMO's own ``tools/game/ramp`` sample (33.3 m/s),
  where the drop-in's traffic crawls at ~10 m/s in ``docs/simulate/sumo-game-ramp_time_space.png``;
- ``merge lane 0/1/2``: the bundled ``motorway_merge`` mainline (33.3 m/s), one car per lane.

The car: a Krauss passenger car, ``accel 2.6 m/s^2``, ``sigma 0``, ``speedFactor 1`` (the native row is SUMO's
deterministic profile). Prints each car's speed 10 s and 30 s after the hold ends; a policy that copies its recent
speed stays near ``v0``. Session 16, session-15 r1sim-nano, 2 s hold: 22.8 m/s on average 10 s after the hold (SUMO:
32.6), most cars level off at ~20 m/s; the session-12 nano 25.2.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import libsumo

import r1sim_sumo
from r1sim_sumo._sumo_env import ensure_sumo_home
from r1sim_sumo.resources import network_path
from r1sim_sumo.sim.sumo_controller import SumoController
from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command

CAR = ('<vType id="car" vClass="passenger" length="5.0" width="1.8" minGap="2.5" maxSpeed="50.0" accel="2.6" '
       'decel="4.5" sigma="0.0" tau="1.0" speedFactor="1.0" speedDev="0"/>')
HOLD_S = (2.0, 4.0)  # [s] steady at v0 before the controller (or SUMO) drives
DRIVE_S = 30.0  # [s] after the hold
SAMPLE_AT_S = (10.0, 30.0)  # [s] after the hold


def probes() -> dict[str, tuple[Path, str, str]]:
    """``{probe: (net file, route edges, departLane)}``."""
    import sumo

    ramp = Path(sumo.SUMO_HOME) / "tools" / "game" / "ramp" / "ramp.net.xml"
    merge = network_path("motorway_merge") / "motorway_merge.net.xml"
    out = {"ramp gneE11 lane 0": (ramp, "gneE8 gneE11", "0"), "ramp gneE11 lane 1": (ramp, "gneE8 gneE11", "1")}
    out.update({f"merge lane {i}": (merge, "main_in merge main_out", str(i)) for i in range(3)})
    return out


def write_cfg(folder: Path, net: Path, edges: str, lane: str, v0: float) -> Path:
    (folder / "p.rou.xml").write_text(
        f'<routes>\n    {CAR}\n    <route id="r" edges="{edges}"/>\n'
        f'    <vehicle id="car" type="car" route="r" depart="0" departSpeed="{v0:g}" departLane="{lane}"/>\n</routes>\n')
    cfg = folder / "p.sumocfg"
    cfg.write_text(f'<configuration><input><net-file value="{net}"/><route-files value="p.rou.xml"/></input>'
                   f'<time><begin value="0"/><step-length value="0.1"/></time></configuration>\n')
    return cfg


def run(cfg: Path, v0: float, policy, hold_s: float, seed: int = 0) -> list[float]:
    """The car's speed [m/s] at :data:`SAMPLE_AT_S` after a ``hold_s`` hold (NaN where it already left the network)."""
    libsumo.start(sumo_command(0, sumocfg=cfg, end_s=hold_s + DRIVE_S + 1.0))
    try:
        ctl = None if policy is None else SumoController(libsumo, policy, control="all", sampler="topk:5", seed=seed,
                                                         drive="commands")
        hold = round(hold_s / 0.1)
        at = {hold + round(s / 0.1): s for s in SAMPLE_AT_S}
        got = {s: float("nan") for s in SAMPLE_AT_S}
        for k in range(hold + round(DRIVE_S / 0.1) + 1):
            ids = libsumo.vehicle.getIDList()
            controlled = ctl is not None and "car" in ctl.vehicles and ctl.vehicles["car"].state == "controlled"
            if "car" in ids and (k < hold or (k == hold and not controlled)):  # held (over the controller's commands)
                libsumo.vehicle.setSpeed("car", v0 if k < hold else -1.0)  # then SUMO's own driving, or the controller's
            libsumo.simulationStep()
            if ctl is not None:
                ctl.step()
            if k in at and "car" in libsumo.vehicle.getIDList():
                got[at[k]] = libsumo.vehicle.getSpeed("car")
        return [got[s] for s in SAMPLE_AT_S]
    finally:
        settle_remote_control(libsumo)  # libsumo keeps pending moveToXY past close (r1sim_sumo.sumo_launch)
        libsumo.close()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("checkpoints", nargs="*", default=["r1sim-nano"])
    ap.add_argument("--v0", type=float, nargs="+", default=[5.0, 10.0, 15.0], help="steady start speeds [m/s]")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="sampler seeds of the policy runs")
    ap.add_argument("--hold", type=float, nargs="+", default=list(HOLD_S), help="seconds held at v0 [s]")
    ap.add_argument("--json", help="write the table here too")
    a = ap.parse_args(argv)
    ensure_sumo_home()
    drivers = {"native": None, **{c: r1sim_sumo.load_policy(c) for c in a.checkpoints}}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, (net, edges, lane) in probes().items():
            for v0 in a.v0:
                cfg = write_cfg(Path(tmp), net, edges, lane, v0)
                for hold in a.hold:
                    for who, pol in drivers.items():
                        for seed in a.seeds[:1] if pol is None else a.seeds:  # SUMO's car is deterministic
                            v10, v30 = run(cfg, v0, pol, hold, seed)
                            rows.append({"probe": name, "v0_mps": v0, "hold_s": hold, "driver": who, "seed": seed,
                                         "speed_10s_mps": v10, "speed_30s_mps": v30})
                            print(f"{name:20s} v0 {v0:4.1f} hold {hold:3.1f} s seed {seed} {who:40s} after 10 s "
                                  f"{v10:5.1f}  after 30 s {v30:5.1f} m/s", flush=True)
    for hold in a.hold:
        for who in drivers:
            mine = [r for r in rows if r["driver"] == who and r["hold_s"] == hold]
            m10 = sum(r["speed_10s_mps"] for r in mine) / len(mine)
            m30 = sum(r["speed_30s_mps"] for r in mine) / len(mine)
            print(f"hold {hold:3.1f} s, {who}: mean speed {m10:.1f} m/s 10 s after the hold, {m30:.1f} m/s after 30 s")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
