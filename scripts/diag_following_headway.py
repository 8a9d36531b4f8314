"""How closely vehicles follow in the drop-in vs under SUMO's own drivers: time headways of following vehicles.

Every 0.5 s of a run, every vehicle faster than ``--min-speed`` [m/s] with a leader within 100 m on its route
(``vehicle.getLeader``) gives one sample: gap = SUMO's leader distance + the follower's minGap [m] (back of the
leader to the front bumper of the follower), time headway = gap / speed [s]. "Steady" samples are those whose
speed is within 1.5 m/s of the leader's (car following, not closing in or falling back). A bottleneck's capacity is
about 1 / (time headway + length / speed) per lane: followers that keep 1.6 s where SUMO's keep 1.1 s carry ~30% less.

    python scripts/diag_following_headway.py --scenario sumo-game-ramp --drive native
    python scripts/diag_following_headway.py --scenario sumo-game-ramp --drive commands [--checkpoint CKPT]

Scenarios: bundled network names or sumo-game-ramp / sumo-game-cross / sumo-game-grid6 (eclipse-sumo's tools/game);
``--end`` simulated s (default: 300). Commands drive = the drop-in's defaults, ``--control all``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
from full_horizon_runs import scenario_sumocfg  # noqa: E402  (scenario name -> .sumocfg, as the full-horizon runs)

from r1sim_sumo.sim.free_road_speed import SAMPLE_EVERY_STEPS  # noqa: E402  (one sample per 0.5 s)


def start_run(scenario: str, drive: str, end_s: float, seed: int, checkpoint: str | None, guidance: float = 0.0,
              sampler: str | None = None):
    """``(libsumo, controller)``: the scenario started in this process's libsumo, and the drop-in controller with its
    defaults (``sampler`` None: the drive's own) and ``--control all`` (``None`` for ``drive='native'``)."""
    cfg = scenario_sumocfg(scenario)  # before libsumo is imported: importing it sets SUMO_HOME to its own data folder
    import libsumo
    import torch

    from r1sim_sumo.sumo_launch import sumo_command

    torch.set_num_threads(1)
    libsumo.start(sumo_command(seed, sumocfg=cfg, end_s=end_s + 1))
    if drive == "native":
        return libsumo, None
    from r1sim_sumo.model.checkpoint import load_policy
    from r1sim_sumo.sim.sumo_controller import SumoController

    return libsumo, SumoController(libsumo, load_policy(checkpoint or "r1sim-nano"), control="all", seed=seed,
                                   drive=drive, guidance=guidance, sampler=sampler)


def drop_in_parser(description: str) -> argparse.ArgumentParser:
    """The arguments every drop-in diagnostic here takes: scenario, drive, horizon, seed, checkpoint."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--scenario", default="sumo-game-ramp")
    ap.add_argument("--drive", choices=["native", "commands", "position"], default="commands")
    ap.add_argument("--end", type=float, default=300.0, help="simulated seconds")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--checkpoint", default=None, help="policy (default: the shipped r1sim-nano)")
    ap.add_argument("--sampler", default=None, help="the policy's token sampler (default: the drive's own, r1sim simulate --sampler)")
    return ap


def sampled_steps(libsumo, ctrl, end_s: float, every: int = SAMPLE_EVERY_STEPS):
    """Step the run to ``end_s`` [s] (SUMO, then the controller, every 0.1 s) and yield once every ``every`` steps
    (default :data:`SAMPLE_EVERY_STEPS`: 0.5 s), after the step; closes ``libsumo`` at the end."""
    from r1sim_sumo.sumo_launch import STEP_LENGTH_S

    try:
        for k in range(int(round(end_s / STEP_LENGTH_S))):
            libsumo.simulationStep()
            if ctrl is not None:
                ctrl.step()
            if k % every == every - 1:
                yield
    finally:
        from r1sim_sumo.sumo_launch import settle_remote_control

        settle_remote_control(libsumo)  # libsumo keeps pending moveToXY past close (r1sim_sumo.sumo_launch)
        libsumo.close()


def run(scenario: str, drive: str, end_s: float, seed: int, checkpoint: str | None, min_speed: float) -> dict:
    libsumo, ctrl = start_run(scenario, drive, end_s, seed, checkpoint)
    th, steady, speeds = [], [], []
    for _ in sampled_steps(libsumo, ctrl, end_s):
        for v in libsumo.vehicle.getIDList():
            s = libsumo.vehicle.getSpeed(v)
            if s < min_speed:
                continue
            lead = libsumo.vehicle.getLeader(v, 100.0)
            if not lead or not lead[0]:
                continue
            gap = lead[1] + libsumo.vehicle.getMinGap(v)
            th.append(gap / s)
            steady.append(abs(s - libsumo.vehicle.getSpeed(lead[0])) < 1.5)
            speeds.append(s)
    th, steady, speeds = np.asarray(th), np.asarray(steady, bool), np.asarray(speeds)
    out = {"scenario": scenario, "drive": drive, "samples": int(len(th)), "steady_samples": int(steady.sum())}
    for key, m in (("all", np.ones(len(th), bool)), ("steady", steady)):
        if m.any():
            q = np.percentile(th[m], [10, 25, 50, 75, 90])
            out[key] = {"p10": q[0], "p25": q[1], "median": q[2], "p75": q[3], "p90": q[4],
                        "share_below_1s": float((th[m] < 1.0).mean()), "share_above_2s": float((th[m] > 2.0).mean()),
                        "mean_speed_mps": float(speeds[m].mean())}
    return out


def main(argv=None) -> int:
    ap = drop_in_parser(__doc__.splitlines()[0])
    ap.add_argument("--min-speed", type=float, default=5.0)
    a = ap.parse_args(argv)
    r = run(a.scenario, a.drive, a.end, a.seed, a.checkpoint, a.min_speed)
    print(f"{r['scenario']} {r['drive']} ({a.checkpoint or 'r1sim-nano' if a.drive != 'native' else 'SUMO'}), "
          f"{a.end:g} s, seed {a.seed}: {r['samples']} following samples ({r['steady_samples']} steady)")
    for key in ("all", "steady"):
        if key in r:
            s = r[key]
            print(f"  {key:6s} time headway [s] p10 {s['p10']:.2f}  p25 {s['p25']:.2f}  median {s['median']:.2f}  "
                  f"p75 {s['p75']:.2f}  p90 {s['p90']:.2f};  < 1 s {s['share_below_1s']:.2f}, > 2 s "
                  f"{s['share_above_2s']:.2f};  mean speed {s['mean_speed_mps']:.1f} m/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
