#!/usr/bin/env python3
"""Does a policy-driven car speed up from a *steady* low speed on an empty road? (issue 19/20, session 16)

    python scripts/diag_steady_start.py [CHECKPOINT ...] [--v0 5 10 15] [--json OUT.json]

Each probe car departs alone at ``v0`` [m/s] and is held there by ``vehicle.setSpeed`` for its first 2 s, so the
controller takes it over with 1.1 s of steady history, as a car leaving a queue or a merge looks; then the drop-in
controller (``--drive commands``, top-5, seed 0) or SUMO (the ``native`` row) drives it for 30 s. Roads:

- ``ramp``: the 2-lane, 1.1 km straight last edge ``gneE11`` of SUMO's own ``tools/game/ramp`` sample (33.3 m/s),
  where the drop-in's traffic crawls at ~10 m/s in ``docs/simulate/sumo-game-ramp_time_space.png``;
- ``merge lane 0/1/2``: the bundled ``motorway_merge`` mainline (33.3 m/s), one car per lane.

The car: a Krauss passenger car, ``accel 2.6 m/s^2``, ``sigma 0``, ``speedFactor 1`` (the native row is SUMO's
deterministic profile). Prints each car's speed 10 s and 30 s after the hold ends; a policy that copies its recent
speed stays near ``v0``. Session 16, session-15 r1sim-nano: from a steady 10 m/s it stays at 10 m/s on the ramp and
in the merge's lane 0 (SUMO: 33 m/s within 10 s); the same car *accelerating* at takeover speeds up.
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
from r1sim_sumo.sumo_launch import sumo_command

CAR = ('<vType id="car" vClass="passenger" length="5.0" width="1.8" minGap="2.5" maxSpeed="50.0" accel="2.6" '
       'decel="4.5" sigma="0.0" tau="1.0" speedFactor="1.0" speedDev="0"/>')
HOLD_S = 2.0  # [s] steady at v0 before the controller (or SUMO) drives
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


def run(cfg: Path, v0: float, policy) -> list[float]:
    """The car's speed [m/s] at :data:`SAMPLE_AT_S` after the hold (NaN where it already left the network)."""
    libsumo.start(sumo_command(0, sumocfg=cfg, end_s=HOLD_S + DRIVE_S + 1.0))
    try:
        ctl = None if policy is None else SumoController(libsumo, policy, control="all", sampler="topk:5", seed=0,
                                                         drive="commands")
        hold = round(HOLD_S / 0.1)
        at = {hold + round(s / 0.1): s for s in SAMPLE_AT_S}
        got = {s: float("nan") for s in SAMPLE_AT_S}
        for k in range(hold + round(DRIVE_S / 0.1) + 1):
            ids = libsumo.vehicle.getIDList()
            controlled = ctl is not None and "car" in ctl.vehicles and ctl.vehicles["car"].state == "controlled"
            if "car" in ids and not controlled:
                libsumo.vehicle.setSpeed("car", v0 if k < hold else -1.0)
            libsumo.simulationStep()
            if ctl is not None:
                ctl.step()
            if k in at and "car" in libsumo.vehicle.getIDList():
                got[at[k]] = libsumo.vehicle.getSpeed("car")
        return [got[s] for s in SAMPLE_AT_S]
    finally:
        libsumo.close()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("checkpoints", nargs="*", default=["r1sim-nano"])
    ap.add_argument("--v0", type=float, nargs="+", default=[5.0, 10.0, 15.0], help="steady start speeds [m/s]")
    ap.add_argument("--json", help="write the table here too")
    a = ap.parse_args(argv)
    ensure_sumo_home()
    drivers = {"native": None, **{c: r1sim_sumo.load_policy(c) for c in a.checkpoints}}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, (net, edges, lane) in probes().items():
            for v0 in a.v0:
                cfg = write_cfg(Path(tmp), net, edges, lane, v0)
                for who, pol in drivers.items():
                    v10, v30 = run(cfg, v0, pol)
                    rows.append({"probe": name, "v0_mps": v0, "driver": who, "speed_10s_mps": v10, "speed_30s_mps": v30})
                    print(f"{name:20s} v0 {v0:4.1f}  {who:40s} after 10 s {v10:5.1f}  after 30 s {v30:5.1f} m/s", flush=True)
    for who in drivers:
        mine = [r["speed_10s_mps"] for r in rows if r["driver"] == who]
        print(f"mean speed 10 s after a steady start, {who}: {sum(mine) / len(mine):.1f} m/s")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
