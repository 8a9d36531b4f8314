"""Where SUMO's game/ramp sample jams, native vs the policy's commands drive: standing vehicle-seconds per lane of the
merge area and arrivals per demand stream (highway / onramp / offramp), per 50 s of simulated time.

The ramp (eclipse-sumo ``tools/game/ramp``): the on-ramp ``gneE14`` joins the motorway on ``gneE7``'s lane 0, an
acceleration lane that ends after 110 m (lanes 1-2 continue as ``gneE8``); the off-ramp leaves ``gneE2``/``offramp``
further upstream. Same SUMO command and controller settings as ``examples/full_horizon_runs.py`` / ``r1sim simulate``.

    python scripts/diag_ramp_merge.py --drive native --seed 0
    python scripts/diag_ramp_merge.py --drive commands --seed 0 [--checkpoint CKPT] [--merge-cooperation on|off]
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter, defaultdict
from pathlib import Path

LANES = ("gneE2_0", "gneE2_1", "offramp_0", "offramp_1", "gneE3_0", "gneE3_1", "gneE18_0", "gneE13_0", "gneE14_0",
         "gneE7_0", "gneE7_1", "gneE7_2", "gneE8_0", "gneE8_1")
STAND_MPS = 0.5  # [m/s]
BIN_S = 50.0


def stream(vid: str) -> str:
    """The demand stream of a vehicle id (``highway2.17`` -> ``highway``)."""
    return vid.split(".")[0].rstrip("0123456789") or vid


def snapshot(conn, ctrl, t: float) -> None:
    """One line per vehicle on gneE14_0 / gneE7_0: position [m from the lane's start], speed, who drives it, SUMO's
    lane-change wish to the left (its own state, without TraCI requests) and the leader / follower on gneE7_1."""
    print(f"t = {t:.1f} s")
    for lane in ("gneE14_0", "gneE7_0"):
        for vid in conn.lane.getLastStepVehicleIDs(lane)[::-1]:  # front first
            rec = ctrl.vehicles.get(vid) if ctrl is not None else None
            who = "sumo" if rec is None else rec.state + (" route-merge" if rec.route_merge else "")
            lc = conn.vehicle.getLaneChangeState(vid, 1)[0]
            names = [n for bit, n in ((2, "left"), (8, "strategic"), (16, "cooperative"), (32, "speedgain"),
                                      (256, "urgent"), (512, "blk-leader"), (1024, "blk-follower"), (8192, "overlap"))
                     if lc & bit]  # SUMO's LaneChangeAction bits
            fol = conn.vehicle.getNeighbors(vid, 4)  # blocking followers on the left
            names.append("followers " + (",".join(f"{f}({'policy' if (r := ctrl.vehicles.get(f) if ctrl else None) is not None and r.state == 'controlled' else 'sumo'})" for f, _ in fol) or "-"))
            print(f"  {lane} {vid:12s} pos {conn.vehicle.getLanePosition(vid):6.1f} v {conn.vehicle.getSpeed(vid):5.2f}"
                  f" {who:28s} lc-left {','.join(names) or '-'}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drive", choices=("native", "commands"), default="commands")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--end", type=float, default=400.0)
    ap.add_argument("--checkpoint", default=None, help="policy (default: the shipped r1sim-nano)")
    ap.add_argument("--sampler", default=None, help="the policy's token sampler (default: the commands drive's own)")
    ap.add_argument("--merge-cooperation", choices=("on", "off"), default="on", help="the commands drive's yields (default on)")
    ap.add_argument("--snapshots", type=float, nargs="*", default=[], metavar="T",
                    help="[s] list the vehicles on the acceleration lane gneE7_0 (and gneE14_0) at these times")
    a = ap.parse_args(argv)

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
    from full_horizon_runs import scenario_sumocfg

    cfg = scenario_sumocfg("sumo-game-ramp")
    import libsumo as conn
    import torch

    from r1sim_sumo.sumo_launch import settle_remote_control, sumo_command

    torch.set_num_threads(1)
    conn.start(sumo_command(a.seed, sumocfg=cfg, end_s=a.end + 1.0))
    ctrl = None
    if a.drive == "commands":
        from r1sim_sumo.model.checkpoint import load_policy
        from r1sim_sumo.sim.sumo_controller import SumoController

        policy = load_policy(a.checkpoint) if a.checkpoint else load_policy()
        ctrl = SumoController(conn, policy, control="all", sampler=a.sampler, seed=a.seed, drive="commands",
                              standstill_handoff_s=5.0, merge_cooperation=a.merge_cooperation == "on")
    stand: dict[int, Counter] = defaultdict(Counter)  # bin -> lane -> standing vehicle-seconds
    merge_stand: Counter = Counter()  # bin -> standing vehicle-seconds on gneE7_0 while SUMO drives it (route merge)
    arrived: dict[int, Counter] = defaultdict(Counter)
    try:
        for k in range(int(round(a.end / 0.1))):
            conn.simulationStep()
            t = (k + 1) * 0.1
            b = int((t - 1e-9) // BIN_S)
            for vid in conn.simulation.getArrivedIDList():
                arrived[b][stream(vid)] += 1
            if ctrl is not None:
                ctrl.step()
            if any(abs(t - ts) < 0.05 for ts in a.snapshots):
                snapshot(conn, ctrl, t)
            for lane in LANES:
                for vid in conn.lane.getLastStepVehicleIDs(lane):
                    if conn.vehicle.getSpeed(vid) < STAND_MPS:
                        stand[b][lane] += 0.1
                        if lane == "gneE7_0" and ctrl is not None:
                            rec = ctrl.vehicles.get(vid)
                            if rec is not None and rec.route_merge:
                                merge_stand[b] += 0.1
    finally:
        settle_remote_control(conn)  # libsumo keeps pending moveToXY past close (r1sim_sumo.sumo_launch)
        conn.close()
    shown = [ln for ln in LANES if any(stand[b][ln] > 0 for b in stand)]
    print(f"game/ramp {a.drive} seed {a.seed}" + (f" checkpoint {a.checkpoint or 'r1sim-nano'}" if ctrl else ""))
    print("standing vehicle-seconds (< 0.5 m/s) per lane and 50 s" + ("; gneE7_0 (SUMO-driven route merges)" if ctrl else ""))
    print("| t [s] | " + " | ".join(shown) + " | arrivals: highway / onramp / offramp |")
    print("|---" * (len(shown) + 2) + "|")
    total = Counter()
    for b in range(int(a.end // BIN_S)):
        cells = []
        for ln in shown:
            c = f"{stand[b][ln]:.0f}"
            if ln == "gneE7_0" and ctrl is not None:
                c += f" ({merge_stand[b]:.0f})"
            cells.append(c)
        total.update(arrived[b])
        print(f"| {b * BIN_S:.0f}-{(b + 1) * BIN_S:.0f} | " + " | ".join(cells)
              + f" | {arrived[b]['highway']} / {arrived[b]['onramp']} / {arrived[b]['offramp']} |")
    print(f"arrivals: {sum(total.values())} (highway {total['highway']}, onramp {total['onramp']}, offramp {total['offramp']})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
